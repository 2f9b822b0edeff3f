"""docs/operator-guide.md's "Teaching a new job", followed word for word in Chromium.

`vservo serve` as a real process, headless Chromium as the operator's browser. The test
starts where a demo run leaves the arm (over the metal part's pocket) and does what the
guide says, step by step: Home, Survey, then from "(new job)" (no template), with the
values the page shows (the flange pose the Teach tab offers to view the part it sees, the
cup pose on it and in the pocket of the cell file's metal part), it teaches a new job on a
part presented 40 mm from where the demo job's part lies, saves it, and assembles it three
times, each on a newly presented part: placed each time. Every refusal it provokes on the
way (Start with no part, an unreachable Move there, a straight line a joint path makes, a
test pick with nothing under the cup) shows the catalogue's sentence and action
(core/production/protocol/catalogue.py), and the Teach tab's next step follows the draft. Each teach step's page goes to
$VSERVO_DOC_IMAGES (docs/images: the guide's pictures are made so) or else
$VSERVO_ARTIFACTS (default test-artifacts/, not versioned) as guide-NN-step.png. Chromium
must be at /usr/bin/chromium: a missing browser fails the test, it never skips it.
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import pytest

from tests.chromium import chromium_or_fail, headless_chromium
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
# Where the guide's new part lies: 40 mm from the demo job's part (top-face centre X -390, Y 0).
PART_X_MM, PART_Y_MM = -390.0, -40.0
# Three parts as they might arrive for the runs: a few mm and degrees off where it was taught.
ARRIVALS = ((-388.0, -42.0, 5.0), (-393.0, -37.0, -8.0), (-390.0, -40.0, 12.0))
POSE = r"((?:-?[\d.]+ ){5}-?[\d.]+)"


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


def press(page, button: str, done: str, timeout_s: float = 60.0) -> None:
    """Press ``button`` and wait for the page to say ``done`` (a notice or the status line)."""
    dismiss_notifications(page)
    page.get_by_role("button", name=button, exact=True).click()

    def said() -> bool:
        return re.search(done, notices(page) + status_text(page)) is not None

    wait_until(said, f"{button}: the page never said {done!r}; last {status_text(page)!r}", timeout_s)


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


def offered(page, words: str) -> str:
    """The pose the Teach tab offers after ``words`` (e.g. "Cup on it")."""
    line = page.get_by_text(re.compile(f"{words}: ")).first
    line.wait_for(timeout=30_000)
    found = re.search(rf"{words}: {POSE}", line.inner_text())
    assert found is not None, line.inner_text()
    return found.group(1)


def move_to(page, tool: str, words: str) -> None:
    """Move to: ``tool``, the pose the tab offers after ``words``, Move there."""
    choose(page, "Move to: tool", tool)
    type_into(page, "Pose X Y Z phi theta psi (mm, deg)", offered(page, words))
    press(page, "Move there", "arrived")


def present(page, x: float, y: float, turn: float) -> None:
    type_into(page, "Part X (mm)", f"{x:g}")
    type_into(page, "Part Y (mm)", f"{y:g}")
    type_into(page, "Part turn (deg)", f"{turn:g}")
    press(page, "Present part here", "a new part is on the table")


def seen_at(page, x: float, y: float) -> None:
    """Wait until the tab's "Part seen" puts the part's top-face centre within 2 mm of X, Y."""

    def there() -> bool:
        seen = page.get_by_text("Part seen").first.inner_text()
        found = re.search(r"Part seen: top-face centre X (-?[\d.]+) Y (-?[\d.]+)", seen)
        return found is not None and abs(float(found.group(1)) - x) < 2.0 and abs(float(found.group(2)) - y) < 2.0

    wait_until(
        there,
        f"the part seen at X {x:g}, Y {y:g}; the tab says {page.get_by_text('Part seen').first.inner_text()!r}"
        f" at {status_text(page)!r}",
    )


def jog(page, button: str, times: int, axis: int, mm: float) -> None:
    """Step 20 mm / 10 deg, ``button`` pressed ``times``, each waited for on the status line's flange pose."""
    choose(page, "Step", "20 mm / 10 deg")
    for _ in range(times):
        before = flange_of(status_text(page))[axis]
        page.get_by_role("button", name=button, exact=True).click()
        wait_until(lambda: abs(flange_of(status_text(page))[axis] - (before + mm)) < 0.05, f"the flange moved {button}")


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


def test_teach_a_new_job_as_the_guide_says_and_assemble_it_three_times(page):
    # Taking control; a demo run leaves the arm over the pocket.
    take_control(page, TOKEN)
    after_a_demo_run(page)

    # Home, then Survey: the camera over the table where parts are presented.
    page.get_by_role("tab", name="Teach").click()
    over_the_pocket = flange_of(status_text(page))
    press(page, "Home", "arrived at home")
    assert flange_of(status_text(page)) != over_the_pocket
    press(page, "Survey", "arrived at the survey pose")

    # 1. Teach tab, Template (new job), Begin teaching.
    choose(page, "Template", "(new job)")
    press(page, "Begin teaching", r"jog to the desired view")
    assert next_step(page) == "Capture desired image"
    shot(page, 1, "begin")

    # 2. Present the part: X -390, Y -40, turn 0; the survey sees it.
    present(page, PART_X_MM, PART_Y_MM, 0.0)
    seen_at(page, PART_X_MM, PART_Y_MM)

    # Reachability explained: a target no joints reach names the joint and the way to move
    # it; one the straight line cannot make is offered on a joint path, which makes it.
    choose(page, "Move to: tool", "flange")
    type_into(page, "Pose X Y Z phi theta psi (mm, deg)", "-200 0 0 180 0 180")
    words = refused(page, "Move there", Refusal.UNREACHABLE)
    assert re.search(r"joint_\d stops at its (upper|lower) limit: move the target toward [+-][XYZ]", words), words
    assert "joint" in engineering_line(page, "Move there")  # the safety layer's own line
    type_into(page, "Pose X Y Z phi theta psi (mm, deg)", "-350 200 300 180 0 180")
    refused(page, "Move there", Refusal.LINE_BLOCKED)
    press(page, "Move there (joint path)", "arrived")
    press(page, "Survey", "arrived at the survey pose")

    # 3. The desired view: the part seen where it was presented, the flange to the pose the
    # tab offers to view it, capture.
    seen_at(page, PART_X_MM, PART_Y_MM)
    move_to(page, "flange", "Flange to view it")
    press(page, "Capture desired image", "desired image captured")
    shot(page, 2, "desired-view")

    # 4. The pick: a test pick with nothing under the cup is refused and offered again; the
    # cup to the pose the tab offers, a test pick, set it, suction on.
    assert next_step(page) == "Test pick"
    refused(page, "Test pick", Refusal.NO_GRIP)
    assert next_step(page) == "Test pick"  # the failed test pick is the next step again
    move_to(page, "cup", "Cup on it")
    press(page, "Test pick", "grip good")
    assert next_step(page) == "Set pick pose here"
    press(page, "Set pick pose here", "pick pose set")
    assert next_step(page) == "Suction on"
    press(page, "Suction on", "reports a part on the cup")
    shot(page, 3, "pick")

    # 5. The place: lift 40 mm, above the pocket, the cup in the pocket, set it (the place
    # check said at once), suction off.
    jog(page, "+Z", 2, axis=2, mm=20.0)
    press(page, "Go above the pocket", "arrived")
    move_to(page, "cup", "Cup in the pocket")
    press(page, "Set place pose here", r"place pose set here: the part sits 0\.\d mm and [+-]0\.\d deg from the pocket")
    assert "WARNING" not in status_text(page)
    assert next_step(page) == "Suction off"  # the part still on the cup
    shot(page, 4, "place")
    press(page, "Suction off", "reports no part on the cup")
    assert next_step(page) == "Capture check view"

    # 6. The check view: over the placed part, capture it.
    press(page, "Go over the placed part", "arrived")
    press(page, "Capture check view", "check view captured: the part lies")
    shot(page, 5, "check-view")

    # 7. The start pose: a part where parts arrive, the desired view, 20 mm along +X, set it.
    present(page, PART_X_MM, PART_Y_MM, 0.0)
    press(page, "Go to the desired view", "arrived")
    jog(page, "+X", 1, axis=0, mm=20.0)
    press(page, "Set start pose here", "start pose set")

    # 8. A new job's settings, Apply settings; name it, Save job.
    press(page, "Apply settings", "settings changed")
    page.get_by_text("Everything is taught").wait_for(timeout=10_000)
    shot(page, 6, "save")
    type_into(page, "Job name", "shifted")
    press(page, "Save job", r"job 'shifted' saved")

    # Assemble it three times, each on a newly presented part.
    outcomes, run_id = [], 0
    for run, (x, y, turn) in enumerate(ARRIVALS, start=1):
        page.get_by_role("tab", name="Teach").click()
        present(page, x, y, turn)
        page.get_by_role("tab", name="Assemble").click()
        choose(page, "Job", "shifted")
        page.get_by_role("button", name="Start", exact=True).click()

        # The run's end (the fast step policy servoes in a handful of cycles: its start may pass unseen).
        def ended_after(last: int = run_id) -> bool:
            found = re.search(r"(Done|FAULT|E-STOPPED) · job shifted · run (\d+)", status_text(page))
            return found is not None and int(found.group(2)) > last

        wait_until(ended_after, f"run {run} of job shifted never ended", timeout_s=180)
        ended = status_text(page)
        run_id = int(re.search(r"run (\d+)", ended).group(1))
        outcome = page.get_by_text(f"Run {run_id}: ").first
        outcome.wait_for(timeout=10_000)
        assert f"Run {run_id}: placed" in outcome.inner_text(), (run, outcome.inner_text(), ended)
        outcomes.append(outcome.locator("xpath=..").inner_text())  # the figures under the outcome
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
