"""The operator app on the virtual cell, end to end: `vservo virtual-cell` and `vservo serve
--cell <its cell file>` as real processes, headless Chromium as the operator's browser.

The controller behind the page drives the virtual cell as it would a real one (the JRC on
a pseudo-terminal, the camera stream, the cup on the JRC's I/O, parts from the fixture);
the test reads the virtual cell's gauge to check each released part. The operator
presents a part and assembles it, presses E-STOP in the middle of the next run, resets,
and assembles again.
"""

from __future__ import annotations

import re
import time

import pytest

from tests.chromium import chromium_or_fail
from tests.jrc_fixtures import thesis_policy_cell_file
from tests.virtual_cell_process import VirtualCellProcess
from vservo.app.browser import (
    ServeProcess,
    choose,
    cycle_of,
    open_pages,
    present_part_and_start,
    status_text,
    take_control,
    wait_for_status,
)

TOKEN = "e2e-virtual-cell-token"
RUN_TIMEOUT_S = 300


@pytest.fixture(scope="module")
def virtual_cell(tmp_path_factory):
    # The thesis's step policy: a servo long enough to press E-STOP in its middle.
    cell = VirtualCellProcess("--seed", "4", "--cell", thesis_policy_cell_file(tmp_path_factory.mktemp("cell")))
    yield cell
    assert cell.stop() == 0, cell.log()[-2000:]


@pytest.fixture(scope="module")
def app(virtual_cell, tmp_path_factory):
    chromium_or_fail()
    with ServeProcess.start(
        tmp_path_factory.mktemp("serve-data"), TOKEN, cycle_period_s=0.0, cell=virtual_cell.addresses["cell_file"]
    ) as serve:
        yield serve


@pytest.fixture(scope="module")
def operator(app, chromium):
    page = open_pages(chromium, app.url, [(1400, 900)])[0]
    take_control(page, app.token)
    page.get_by_role("tab", name="Assemble").click()
    choose(page, "Job", "demo")
    return page


def _assemble(page, virtual_cell) -> None:
    run = present_part_and_start(page)
    done = wait_for_status(page, rf"Done .*run {run}", timeout_s=RUN_TIMEOUT_S)
    seen = re.search(r"part seen (\d+\.\d+) mm from its taught place", done)
    assert seen, done
    released = virtual_cell.next_event()
    assert released["event"] == "released" and released["inside"], released
    assert abs(float(seen.group(1)) - released["placement_error_mm"]) <= 0.1, (done, released)
    page.get_by_text(f"Run {run}: placed").wait_for(timeout=10_000)


def test_present_assemble_estop_reset_and_assemble_again_on_the_virtual_cell(app, virtual_cell, operator):
    _assemble(operator, virtual_cell)

    run = present_part_and_start(operator)
    wait_for_status(operator, rf"Servoing .*run {run}.*cycle ([2-9]\d|\d{{3}})", timeout_s=60)
    operator.get_by_role("button", name="E-STOP", exact=True).click()
    stopped = wait_for_status(operator, r"E-STOPPED", timeout_s=10)
    time.sleep(1.0)
    settled = status_text(operator)
    time.sleep(1.0)
    assert cycle_of(status_text(operator)) == cycle_of(settled) and cycle_of(settled) - cycle_of(stopped) <= 1
    operator.get_by_role("button", name=re.compile("^Reset")).click()
    wait_for_status(operator, r"Idle")

    _assemble(operator, virtual_cell)


def test_the_app_on_the_virtual_cell_stops_cleanly(app):
    assert app.stop() == 0
    log = app.stderr()
    assert "Traceback" not in log and "unhandled exception" not in log, log[-3000:]
