"""The README's screenshot: the assemble view in the middle of a run on the simulated cell.

    python -m vservo.app.screenshot [static/screenshots/assemble.png]

Starts the app (as ``vservo serve`` does, on a free port and a scratch data folder),
opens it in headless Chromium, takes control, presents a part, starts the demo job and
saves the page when the servo is well under way: on the thesis's step policy, whose servo
lasts a few hundred cycles (the shipped fast policy's, a handful, would leave nothing to see).
"""

from __future__ import annotations

import sys
import tempfile
from dataclasses import replace
from pathlib import Path

from vservo.app.browser import dismiss_notifications, free_port, launch_chromium, open_pages, take_control, wait_for_status
from vservo.app.roles import new_token
from vservo.app.server import ServeOptions, start_app
from vservo.core.cell.config import load_cell, write_thesis_policy_cell

DEFAULT = Path("static/screenshots/assemble.png")


def take_screenshot(path: Path, seed: int = 0) -> Path:
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(prefix="vservo-screenshot-") as data:
        options = ServeOptions(port=free_port(), data=Path(data), seed=seed, token=new_token(), cycle_period_s=0.05)
        cell = write_thesis_policy_cell(Path(data))
        running = start_app(replace(options, cell=str(cell)), load_cell(cell))
        try:
            with sync_playwright() as playwright:
                browser = launch_chromium(playwright)
                (page,) = open_pages(browser, running.url, [(1600, 1000)])
                take_control(page, options.token)
                page.get_by_role("button", name="Present part", exact=True).click()
                wait_for_status(page, r"a new part is on the table")
                page.get_by_role("button", name="Start", exact=True).click()
                wait_for_status(page, r"Servoing .*cycle (1[2-9]\d)", timeout_s=120)
                dismiss_notifications(page)
                path.parent.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(path))
                browser.close()
        finally:
            running.close()
    return path


if __name__ == "__main__":
    print(f"wrote {take_screenshot(Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT)}")
