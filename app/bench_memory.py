"""``vservo bench browsers``: what ``vservo serve`` keeps of the browsers that came and went.

``vservo serve`` runs as its own process on the simulated cell; light monitors (app/light_monitor.py:
WebSocket clients of the page that read everything it sends, as a browser's page does) connect in
batches, each batch until every monitor has the page's camera image, then leave. The serving
process's resident memory (``VmRSS``) is read after the first batch and after the last: a server
that forgets a browser that left grows by little more than the heap's noise between the two.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

from vservo.app.browser import ServeProcess
from vservo.app.light_monitor import LightMonitors
from vservo.app.roles import new_token

SETTLE_S = 2.0  # after a batch left, before the memory is read: the server's disconnects are done


def resident_mb(pid: int) -> float:
    """A process's resident memory (MB) from /proc."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise ValueError(f"/proc/{pid}/status has no VmRSS")


def bench_browsers(clients: int = 200, batch: int = 10, cell: str | None = None) -> dict[str, Any]:
    """``clients`` light monitors of a fresh ``vservo serve``, ``batch`` at a time; its memory after the first
    batch and after all of them."""
    batches = max(1, -(-clients // batch))
    rss: list[float] = []
    with tempfile.TemporaryDirectory(prefix="vservo-bench-browsers-") as data:
        with ServeProcess.start(Path(data), new_token(), cycle_period_s=0.05, cell=cell) as serve:
            pid = serve.process.pid
            started_mb = resident_mb(pid)
            for _ in range(batches):
                with LightMonitors(serve.url, batch):
                    pass
                time.sleep(SETTLE_S)
                rss.append(resident_mb(pid))
    return {
        "what": "vservo serve's resident memory (MB) after light monitors connected, received the page and left, "
        f"{batch} at a time",
        "clients": batches * batch,
        "rss_at_start_mb": round(started_mb, 1),
        f"rss_after_first_{batch}_mb": round(rss[0], 1),
        f"rss_after_{batches * batch}_mb": round(rss[-1], 1),
        "growth_mb": round(rss[-1] - rss[0], 1),
        "growth_per_client_kb": round(1024 * (rss[-1] - rss[0]) / max(1, (batches - 1) * batch), 1),
        "rss_after_each_batch_mb": [round(value, 1) for value in rss],
        "load_average": [round(v, 2) for v in os.getloadavg()],
        "cpu_count": os.cpu_count(),
    }
