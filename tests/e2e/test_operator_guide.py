"""docs/operator-guide.md's "Teaching a new job", followed word for word in Chromium.

`vservo serve` as a real process, headless Chromium as the operator's browser. The test
starts from the arm left over the pocket by a demo run (and a Start with no part, a fault
in the catalogue's words), shows reachability explained in manual mode (an unreachable Move
there names the joint; a line the arm cannot make is offered on a joint path), presses
Home and Survey, then does what the guide says, step by step, from "(new job)"
(tests/e2e/guide_steps.py), with a test pick refused while nothing is under the cup; it
saves the job and assembles it three times, each on a newly presented part: placed each
time. Each teach step's page goes to $VSERVO_DOC_IMAGES (docs/images: the guide's pictures
are made so) or else $VSERVO_ARTIFACTS (default test-artifacts/, not versioned) as
guide-NN-step.png. Chromium must be at /usr/bin/chromium: a missing browser fails the
test, it never skips it.
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import pytest

from tests.chromium import chromium_or_fail, headless_chromium
from tests.e2e.guide_steps import PART_X_MM, PART_Y_MM, assemble_once, present, press, seen_at, teach_the_guide_job
from tests.polling import wait_until
from vservo.app.browser import (
    ServeProcess,
    choose,
    dismiss_notifications,
    flange_of,
    open_pages,
    status_text,
    take_control,
    type_into,
    wait_for_banner,
)
from vservo.core.production.protocol.catalogue import Refusal, RunEnd, explain

TOKEN = "guide-operator-token"
ARTIFACTS = Path(os.environ.get("VSERVO_ARTIFACTS", Path(__file__).resolve().parents[2] / "test-artifacts"))
IMAGES = Path(os.environ.get("VSERVO_DOC_IMAGES") or ARTIFACTS)
# Three parts as they might arrive for the runs: a few mm and degrees off where it was taught.
ARRIVALS = ((PART_X_MM + 2.0, PART_Y_MM - 2.0, 5.0), (PART_X_MM - 3.0, PART_Y_MM + 3.0, -8.0), (PART_X_MM, PART_Y_MM, 12.0))


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    chromium_or_fail()  # before `vservo serve` starts
    serve = ServeProcess.start(tmp_path_factory.mktemp("guide-data"), TOKEN, cycle_period_s=0.02)
    try:
        with headless_chromium() as chromium:
            (operator,) = open_pages(chromium, serve.url, [(1600, 1000)])
            yield operator
    finally:
        assert serve.stop() == 0
        assert "Traceback" not in serve.stderr(), serve.stderr()[-3000:]  # nor a display update that failed


def notices(page) -> str:
    return " ".join(page.locator(".mantine-Notification-root").all_inner_texts())


def refused(page, button: str, kind: Refusal, timeout_s: float = 60.0) -> str:
    """Press ``button``: the notice says it was refused, in the catalogue's sentence and action
    for ``kind`` (no engineering line, no doubled prefix); the notice's words."""
    explanation = explain(kind)
    dismiss_notifications(page)
    page.get_by_role("button", name=button, exact=True).click()
    wait_until(lambda: f"{button}: refused" in notices(page), f"{button} was never refused; {status_text(page)!r}", timeout_s)
    words = notices(page)
    assert explanation.sentence in words and explanation.action.value in words, words
    assert "refused: refused" not in words and "move refused" not in words, words
    dismiss_notifications(page)
    return words


def engineering_line(page, button: str) -> str:
    """The refusal's engineering line, in the live panel's Engineering fold (opened, read, folded)."""
    fold = page.get_by_text("Engineering", exact=True).first
    fold.click()
    line = page.get_by_text(f"Last refusal ({button})").first
    line.wait_for(timeout=10_000)
    text = line.inner_text()
    fold.click()
    return text


def next_step(page) -> str:
    """The Teach tab's next step (**Next: ...**), which its orange button follows."""
    return re.search(r"Next: ([^·\n]+?)\s*(·|$)", page.get_by_text("Next: ").first.inner_text()).group(1)


def shot(page, number: int, name: str) -> None:
    IMAGES.mkdir(parents=True, exist_ok=True)
    dismiss_notifications(page)
    page.screenshot(path=str(IMAGES / f"guide-{number:02d}-{name}.png"))


def after_a_demo_run(page) -> None:
    """A demo run placed: the arm ends over the metal part's pocket; then Start again with
    no new part: the run faults, and the banner says so in the catalogue's words."""
    page.get_by_role("tab", name="Assemble").click()
    page.get_by_role("button", name="Present part", exact=True).click()
    wait_until(lambda: "a new part is on the table" in status_text(page), "a part presented")
    page.get_by_role("button", name="Start", exact=True).click()
    wait_for_banner(page, "placed", r"PLACED: job demo", timeout_s=120)
    page.get_by_role("button", name="Start", exact=True).click()  # the part is in the pocket: none to servo on
    words = wait_for_banner(page, "fault", r"FAULT: job demo", timeout_s=120)
    ends = [end for end in RunEnd if explain(end).sentence in words]
    assert ends and explain(ends[0]).action.value in words, words  # the sentence and what to do
    assert "servo failed" not in words, words  # the engineer's line is the Engineering fold's
    page.get_by_role("button", name=re.compile("^Reset")).click()
    wait_for_banner(page, "ready", "READY", timeout_s=30)


def reachability_explained(page) -> None:
    """In manual mode: a target no joints reach names the joint and the way to move it; one
    the straight line cannot make is offered on a joint path, which makes it."""
    press(page, "Manual mode", "manual mode")
    choose(page, "Move to: tool", "flange")
    type_into(page, "Pose X Y Z phi theta psi (mm, deg)", "-200 0 0 180 0 180")
    words = refused(page, "Move there", Refusal.UNREACHABLE)
    assert re.search(r"joint_\d stops at its (upper|lower) limit: move the target toward [+-][XYZ]", words), words
    assert "joint" in engineering_line(page, "Move there")  # the safety layer's own line
    type_into(page, "Pose X Y Z phi theta psi (mm, deg)", "-350 200 300 180 0 180")
    refused(page, "Move there", Refusal.LINE_BLOCKED)
    press(page, "Move there (joint path)", "arrived")
    press(page, "Leave manual mode", "manual mode left")


def a_test_pick_with_nothing_under_the_cup(page) -> None:
    """From the desired view the cup is far above the part: the test pick is refused and stays the next step."""
    assert next_step(page) in ("Centre the cup on the part", "Test pick"), next_step(page)
    refused(page, "Test pick", Refusal.NO_GRIP)
    assert next_step(page) in ("Centre the cup on the part", "Test pick"), next_step(page)


def test_teach_a_new_job_as_the_guide_says_and_assemble_it_three_times(page):
    # Taking control; a demo run leaves the arm over the pocket.
    take_control(page, TOKEN)
    after_a_demo_run(page)
    page.get_by_role("tab", name="Teach").click()
    reachability_explained(page)

    # Home, then Survey: the camera over the table where parts are presented.
    away = flange_of(status_text(page))
    press(page, "Home", "arrived at home")
    assert flange_of(status_text(page)) != away
    press(page, "Survey", "arrived at the survey pose")
    present(page, PART_X_MM, PART_Y_MM, 0.0)
    seen_at(page, PART_X_MM, PART_Y_MM, 2.0)  # the survey sees where parts are presented

    teach_the_guide_job(
        page,
        lambda number, name: shot(page, number, name),
        measured=True,
        at_the_pick=lambda: a_test_pick_with_nothing_under_the_cup(page),
    )

    # Assemble it three times, each on a newly presented part.
    outcomes, run_id = [], 0
    for run, (x, y, turn) in enumerate(ARRIVALS, start=1):
        assembled = assemble_once(page, x, y, turn, run_id)
        run_id = assembled.run_id
        assert assembled.placed, (run, assembled.outcome, assembled.status)
        outcomes.append(assembled.outcome)  # the figures under the outcome
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "guide-runs.txt").write_text("\n".join(outcomes) + "\n")  # the figures, for the record


def test_holding_a_jog_button_moves_the_arm_until_it_is_let_go(page):
    if page.get_by_text("this browser holds control").count() == 0:  # run on its own
        take_control(page, TOKEN)
    page.get_by_role("tab", name="Teach").click()
    page.get_by_text("Hold to jog").first.click()  # the folder is folded
    hold = page.get_by_role("button", name="Hold +Z", exact=True)
    assert hold.is_disabled()  # jogs only while teaching or in manual mode
    press(page, "Manual mode", "manual mode")
    wait_until(lambda: not hold.is_disabled(), "Hold +Z live in manual mode")
    choose(page, "Speed", "medium: 10 mm/s, 5 deg/s")
    # One step first: a fresh controller publishes the flange pose with its first move.
    shown = flange_of(status_text(page))
    choose(page, "Step", "1 mm / 1 deg")
    page.get_by_role("button", name="-Z", exact=True).click()
    wait_until(lambda: flange_of(status_text(page)) != shown, "the flange pose shown after a step")
    time.sleep(1.0)
    before = flange_of(status_text(page))[2]
    hold.hover()
    page.mouse.down()
    time.sleep(1.5)
    page.mouse.up()
    time.sleep(1.0)  # the last jog under way ends
    released = flange_of(status_text(page))[2]
    time.sleep(1.5)
    assert flange_of(status_text(page))[2] == released  # nothing moves once let go
    assert 3.0 < released - before < 30.0, (before, released)  # about 1.5 s at 10 mm/s
    press(page, "Leave manual mode", "manual mode left")
    wait_until(hold.is_disabled, "Hold +Z disabled once manual mode is left")
