"""``vservo bench ui``: how fast the camera image reaches the monitors, and whether watching
slows the controller.

The app runs as ``vservo serve`` does (the controller as its own process, the page served
by viser), on the simulated cell, and assembles the demo job with monitors connected. Two
kinds of monitor (``Monitors``):

- light: WebSocket clients that decode every message of the page but render nothing
  (app/light_monitor.py), in a process of their own, at 1, 5 and 20 clients, and first
  with none as the reference. The bench drives the runs through the controller's channel.
  Per run, while the servo runs: the frames per second each client receives, the CPU of
  the serving process (this one: viser, the display thread, the channel) and of the
  controller process, from /proc, in % of one core;
- chromium: 1 and then 5 headless Chromium pages; the first takes control and runs the
  assemblies from its buttons; every page counts its camera image's updates (a
  MutationObserver on the <img>'s src, with their times).

Both: frames per second = (frames - 1) / (last - first) over the servo; the controller's
loop rate = servo cycles per second over the run, from the state stream (iteration and
controller time of every cycle, as the session records them). Medians over runs (and
clients). The servo cycle is free-running by default (no floor), so the loop rate shows
what the machine gives; the app sends at most 30 frames a second.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from dataclasses import dataclass
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
from vservo.app.light_monitor import LIGHT_COUNTS, LightMonitors, Monitors
from vservo.app.roles import new_token
from vservo.app.server import IMAGE_PERIOD_S, RunningApp, ServeOptions, start_app
from vservo.core.cell.config import CellConfig, load_cell, write_thesis_policy_cell
from vservo.core.production.protocol import Command, Phase, PresentPart, Reset, Start

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
BROWSER_COUNTS = (1, 5)
CLOCK_TICKS_PER_S = os.sysconf("SC_CLK_TCK")


@dataclass(frozen=True)
class CpuSample:
    """The CPU time (user + system, s) a process has used, read from /proc at a monotonic time."""

    cpu_s: float
    at_s: float

    @classmethod
    def of(cls, pid: int) -> CpuSample:
        stat = Path(f"/proc/{pid}/stat").read_text()
        fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (name) ", the state is field 3
        return cls((int(fields[11]) + int(fields[12])) / CLOCK_TICKS_PER_S, time.monotonic())

    def percent_since(self, earlier: CpuSample) -> float:
        """The process's CPU between the two samples, in % of one core."""
        return 100.0 * (self.cpu_s - earlier.cpu_s) / (self.at_s - earlier.at_s)


def _fps(times_s: list[float]) -> float | None:
    if len(times_s) < 2 or times_s[-1] <= times_s[0]:
        return None
    return (len(times_s) - 1) / (times_s[-1] - times_s[0])


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 2)


def _median(values: list[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return round(statistics.median(present), 2) if present else None


def _cpu_medians(measured: list[dict[str, Any]]) -> dict[str, float | None]:
    return {f"{name}_cpu_pct_median": _median([m["cpu_pct"][name] for m in measured]) for name in measured[0]["cpu_pct"]}


def _watch_servo(running: RunningApp, pids: dict[str, int]) -> tuple[float, float, dict[str, float]]:
    """From the run's start until its servo ends: the servo's start and end (monotonic s) and the
    CPU of each process over it (% of one core)."""
    session = running.app.session
    deadline = time.monotonic() + RUN_TIMEOUT_S
    start = None
    while time.monotonic() < deadline:
        phase = session.state.phase
        if start is None and phase == Phase.SERVOING:
            start, before = time.monotonic(), {name: CpuSample.of(pid) for name, pid in pids.items()}
        if start is not None and phase != Phase.SERVOING:
            end = time.monotonic()
            return start, end, {name: round(CpuSample.of(pid).percent_since(before[name]), 1) for name, pid in pids.items()}
        time.sleep(0.02)
    raise TimeoutError("the assembly's servo did not end within the bench's time limit")


def _finish_run(running: RunningApp, deadline: float) -> dict[str, Any]:
    """After the servo: its loop rate and cycles, then wait for the pick and place to end."""
    session = running.app.session
    trace = session.view().trace
    while session.state.phase in (Phase.PICKING, Phase.PLACING) and time.monotonic() < deadline:
        time.sleep(0.05)
    return {
        "loop_hz": _rounded(trace.cycle_rate_hz()),
        "servo_cycles": int(len(trace.iterations)),
        "outcome": session.state.detail,
    }


# -- light monitors ----------------------------------------------------------------------------


def _call(running: RunningApp, command: Command) -> None:
    reply = running.channel.call(command)
    if not reply.ok:
        raise RuntimeError(f"the controller refused {command.command_name!r}: {reply.error}")


def _light_run(running: RunningApp, monitors: LightMonitors | None) -> dict[str, Any]:
    """One assembly driven through the channel, ``monitors`` (if any) watching."""
    if running.app.session.state.phase in (Phase.DONE, Phase.FAULT, Phase.ESTOPPED):
        _call(running, Reset())
    _call(running, PresentPart())
    _call(running, Start("demo"))
    deadline = time.monotonic() + RUN_TIMEOUT_S
    pids = {"serve": os.getpid(), "controller": running.controller.process.pid}
    if monitors is not None and monitors.process.pid is not None:
        pids["clients"] = monitors.process.pid
    start, end, cpu = _watch_servo(running, pids)
    frames = monitors.frames() if monitors is not None else []
    fps = [_fps([t for t in times if start <= t <= end]) for times in frames]
    return {"fps_per_client": [_rounded(f) for f in fps], "cpu_pct": cpu, **_finish_run(running, deadline)}


def _light(running: RunningApp, runs: int, counts: tuple[int, ...]) -> dict[str, Any]:
    """Per count, ``runs`` pairs of runs: one with no client (the reference), one with the clients.

    Paired, so that the load other programs put on the machine meanwhile falls on both sides
    of the comparison of the controller's loop rate alike."""
    results: dict[str, Any] = {}
    for count in counts:
        alone, watched = [], []
        for _ in range(runs):
            alone.append(_light_run(running, None))
            with LightMonitors(running.url, count) as monitors:
                watched.append(_light_run(running, monitors))
        fps = [f for m in watched for f in m["fps_per_client"] if f is not None]
        loop_hz, reference_hz = _median([m["loop_hz"] for m in watched]), _median([m["loop_hz"] for m in alone])
        results[str(count)] = {
            "fps_median": _median(fps),
            "fps_min": min(fps) if fps else None,
            "loop_hz_median": loop_hz,
            "loop_hz_no_clients_median": reference_hz,
            "loop_change_pct": None if loop_hz is None or not reference_hz else round(100.0 * (loop_hz / reference_hz - 1), 1),
            **_cpu_medians(watched),
            **{f"no_clients_{key}": value for key, value in _cpu_medians(alone).items()},
            "runs": watched,
            "runs_no_clients": alone,
        }
    return results


# -- Chromium pages ----------------------------------------------------------------------------


def _page_run(running: RunningApp, pages: list[Any]) -> dict[str, Any]:
    operator = pages[0]
    session = running.app.session
    if session.state.phase in (Phase.DONE, Phase.FAULT, Phase.ESTOPPED):
        operator.get_by_role("button", name="Reset (after e-stop, fault or a finished run)").click()
        wait_for_status(operator, r"Idle")
    operator.get_by_role("button", name="Present part", exact=True).click()
    wait_for_status(operator, r"a new part is on the table")
    for page in pages:
        page.evaluate(WATCH_IMAGE_TIMES)
    operator.get_by_role("button", name="Start", exact=True).click()
    deadline = time.monotonic() + RUN_TIMEOUT_S
    _, _, cpu = _watch_servo(running, {"serve": os.getpid(), "controller": running.controller.process.pid})
    fps = [_fps([t / 1000.0 for t in page.evaluate("window.__imageTimes")]) for page in pages]
    return {"fps_per_page": [_rounded(f) for f in fps], "cpu_pct": cpu, **_finish_run(running, deadline)}


def _chromium(running: RunningApp, token: str, runs: int, counts: tuple[int, ...]) -> dict[str, Any]:
    from playwright.sync_api import sync_playwright

    results: dict[str, Any] = {}
    with sync_playwright() as playwright:
        browser = launch_chromium(playwright)
        for count in counts:
            pages = open_pages(browser, running.url, [(1280, 800)] * count)
            take_control(pages[0], token)
            dismiss_notifications(pages[0])
            measured = [_page_run(running, pages) for _ in range(runs)]
            results[str(count)] = {
                "fps_median": _median([f for m in measured for f in m["fps_per_page"]]),
                "loop_hz_median": _median([m["loop_hz"] for m in measured]),
                **_cpu_medians(measured),
                "runs": measured,
            }
            for page in pages:
                page.context.close()
        browser.close()
    return results


def bench_ui(
    config: CellConfig,
    seed: int = 0,
    runs: int = 3,
    monitors: Monitors = Monitors.BOTH,
    light_counts: tuple[int, ...] = LIGHT_COUNTS,
    browser_counts: tuple[int, ...] = BROWSER_COUNTS,
    cycle_period_s: float = 0.0,
    cell: str | None = None,
) -> dict[str, Any]:
    if monitors != Monitors.LIGHT:
        require_chromium()
    result: dict[str, Any] = {
        "what": "camera frames per second reaching each monitor during the servo, the controller's servo cycles "
        "per second from the state stream, the processes' CPU in % of one core; medians over runs (and "
        "monitors)",
    }
    with tempfile.TemporaryDirectory(prefix="vservo-bench-ui-") as data:
        if cell is None:  # the shipped fast policy's servo is over in a handful of cycles: too few to watch
            cell = str(write_thesis_policy_cell(Path(data)))
            config = load_cell(cell)
            result["cell"] = "the shipped cell on the thesis's step policy"
        options = ServeOptions(
            port=free_port(), data=Path(data), seed=seed, token=new_token(), cycle_period_s=cycle_period_s, cell=cell
        )
        running = start_app(options, config)
        try:
            if monitors != Monitors.CHROMIUM:
                result["light_clients"] = _light(running, runs, light_counts)
            if monitors != Monitors.LIGHT:
                result["browsers"] = _chromium(running, options.token, runs, browser_counts)
        finally:
            running.close()
    return {
        **result,
        "runs_per_setting": runs,
        "cycle_period_s": cycle_period_s,
        "app_image_cap_fps": round(1.0 / IMAGE_PERIOD_S, 1),
        "load_average": [round(v, 2) for v in os.getloadavg()],
        "cpu_count": os.cpu_count(),
    }
