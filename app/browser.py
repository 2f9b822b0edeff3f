"""Driving the app with headless Chromium: for its end-to-end tests, `vservo bench ui` and
the README screenshot.

``ServeProcess`` runs ``vservo serve`` as a real process on a free port and stops it with
SIGTERM; ``launch_chromium`` starts the system's Chromium (/usr/bin/chromium) through
Playwright with the flags that work headless as root (docs/architecture.md, "Tests"); the page
helpers find viser's elements by their labels and read the status line.
"""

from __future__ import annotations

import os
import re
import select
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vservo.app.roles import TOKEN_ENVIRONMENT
from vservo.core.errors import VservoError

CHROMIUM = Path(os.environ.get("VSERVO_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
)
URL_LINE = re.compile(r"vservo serve: (http://\S+)")
STATUS_CYCLE = re.compile(r"cycle (\d+)")
STATUS_FLANGE = re.compile(
    r"flange X (-?[\d.]+) Y (-?[\d.]+) Z (-?[\d.]+) mm, phi (-?[\d.]+) theta (-?[\d.]+) "
    r"psi (-?[\d.]+) deg"
)
# Counts the camera image's updates in a page: viser swaps the <img>'s blob URL per frame.
COUNT_IMAGE_UPDATES = """() => {
    window.__imageUpdates = 0;
    new MutationObserver((records) => {
        for (const record of records) { if (record.target.tagName === 'IMG') { window.__imageUpdates += 1; } }
    }).observe(document.body, {subtree: true, attributes: true, attributeFilter: ['src']});
}"""


class ChromiumMissing(VservoError, RuntimeError):
    """No Chromium where the browser tests and the UI bench need it."""


def require_chromium() -> Path:
    if not CHROMIUM.is_file():
        raise ChromiumMissing(
            f"Chromium is not installed at {CHROMIUM}: install it with "
            "`apt-get update && apt-get install -y chromium` (tests/install.sh does) or set VSERVO_CHROMIUM"
        )
    return CHROMIUM


def launch_chromium(playwright: Any) -> Any:
    """Headless Chromium; Playwright gives every launch a fresh temporary profile (user data folder)."""
    return playwright.chromium.launch(executable_path=str(require_chromium()), args=list(CHROMIUM_FLAGS))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class ServeProcess:
    """``vservo serve`` in its own process: its URL and token, and its standard error in a file."""

    process: subprocess.Popen
    url: str
    token: str
    stderr_path: Path

    @classmethod
    def start(
        cls,
        data: Path,
        token: str,
        *,
        cycle_period_s: float = 0.02,
        time_scale: float | None = 0.0,
        seed: int = 3,
        timeout_s: float = 120.0,
        cell: str | None = None,
        python_options: tuple[str, ...] = (),
    ) -> ServeProcess:
        """``python_options``: the interpreter's own (``-X importtime``: its imports on standard error);
        ``time_scale``: the simulated cell's pace (0, as tests run it: as fast as it computes; None:
        the shipped default, the real cell's)."""
        stderr_path = Path(data) / "serve.stderr"
        Path(data).mkdir(parents=True, exist_ok=True)
        cell_option = ["--cell", cell] if cell else []
        command = [
            sys.executable,
            *python_options,
            "-m",
            "vservo.app.cli",
            *cell_option,
            "serve",
            "--port",
            str(free_port()),
            "--data",
            str(data),
            "--cycle-period",
            str(cycle_period_s),
            "--seed",
            str(seed),
            *([] if time_scale is None else ["--time-scale", f"{time_scale:g}"]),
        ]
        environment = {**os.environ, TOKEN_ENVIRONMENT: token}  # not --token: ps would show it
        with open(stderr_path, "w") as stderr:
            process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=stderr, text=True, env=environment)
        stdout = process.stdout
        assert stdout is not None  # piped
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if select.select([stdout], [], [], 0.5)[0]:
                match = URL_LINE.search(stdout.readline())
                if match:
                    return cls(process, match.group(1), token, stderr_path)
            if process.poll() is not None:
                break
        process.kill()
        process.wait()
        raise RuntimeError(f"vservo serve did not start: {stderr_path.read_text()[-2000:]}")

    def stop(self, timeout_s: float = 60.0) -> int:
        """SIGTERM, as Ctrl-C or a service manager would; the exit code."""
        self.process.send_signal(signal.SIGTERM)
        try:
            code = self.process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.process.kill()
            code = self.process.wait()
        if self.process.stdout is not None:
            self.process.stdout.close()
        return code

    def stderr(self) -> str:
        return self.stderr_path.read_text()

    def __enter__(self) -> ServeProcess:
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self.process.poll() is None:  # a test may have stopped it itself
            self.stop()


# -- page helpers ----------------------------------------------------------------------------


def open_pages(browser: Any, url: str, sizes: list[tuple[int, int]]) -> list[Any]:
    """One new browser context per size (each its own client of the app), all loading at once."""
    pages = [browser.new_context(viewport={"width": w, "height": h}).new_page() for w, h in sizes]
    for page in pages:
        page.goto(url, wait_until="commit")
    for page in pages:
        page.get_by_role("button", name="Take control").wait_for(timeout=90_000)
        dismiss_notifications(page)  # headless Chromium's "software WebGL" notice covers the canvas's corner
    return pages


def field(page: Any, label: str) -> Any:
    """The input viser shows beside ``label`` (its text inputs carry no id for a <label for>)."""
    return page.locator(f"xpath=//label[normalize-space()='{label}']/ancestor::div[.//input][1]//input").first


# viser's page sends GUI messages through one sender throttled to 50 ms that keeps only the
# newest pending message: a click right after typing could replace the typed value.
SETTLE_S = 0.25


def choose(page: Any, label: str, option: str) -> None:
    """Pick ``option`` in the dropdown labelled ``label``."""
    field(page, label).click()
    page.get_by_role("option", name=option, exact=True).click()
    time.sleep(SETTLE_S)


def type_into(page: Any, label: str, text: str) -> None:
    """Type ``text`` into the input labelled ``label``."""
    field(page, label).fill(text)
    time.sleep(SETTLE_S)


def take_control(page: Any, token: str) -> None:
    type_into(page, "Operator token", token)
    page.get_by_role("button", name="Take control").click()
    page.get_by_text("this browser holds control").wait_for(timeout=30_000)


def operator_on_assemble(browser: Any, url: str, token: str, job: str = "demo", size: tuple[int, int] = (1400, 900)) -> Any:
    """A page holding control, on the Assemble tab with ``job`` chosen: where a run starts."""
    page = open_pages(browser, url, [size])[0]
    take_control(page, token)
    page.get_by_role("tab", name="Assemble").click()
    choose(page, "Job", job)
    return page


def dismiss_notifications(page: Any) -> None:
    """Close the toasts (software WebGL notice, command replies) before a screenshot."""
    for button in page.locator(".mantine-Notification-closeButton").all():
        try:
            button.click(timeout=1000)
        except Exception:  # a toast that closed itself meanwhile
            pass


def status_text(page: Any) -> str:
    """The status line under the E-STOP (phase, run, stage, cycle, error, detail, flange pose)."""
    return page.get_by_text(re.compile("flange (X|pose not known)")).first.locator("xpath=..").inner_text()


def banner(page: Any) -> tuple[str, str, str]:
    """The banner over the page (app/banner.py): its kind, its words and its background colour."""
    element = page.locator(".vservo-banner").first
    return (
        element.get_attribute("data-kind") or "",
        element.inner_text(),
        element.evaluate("(e) => getComputedStyle(e).backgroundColor"),
    )


def wait_for_banner(page: Any, kind: str, pattern: str = "", timeout_s: float = 60.0) -> str:
    """Poll the banner until it is of ``kind`` and its words match ``pattern`` (regex); its words."""
    deadline = time.monotonic() + timeout_s
    shown = ("", "", "")
    while time.monotonic() < deadline:
        shown = banner(page)
        if shown[0] == kind and re.search(pattern, shown[1]):
            return shown[1]
        time.sleep(0.1)
    raise TimeoutError(f"the banner never showed {kind} {pattern!r}; last: {shown!r}")


def wait_for_status(page: Any, pattern: str, timeout_s: float = 60.0) -> str:
    """Poll the status line until ``pattern`` (regex) matches; the line."""
    deadline = time.monotonic() + timeout_s
    text = ""
    while time.monotonic() < deadline:
        text = status_text(page)
        if re.search(pattern, text):
            return text
        time.sleep(0.1)
    raise TimeoutError(f"the status never matched {pattern!r}; last: {text!r}")


def present_part_and_start(page: Any) -> int:
    """Present a new part, press Start on the Assemble tab; the run's number once it servoes."""
    page.get_by_role("button", name="Present part", exact=True).click()
    wait_for_status(page, r"a new part is on the table")
    page.get_by_role("button", name="Start", exact=True).click()
    running = wait_for_status(page, r"Servoing .*run (\d+)")
    number = re.search(r"run (\d+)", running)
    assert number is not None  # the status matched it
    return int(number.group(1))


def servo_then_estop(page: Any) -> int:
    """Present a part, start the job, and once its servo has run a few cycles press E-STOP and
    wait for the page to say E-STOPPED; the run's number."""
    run = present_part_and_start(page)
    wait_for_status(page, rf"Servoing .*run {run}.*cycle [2-9]", timeout_s=60)
    page.get_by_role("button", name="E-STOP", exact=True).click()
    wait_for_status(page, r"E-STOPPED", timeout_s=10)
    return run


def cycle_of(text: str) -> int | None:
    match = STATUS_CYCLE.search(text)
    return int(match.group(1)) if match else None


def flange_of(text: str) -> tuple[float, ...]:
    match = STATUS_FLANGE.search(text)
    if match is None:
        raise ValueError(f"no flange pose in {text!r}")
    return tuple(float(v) for v in match.groups())


def count_image_updates(page: Any) -> None:
    page.evaluate(COUNT_IMAGE_UPDATES)


def image_updates(page: Any) -> int:
    return int(page.evaluate("window.__imageUpdates || 0"))
