"""Commissioning from the Calibrate tab, end to end: `vservo serve` on the shipped simulated
cell as a real process, headless Chromium as the operator's browser. Start commissioning,
wait for the verdicts, Apply through its confirmation; the controller then runs on the
commissioned file, which the page names. A screenshot of the tab goes to $VSERVO_ARTIFACTS
(default test-artifacts/). Chromium must be at /usr/bin/chromium: a missing browser fails
the test, it never skips it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from tests.chromium import chromium_or_fail, headless_chromium
from vservo.app.browser import (
    ServeProcess,
    dismiss_notifications,
    open_pages,
    take_control,
    wait_for_status,
)
from vservo.core.cell.config import load_cell

TOKEN = "e2e-commissioning-token"
ARTIFACTS = Path(os.environ.get("VSERVO_ARTIFACTS", Path(__file__).resolve().parents[2] / "test-artifacts"))


def test_commission_the_simulated_cell_from_the_calibrate_tab_and_apply(tmp_path):
    chromium_or_fail()
    data = tmp_path / "data"
    serve = ServeProcess.start(data, TOKEN)
    try:
        with headless_chromium() as browser:
            (page,) = open_pages(browser, serve.url, [(1600, 1100)])
            take_control(page, serve.token)
            page.get_by_role("tab", name="Calibrate").click()
            page.get_by_text("The controller runs on static/cell.toml").wait_for(timeout=30_000)
            page.get_by_role("button", name="Start commissioning").click()
            wait_for_status(page, r"Commissioning")
            page.get_by_text("tilted views (camera, hand-eye)").wait_for(timeout=30_000)
            assert page.get_by_role("button", name="Start commissioning").is_disabled()

            page.get_by_text("Acceptance check, the figure to sign off").wait_for(timeout=90_000)
            verdicts = page.locator("li").filter(has_text=re.compile(r"^(camera|hand-eye|laser|network \(nn\)): good$"))
            assert verdicts.count() == 4  # camera, hand-eye, laser, network, in plain words
            page.get_by_text("Engineering (calibration)").click()  # the residuals and measured values, folded
            residuals = page.locator("table").filter(has_text="residuals").get_by_role("row")
            residuals.nth(4).wait_for(timeout=30_000)  # the fold's content is drawn after the click
            assert residuals.count() == 5  # the header and a row per step
            page.get_by_text(re.compile(r"camera: fx \d+\.\d\d px, fy")).wait_for(timeout=5_000)
            page.get_by_text(re.compile(r"laser baseline d \d+\.\d\d mm, angle alpha")).wait_for(timeout=5_000)
            dismiss_notifications(page)
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "calibrate.png"))

            out = data / "cell-commissioned.toml"
            assert not out.exists()  # written on Apply, not before
            page.get_by_role("button", name="Apply", exact=True).click()
            page.get_by_text("and reload the controller's model from it?").wait_for(timeout=10_000)
            assert page.get_by_text(str(out)).count() >= 1  # the modal names the file
            page.get_by_role("button", name="Write and reload").click()
            page.get_by_text(re.compile(r"Applied: the controller's model is now .*cell-commissioned\.toml")).wait_for(
                timeout=60_000
            )
            wait_for_status(page, re.escape(f"the controller's model is now {out}"))
            assert page.get_by_role("button", name="Apply", exact=True).is_disabled()  # applied once
            assert load_cell(out).commissioning.nn_path.is_file()
    finally:
        code = serve.stop()
    assert code == 0
    log = serve.stderr()
    assert "Traceback" not in log and "unhandled exception" not in log, log[-3000:]
