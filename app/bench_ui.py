"""``vservo bench ui``: how fast the camera image reaches the browsers, and whether watching
slows the controller.

The app runs as ``vservo serve`` does (the controller as its own process, the page served
by viser), on the simulated cell, with 1 and then 5 headless Chromium pages connected.
The first page takes control and runs assemblies of the demo job from its buttons. Per run:

- frames per second reaching each browser, while the servo runs: every page counts its
  camera image's updates (a MutationObserver on the <img>'s src, with their times),
  rate = (updates - 1) / (last - first);
- the controller's loop rate: servo cycles per second over the run, from the state stream
  (iteration and controller time of every cycle, as the session records them).

Medians over runs (and pages). The servo cycle is free-running by default (no floor), so the
loop rate shows what the machine gives; the app sends at most 30 frames a second.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from vservo.app.browser import (
    dismiss_notifications,
    free_port,
    launch_chromium,
    open_pages,
    require_chromium,
    take_control,
    wait_for_status,
)
from vservo.app.roles import new_token
from vservo.app.server import IMAGE_PERIOD_S, RunningApp, ServeOptions, start_app
from vservo.core.cell.config import CellConfig
from vservo.core.production.assembly import Phase

WATCH_IMAGE_TIMES = """() => {
    window.__imageTimes = [];
    if (window.__watching) { return; }
    window.__watching = true;
    new MutationObserver((records) => {
        for (const record of records) {
            if (record.target.tagName === 'IMG') { window.__imageTimes.push(performance.now()); }
        }
    }).observe(document.body, {subtree: true, attributes: true, attributeFilter: ['src']});
}"""
RUN_TIMEOUT_S = 180.0


def _fps(times_ms: list[float]) -> float | None:
    if len(times_ms) < 2 or times_ms[-1] <= times_ms[0]:
        return None
    return (len(times_ms) - 1) / ((times_ms[-1] - times_ms[0]) / 1000.0)


def _one_run(running: RunningApp, pages: list[Any]) -> dict[str, Any]:
    operator = pages[0]
    session = running.app.session
    if session.state.get("phase") in (Phase.DONE, Phase.FAULT, Phase.ESTOPPED):
        operator.get_by_role("button", name="Reset (after e-stop, fault or a finished run)").click()
        wait_for_status(operator, r"Idle")
    operator.get_by_role("button", name="Present part", exact=True).click()
    wait_for_status(operator, r"a new part is on the table")
    for page in pages:
        page.evaluate(WATCH_IMAGE_TIMES)
    operator.get_by_role("button", name="Start", exact=True).click()
    deadline = time.monotonic() + RUN_TIMEOUT_S
    servo_seen = False
    while time.monotonic() < deadline:
        phase = session.state.get("phase")
        servo_seen = servo_seen or phase == Phase.SERVOING
        if servo_seen and phase != Phase.SERVOING:
            break  # the servo is over: the frames stop until the run ends
        time.sleep(0.02)
    else:
        raise TimeoutError("the assembly's servo did not end within the bench's time limit")
    fps = [_fps(page.evaluate("window.__imageTimes")) for page in pages]
    trace = session.view().trace
    while session.state.get("phase") in (Phase.PICKING, Phase.PLACING) and time.monotonic() < deadline:
        time.sleep(0.05)
    return {"fps_per_page": [None if f is None else round(f, 2) for f in fps],
            "loop_hz": None if trace.cycle_rate_hz() is None else round(trace.cycle_rate_hz(), 2),
            "servo_cycles": int(len(trace.iterations)), "outcome": session.state.get("detail")}


def _median(values: list[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return round(statistics.median(present), 2) if present else None


def bench_ui(config: CellConfig, seed: int = 0, runs: int = 3, browser_counts: tuple[int, ...] = (1, 5),
             cycle_period_s: float = 0.0, cell: str | None = None) -> dict[str, Any]:
    from playwright.sync_api import sync_playwright

    require_chromium()
    with tempfile.TemporaryDirectory(prefix="vservo-bench-ui-") as data:
        options = ServeOptions(port=free_port(), data=Path(data), seed=seed, token=new_token(),
                               cycle_period_s=cycle_period_s, cell=cell)
        running = start_app(options, config)
        results: dict[str, Any] = {}
        try:
            with sync_playwright() as playwright:
                browser = launch_chromium(playwright)
                for count in browser_counts:
                    pages = open_pages(browser, running.url, [(1280, 800)] * count)
                    take_control(pages[0], options.token)
                    dismiss_notifications(pages[0])
                    measured = [_one_run(running, pages) for _ in range(runs)]
                    results[str(count)] = {
                        "fps_median": _median([f for m in measured for f in m["fps_per_page"]]),
                        "loop_hz_median": _median([m["loop_hz"] for m in measured]),
                        "runs": measured,
                    }
                    for page in pages:
                        page.context.close()
                browser.close()
        finally:
            running.close()
    return {
        "what": "camera frames per second reaching each browser during the servo, and the controller's servo "
                "cycles per second from the state stream; medians over runs and pages",
        "browsers": results,
        "runs_per_setting": runs,
        "cycle_period_s": cycle_period_s,
        "app_image_cap_fps": round(1.0 / IMAGE_PERIOD_S, 1),
        "load_average": [round(v, 2) for v in os.getloadavg()],
        "cpu_count": os.cpu_count(),
    }
