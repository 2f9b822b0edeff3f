"""A virtual cell whose gauge a browser test reads, and the operator's page served on it:
shared by the tests that teach by the guide on a virtual cell and assemble what they taught."""

from __future__ import annotations

import json
import queue
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from tests.chromium import chromium_or_fail
from tests.virtual_cell_process import VirtualCellProcess
from vservo.app.browser import ServeProcess, open_pages, take_control

GAUGE_MM = 0.3  # a part placed: inside the pocket, this close to its centre by the gauge


class Gauge:
    """The virtual cell's lines (one per released part) read as they come, by a thread: a
    select() on its buffered stdout would miss lines already read into the buffer."""

    def __init__(self, cell: VirtualCellProcess) -> None:
        self.lines: queue.Queue[dict] = queue.Queue()
        self._thread = threading.Thread(target=self._read, args=(cell,), daemon=True)
        self._thread.start()

    def _read(self, cell: VirtualCellProcess) -> None:
        for line in cell.process.stdout:
            self.lines.put(json.loads(line))

    def releases(self, wait_s: float) -> list[dict]:
        """The parts the cup let go of since the last call, waiting ``wait_s`` for the first."""
        events = []
        try:
            events.append(self.lines.get(timeout=wait_s))
            while True:
                events.append(self.lines.get(timeout=1.0))
        except queue.Empty:
            pass
        return [event for event in events if event.get("event") == "released"]


@contextmanager
def gauged_virtual_cell(*arguments: str) -> Iterator[tuple[VirtualCellProcess, Gauge]]:
    """`vservo virtual-cell *arguments` and its gauge; the cell must stop cleanly."""
    cell = VirtualCellProcess(*arguments)
    gauge = Gauge(cell)
    yield cell, gauge
    assert cell.stop() == 0, cell.log()[-2000:]


@contextmanager
def operator_page_on(cell: VirtualCellProcess, data: Path, chromium, token: str) -> Iterator:
    """`vservo serve` on the cell file ``cell`` printed, one page (1600 x 1000) holding control;
    serve must stop cleanly, with no traceback on its standard error. The page's browser
    context is closed after: left open, a page of a stopped server keeps reconnecting and
    slows the pages the worker's later tests open in the same Chromium."""
    chromium_or_fail()
    with ServeProcess.start(data, token, cycle_period_s=0.0, cell=cell.addresses["cell_file"]) as serve:
        operator = open_pages(chromium, serve.url, [(1600, 1000)])[0]
        try:
            take_control(operator, token)
            yield operator
        finally:
            operator.context.close()
        assert serve.stop() == 0
        assert "Traceback" not in serve.stderr(), serve.stderr()[-3000:]
