"""The controller process killed in the middle of a run, from the operator's browser.

`vservo virtual-cell` and `vservo serve` on its cell file as real processes, headless Chromium
as the operator. The controller (the serving process's child) is killed with SIGKILL while the
arm servos: the app sees its channel end at once, and the banner says the controller stopped
and, in plain words, that vservo does not hold the robot and to use the pendant's e-stop if it moves. `vservo serve` starts a
new controller, which marks the killed run interrupted; the page shows it in the History and
the next run starts from the same page, without reloading it.
"""

from __future__ import annotations

import os
import re
import signal
import time
from datetime import datetime
from pathlib import Path

from tests.chromium import chromium_or_fail, headless_chromium
from tests.virtual_cell_process import VirtualCellProcess, long_servo_cell_args
from vservo.app.browser import (
    ServeProcess,
    banner,
    operator_on_assemble,
    present_part_and_start,
    servo_then_estop,
    wait_for_banner,
    wait_for_status,
)

TOKEN = "e2e-dead-controller-token"
SEEN_WITHIN_S = 1.0  # by `vservo serve`, from its log's time (0.05 s measured)
SHOWN_WITHIN_S = 5.0  # on the page, as the test's polling of a loaded Chromium sees it (1.1 s measured at a load of 13)


def _logged_at(log: str, words: str) -> float:
    """The time (s since the epoch) of the first line of ``log`` that says ``words``."""
    line = next(line for line in log.splitlines() if words in line)
    stamp = datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f")  # logging's asctime, local time
    return stamp.timestamp()


def _wait_for_the_new_controller(page) -> None:
    """The same page on a new controller: READY; or, when the kill cut a host command in two and the
    new controller's first exchange held the robot, FAULT saying the robot is held since before it
    started, which Reset releases (as after any hold it finds)."""
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        kind, words, _ = banner(page)
        if kind == "ready":
            return
        if kind == "fault" and "since before this controller started" in words:
            page.get_by_role("button", name=re.compile("^Reset")).click()
            wait_for_banner(page, "ready", "READY", timeout_s=30)
            return
        time.sleep(0.1)
    raise AssertionError(f"no new controller within 90 s; the banner: {banner(page)!r}")


def _children(pid: int) -> list[int]:
    return [int(child) for child in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def test_a_killed_controller_is_shown_within_2_s_and_a_new_one_marks_the_run_interrupted(tmp_path):
    chromium_or_fail()
    cell = VirtualCellProcess(*long_servo_cell_args(tmp_path))  # a servo long enough to kill the controller in
    serve = ServeProcess.start(tmp_path / "data", TOKEN, cycle_period_s=0.0, cell=cell.addresses["cell_file"])
    try:
        with headless_chromium() as chromium:
            page = operator_on_assemble(chromium, serve.url, serve.token)
            run = present_part_and_start(page)
            wait_for_status(page, rf"Servoing .*run {run}.*cycle [2-9]", timeout_s=60)

            (controller,) = _children(serve.process.pid)
            os.kill(controller, signal.SIGKILL)
            killed_at, killed_wall = time.monotonic(), time.time()
            words = wait_for_banner(page, "fault", "CONTROLLER STOPPED", timeout_s=30)
            shown_after_s = time.monotonic() - killed_at
            seen_after_s = _logged_at(serve.stderr(), "the controller process stopped") - killed_wall
            print(f"the app saw the controller gone {seen_after_s:.2f} s after the kill, the page {shown_after_s:.2f} s")
            assert seen_after_s < SEEN_WITHIN_S, seen_after_s
            assert shown_after_s < SHOWN_WITHIN_S, (shown_after_s, words)
            assert "not held by vservo" in words and "pendant's e-stop" in words, words
            assert "killed by signal 9" in words, words

            _wait_for_the_new_controller(page)
            (new_controller,) = _children(serve.process.pid)
            assert new_controller != controller
            page.get_by_role("tab", name="History").click()
            row = page.locator("tr", has_text="INTERRUPTED").first
            row.wait_for(timeout=30_000)
            assert row.locator("td").first.inner_text().strip() == str(run), row.inner_text()

            page.get_by_role("tab", name="Assemble").click()
            assert servo_then_estop(page) == run + 1
    finally:
        assert serve.stop() == 0, serve.stderr()[-3000:]
        cell.stop()
    assert "Traceback" not in serve.stderr(), serve.stderr()[-3000:]
