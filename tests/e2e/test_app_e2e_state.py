"""The state at a glance and the replay, end to end: `vservo serve` as a real process, headless Chromium.

The banner over the page says ready, running (the stage in words), placed, e-stopped,
teaching, missed and fault, each in its colour; Start is disabled while a run is under way and while e-stopped, in the
operator's own page; the History tab opens on the newest run, and its replay plays, pauses,
seeks and changes speed. With VSERVO_DOC_IMAGES set (docs/images), the screenshots of each
banner and of the replay are written there for docs/operator-guide.md; else to
$VSERVO_ARTIFACTS (default test-artifacts/, not versioned). Chromium must be at
/usr/bin/chromium: a missing browser fails the tests, it never skips them.
"""

from __future__ import annotations

import os
import re
import time
from dataclasses import replace
from pathlib import Path

import pytest

from tests.chromium import chromium_or_fail, headless_chromium
from tests.jrc_fixtures import thesis_policy_cell_file
from vservo.app.banner import Kind
from vservo.app.browser import (
    ServeProcess,
    banner,
    choose,
    dismiss_notifications,
    open_pages,
    take_control,
    wait_for_banner,
    wait_for_status,
)
from vservo.core.geometry.spatial import transform
from vservo.core.production.protocol.catalogue import RunEnd, explain
from vservo.core.production.storage import Store

TOKEN = "e2e-state-token"
ROOT = Path(__file__).resolve().parents[2]
IMAGES = Path(os.environ.get("VSERVO_DOC_IMAGES") or os.environ.get("VSERVO_ARTIFACTS", ROOT / "test-artifacts"))
# Whether an element is shown whole: no scrolling box it sits in (up to the panel) hides part of it.
SHOWN_WHOLE = """(element) => {
    for (let node = element.parentElement, level = 0; node && level < 12; node = node.parentElement, level++) {
        const overflow = getComputedStyle(node).overflowY;
        const clips = overflow === 'auto' || overflow === 'scroll' || overflow === 'hidden';
        if (clips && node.scrollHeight > node.clientHeight + 1) {
            return false;
        }
    }
    return true;
}"""
REPLAY_TEXT = re.compile(r"run (\d+): ([\d.]+) s of ([\d.]+) s, frame (\d+) of (\d+)")


def _rgb(kind: Kind) -> str:
    value = kind.value.lstrip("#")
    return "rgb({}, {}, {})".format(*(int(value[k : k + 2], 16) for k in (0, 2, 4)))


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    chromium_or_fail()  # before `vservo serve` starts
    IMAGES.mkdir(parents=True, exist_ok=True)
    data = tmp_path_factory.mktemp("serve-data")
    store_a_job_that_misses(data)
    # The thesis's step policy: a run of a few hundred cycles, long enough to watch its banner
    # (the shipped fast policy's takes a handful).
    serve = ServeProcess.start(data, TOKEN, cycle_period_s=0.02, cell=thesis_policy_cell_file(data))
    try:
        with headless_chromium() as chromium:
            (operator,) = open_pages(chromium, serve.url, [(1600, 1000)])
            take_control(operator, TOKEN)
            yield operator
    finally:
        assert serve.stop() == 0
        assert "Traceback" not in serve.stderr(), serve.stderr()[-3000:]


def store_a_job_that_misses(data: Path) -> None:
    """`off`: the demo job with its place pose taught 4 mm aside, as a careless teach would:
    every run sets the part on the pocket's rim, a miss."""
    store = Store(data)
    try:
        demo = store.load_job("demo")
        off = replace(demo, name="off", bMe_place=transform(t=(0.004, 0.0, 0.0)) @ demo.bMe_place)
        store.save_job(off, store.job_image("demo"), store.job_image("demo", check=True))
    finally:
        store.close()


def _colour(page) -> str:
    """The banner's background colour; the page redraws the banner on each state it shows, and
    a banner read as it is replaced has none yet: read it again."""
    deadline = time.monotonic() + 10.0
    while not (colour := banner(page)[2]) and time.monotonic() < deadline:
        time.sleep(0.05)
    return colour


def _shot(page, name: str, top_px: int | None = 480) -> None:
    """The page (its top ``top_px``: the banner, the E-STOP and the Assemble tab's buttons) as PNG."""
    dismiss_notifications(page)
    clip = None if top_px is None else {"x": 0, "y": 0, "width": 1600, "height": top_px}
    page.screenshot(path=str(IMAGES / f"{name}.png"), clip=clip)


def _start(page) -> None:
    page.get_by_role("button", name="Present part", exact=True).click()
    wait_for_status(page, r"a new part is on the table")
    page.get_by_role("button", name="Start", exact=True).click()


def _replay_state(page) -> tuple[int, ...]:
    text = page.get_by_text(REPLAY_TEXT).first.inner_text()
    run, at, duration, frame, frames = REPLAY_TEXT.search(text).groups()
    return int(run), float(at), float(duration), int(frame), int(frames)


def test_the_banner_follows_a_run_from_ready_to_placed(page):
    kind, words, colour = banner(page)
    assert (kind, colour) == ("ready", _rgb(Kind.READY)) and "READY" in words and "press Start" in words
    assert page.locator(".vservo-banner").bounding_box()["width"] == 1600  # the whole width of the page
    estop_button = page.get_by_role("button", name="E-STOP", exact=True)
    estop = estop_button.bounding_box()
    assert estop["y"] + estop["height"] < 400 and estop["height"] >= 60  # large, at the top, never below the fold
    hand, label = estop_button.locator("svg").bounding_box(), estop_button.get_by_text("E-STOP").bounding_box()
    assert hand["x"] + hand["width"] <= label["x"], (hand, label)  # its icon clear of its word
    _shot(page, "banner-ready")

    _start(page)
    running = wait_for_banner(page, "busy", r"RUNNING job demo: (turning|approaching|final)")
    assert _colour(page) == _rgb(Kind.BUSY) and "keep clear" in running
    assert page.get_by_role("button", name="Start", exact=True).is_disabled()
    assert page.get_by_role("button", name="Present part", exact=True).is_disabled()
    wait_for_status(page, r"cycle ([3-9]\d|\d{3})")
    _shot(page, "banner-running", top_px=None)

    placed = wait_for_banner(page, "placed", r"PLACED: job demo", timeout_s=120)
    assert _colour(page) == _rgb(Kind.PLACED) and "press Start" in placed and "mm from its taught place" in placed
    assert not page.get_by_role("button", name="Start", exact=True).is_disabled()
    _shot(page, "banner-placed")


def test_the_banner_says_e_stopped_in_red_and_start_waits_for_reset(page):
    _start(page)
    wait_for_status(page, r"Servoing .*cycle ([2-9]\d|\d{3})")
    page.get_by_role("button", name="E-STOP", exact=True).click()
    stopped = wait_for_banner(page, "estopped", r"E-STOPPED", timeout_s=10)
    assert _colour(page) == _rgb(Kind.ESTOPPED) and "press Reset" in stopped and "e-stop pressed" in stopped
    assert page.get_by_role("button", name="Start", exact=True).is_disabled()
    assert not page.get_by_role("button", name=re.compile("^Reset")).is_disabled()
    status = page.get_by_text(re.compile("flange X")).first.locator("xpath=..")
    assert status.evaluate(SHOWN_WHOLE), status.inner_text()  # the status line is never cut off
    _shot(page, "banner-estopped")
    page.get_by_role("button", name=re.compile("^Reset")).click()
    wait_for_banner(page, "ready", "READY", timeout_s=30)
    assert not page.get_by_role("button", name="Start", exact=True).is_disabled()
    assert page.get_by_role("button", name=re.compile("^Reset")).is_disabled()


def test_history_opens_on_the_newest_run_and_its_replay_plays_pauses_seeks_and_speeds_up(page):
    page.get_by_role("tab", name="History").click()
    page.get_by_text(re.compile(r"Run 2 \(demo\): E-STOPPED")).first.wait_for(timeout=30_000)  # the newest first
    run_field = page.locator("xpath=//label[normalize-space()='Run']/ancestor::div[.//input][1]//input").first
    run_field.click()
    page.get_by_role("option", name=re.compile(r"^#1 demo placed")).click()
    page.get_by_text(re.compile(r"Run 1 \(demo\): placed")).first.wait_for(timeout=10_000)
    page.get_by_role("button", name="Replay its recording").click()

    page.get_by_text(REPLAY_TEXT).first.wait_for(timeout=30_000)
    page.get_by_role("button", name="Pause", exact=True).click()
    time.sleep(0.5)
    paused = _replay_state(page)
    time.sleep(1.0)
    assert _replay_state(page) == paused  # paused: the frame stays
    assert page.get_by_role("button", name="Pause", exact=True).is_disabled()
    assert not page.get_by_role("button", name="Play", exact=True).is_disabled()

    page.get_by_role("slider").first.focus()  # seek: the slider's keyboard, as an operator's arrow keys
    page.keyboard.press("Home")
    deadline = time.monotonic() + 10
    while _replay_state(page)[3] != 1 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _replay_state(page)[3] == 1, _replay_state(page)

    # In real time: at 4x the run's own duration passes four times faster. The replay this
    # replaced played three times slower than the run, i.e. twelve times slower than this.
    field_input = page.locator("xpath=//label[normalize-space()='Replay speed']/ancestor::div[.//input][1]//input")
    field_input.first.click()
    page.get_by_role("option", name="4x", exact=True).click()
    duration = _replay_state(page)[2]
    page.get_by_role("button", name="Play", exact=True).click()
    begun = time.monotonic()
    deadline = begun + duration / 4 + 10.0
    while time.monotonic() < deadline:
        run, at, _, frame, frames = _replay_state(page)
        if frame == frames:
            break
        time.sleep(0.1)
    assert (frame, run) == (frames, 1), _replay_state(page)
    chart = page.get_by_text("replay: how far the part is from the taught view").first
    chart.scroll_into_view_if_needed()
    assert chart.is_visible()
    _shot(page, "replay", top_px=None)


def test_the_banner_says_teaching_missed_and_fault_each_in_its_colour(page):
    page.get_by_role("tab", name="Teach").click()
    page.get_by_role("button", name="Begin teaching", exact=True).click()
    teaching = wait_for_banner(page, "busy", r"TEACHING", timeout_s=30)
    assert _colour(page) == _rgb(Kind.BUSY) and "Teach tab" in teaching, teaching
    _shot(page, "banner-teaching")
    page.get_by_role("button", name="Cancel teaching", exact=True).click()
    wait_for_banner(page, "ready", "READY", timeout_s=30)

    page.get_by_role("tab", name="Assemble").click()
    choose(page, "Job", "off")
    _start(page)
    missed = wait_for_banner(page, "missed", r"MISSED: job off", timeout_s=120)
    assert _colour(page) == _rgb(Kind.MISSED) and "beyond the 1 mm tolerance" in missed, missed
    _shot(page, "banner-missed")

    # No new part: the camera at the start pose finds none, and the run faults.
    choose(page, "Job", "demo")
    page.get_by_role("button", name="Start", exact=True).click()
    fault = wait_for_banner(page, "fault", r"FAULT", timeout_s=120)
    assert _colour(page) == _rgb(Kind.FAULT), fault
    lost = explain(RunEnd.FEATURES_LOST)  # in the catalogue's words, with what to do
    assert lost.sentence in fault and lost.action.value in fault and "servo failed" not in fault, fault
    _shot(page, "banner-fault")
    page.get_by_role("button", name=re.compile("^Reset")).click()
    wait_for_banner(page, "ready", "READY", timeout_s=30)
