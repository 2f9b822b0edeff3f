"""Runs you can watch: `vservo serve` on the simulated cell, with the shipped settings, runs a
demo assembly at the real cell's pace, and its RUNNING banner stays on the page for seconds.

`vservo serve` as a real process with no pace option (the shipped default, --time-scale 1)
and the shipped servo cycle floor, headless Chromium as the operator's browser. The demo
run takes some 10 s of cell time (start pose, servo, pick, place, check); its banner is
read every 0.1 s from the moment it says RUNNING until it says anything else. Chromium
must be at /usr/bin/chromium: a missing browser fails the test, it never skips it.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from tests.chromium import chromium_or_fail, headless_chromium
from vservo.app.browser import ServeProcess, banner, open_pages, take_control, wait_for_banner, wait_for_status

TOKEN = "e2e-pace-token"
ARTIFACTS = Path(os.environ.get("VSERVO_ARTIFACTS", Path(__file__).resolve().parents[2] / "test-artifacts"))
SHIPPED_CYCLE_PERIOD_S = 0.05  # `vservo serve --cycle-period`'s default
WATCHABLE_S = 5.0  # the bar: long enough to watch the stages and reach the E-STOP


def test_the_running_banner_of_a_demo_run_stays_on_the_page_for_seconds_at_the_shipped_pace(tmp_path):
    chromium_or_fail()  # before `vservo serve` starts
    with ServeProcess.start(tmp_path / "data", TOKEN, cycle_period_s=SHIPPED_CYCLE_PERIOD_S, time_scale=None) as serve:
        with headless_chromium() as chromium:
            (page,) = open_pages(chromium, serve.url, [(1600, 1000)])
            take_control(page, TOKEN)
            page.get_by_role("button", name="Present part", exact=True).click()
            wait_for_status(page, r"a new part is on the table")
            page.get_by_role("button", name="Start", exact=True).click()
            wait_for_banner(page, "busy", r"RUNNING job demo", timeout_s=30)
            seen_from = time.monotonic()
            while "RUNNING" in (shown := banner(page))[1] and time.monotonic() - seen_from < 120:
                time.sleep(0.1)
            on_page_s = time.monotonic() - seen_from
            assert shown[0] == "placed", shown  # the run ended, placed: not a fault that cut it short
            assert on_page_s >= WATCHABLE_S, on_page_s
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            (ARTIFACTS / "pace.txt").write_text(f"the RUNNING banner of a demo run was on the page {on_page_s:.1f} s\n")
        assert serve.stop() == 0
        assert "Traceback" not in serve.stderr(), serve.stderr()[-3000:]
