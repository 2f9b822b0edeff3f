"""The operator app end to end: `vservo serve` as a real process, headless Chromium as the browsers.

(a) An operator teaches a job through the browser and assembles it while a second browser
    watches the same run and cannot start one (its Start is disabled, and a click forced
    past the disabled button is refused by the app).
(b) E-stop pressed mid-run (from the monitor: stopping is everyone's) stops the arm within
    one servo cycle: the cycle count and the flange pose shown in every page stop there.
Screenshots of the teach and assemble views go to $VSERVO_ARTIFACTS (default
test-artifacts/, not versioned). Chromium must be at /usr/bin/chromium: a missing browser
fails the tests, it never skips them.
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import numpy as np
import pytest

from tests.chromium import chromium_or_fail
from tests.jrc_fixtures import thesis_policy_cell_file
from vservo.app.browser import (
    ServeProcess,
    choose,
    count_image_updates,
    cycle_of,
    dismiss_notifications,
    flange_of,
    image_updates,
    open_pages,
    status_text,
    take_control,
    type_into,
    wait_for_status,
)

TOKEN = "e2e-operator-token"
ARTIFACTS = Path(os.environ.get("VSERVO_ARTIFACTS", Path(__file__).resolve().parents[2] / "test-artifacts"))
# Calls a button's React click handler directly, as a client that ignores the disabled state would.
FORCE_REACT_CLICK = """(button) => {
    const props = button[Object.keys(button).find((key) => key.startsWith('__reactProps'))];
    props.onClick({button: 0, preventDefault() {}, stopPropagation() {}});
}"""


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    chromium_or_fail()
    # The thesis's step policy: servos long enough to watch and to press E-STOP in.
    with ServeProcess.start(
        tmp_path_factory.mktemp("serve-data"),
        TOKEN,
        cycle_period_s=0.02,
        cell=thesis_policy_cell_file(tmp_path_factory.mktemp("cell")),
    ) as serve:
        yield serve


@pytest.fixture(scope="module")
def pages(app, chromium):
    """The operator's page (large, for the screenshots) and a monitor's, each its own browser context."""
    operator, monitor = open_pages(chromium, app.url, [(1600, 1000), (1400, 900)])
    return operator, monitor


@pytest.fixture(scope="module")
def artifacts():
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS


def _wait_flange(page, check, what: str, timeout_s: float = 30.0) -> tuple[float, ...]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        pose = flange_of(status_text(page))
        if check(np.array(pose)):
            return pose
        time.sleep(0.1)
    raise AssertionError(f"the flange never {what}; last {status_text(page)!r}")


def test_teach_a_job_and_assemble_it_while_a_monitor_watches(app, pages, artifacts):
    operator, monitor = pages
    take_control(operator, app.token)
    monitor.get_by_text("another browser holds control").wait_for(timeout=30_000)

    # Teach, from the demo job's poses: go to its desired view, jog, capture, a new start pose, save.
    operator.get_by_role("tab", name="Teach").click()
    choose(operator, "Template", "demo")
    operator.get_by_role("button", name="Begin teaching").click()
    wait_for_status(operator, r"Teaching")
    home = np.array(flange_of(status_text(operator)))
    operator.get_by_role("button", name="Go to the template's desired view", exact=True).click()
    view = np.array(_wait_flange(operator, lambda p: np.abs(p - home).max() > 1.0, "left home"))
    choose(operator, "Step", "5 mm / 2 deg")
    operator.get_by_role("button", name="+Z", exact=True).click()
    _wait_flange(operator, lambda p: abs(p[2] - (view[2] + 5.0)) < 0.02, "rose 5 mm")
    operator.get_by_role("button", name="-Z", exact=True).click()
    _wait_flange(operator, lambda p: np.abs(p[:3] - view[:3]).max() < 0.02, "came back down")
    operator.get_by_role("button", name="Capture desired image").click()
    wait_for_status(operator, r"desired image captured, laser depth")
    operator.get_by_role("button", name="+X", exact=True).click()
    _wait_flange(operator, lambda p: abs(p[0] - (view[0] + 5.0)) < 0.02, "moved 5 mm along X")
    operator.get_by_role("button", name="Set start pose here").click()
    wait_for_status(operator, r"start pose set here")
    operator.get_by_role("button", name="Apply settings").click()
    wait_for_status(operator, r"settings changed")
    operator.get_by_text("Everything is taught").wait_for(timeout=10_000)
    dismiss_notifications(operator)
    operator.screenshot(path=str(artifacts / "teach.png"))
    type_into(operator, "Job name", "e2e-job")
    operator.get_by_role("button", name="Save job").click()
    wait_for_status(operator, r"job 'e2e-job' saved")

    # Assemble it; the monitor watches the same run.
    operator.get_by_role("tab", name="Assemble").click()
    choose(operator, "Job", "e2e-job")
    count_image_updates(monitor)
    operator.get_by_role("button", name="Present part", exact=True).click()
    wait_for_status(operator, r"a new part is on the table")
    operator.get_by_role("button", name="Start", exact=True).click()
    running = wait_for_status(operator, r"Servoing .*run (\d+).*cycle [1-9]")
    run = int(re.search(r"run (\d+)", running).group(1))
    wait_for_status(monitor, rf"(Servoing|Picking|Placing|Done) .*job e2e-job.*run {run}")
    dismiss_notifications(operator)
    operator.screenshot(path=str(artifacts / "assemble.png"))
    assert monitor.get_by_role("button", name="Start", exact=True).is_disabled()

    done = wait_for_status(operator, r"Done", timeout_s=120)
    watched = wait_for_status(monitor, r"Done", timeout_s=30)
    assert f"run {run}" in done and f"run {run}" in watched
    assert "part in the metal part" in done and "part in the metal part" in watched
    operator.get_by_text(f"Run {run}: placed").wait_for(timeout=10_000)
    monitor.get_by_text(f"Run {run}: placed").wait_for(timeout=10_000)
    assert image_updates(monitor) > 20  # the monitor saw the run's frames

    # The monitor cannot start a run: not with a click, not with a click forced past the disabled button.
    start = monitor.get_by_role("button", name="Start", exact=True)
    start.click(force=True)
    start.evaluate(FORCE_REACT_CLICK)
    monitor.get_by_text("this browser is a read-only monitor").first.wait_for(timeout=10_000)
    time.sleep(2.0)
    after = status_text(operator)
    assert "Done" in after and f"run {run}" in after  # no new run was started


def test_estop_mid_run_stops_the_arm_within_one_cycle(app, pages):
    operator, monitor = pages
    if operator.get_by_text("this browser holds control").count() == 0:
        take_control(operator, app.token)
    operator.get_by_role("tab", name="Assemble").click()
    if re.search(r"Done|FAULT|E-STOPPED", status_text(operator)):
        operator.get_by_role("button", name=re.compile("^Reset")).click()
        wait_for_status(operator, r"Idle")
    choose(operator, "Job", "demo")
    operator.get_by_role("button", name="Present part", exact=True).click()
    wait_for_status(operator, r"a new part is on the table")
    operator.get_by_role("button", name="Start", exact=True).click()
    wait_for_status(operator, r"Servoing .*cycle ([2-9]\d|\d{3})")

    monitor.get_by_role("button", name="E-STOP", exact=True).click()  # every browser may stop the cell
    stopped = wait_for_status(monitor, r"E-STOPPED", timeout_s=10)
    cycle_stopped, pose_stopped = cycle_of(stopped), np.array(flange_of(stopped))
    time.sleep(1.0)  # 50 servo cycles at the test's 20 ms cycle, had the arm gone on
    settled = status_text(monitor)
    time.sleep(1.0)
    later = status_text(monitor)
    assert cycle_of(settled) - cycle_stopped <= 1, (stopped, settled)
    assert cycle_of(later) == cycle_of(settled), (settled, later)
    assert flange_of(later) == flange_of(settled)
    moved = np.abs(np.array(flange_of(settled)) - pose_stopped)
    assert moved[:3].max() < 5.0 and moved[3:].max() < 2.0, (stopped, settled)  # at most one servo step more
    assert "e-stop pressed" in later

    operator.get_by_role("tab", name="History").click()
    operator.get_by_role("cell", name="E-STOPPED").first.wait_for(timeout=30_000)
    operator.get_by_role("button", name=re.compile("^Reset")).click()
    wait_for_status(operator, r"Idle")


def test_the_app_stops_cleanly_and_no_thread_failed(app):
    assert app.stop() == 0
    log = app.stderr()
    assert "Traceback" not in log and "unhandled exception" not in log, log[-3000:]
