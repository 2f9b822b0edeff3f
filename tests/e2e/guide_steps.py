"""docs/operator-guide.md's "Teaching a new job", word for word, on a page in Chromium; and
one assembly of the taught job. Shared by the guide's tests: on the simulated cell
(test_operator_guide.py) and on a virtual cell never commissioned whose truth is Table 5-5's
errors away from its cell file (test_operator_guide_uncommissioned.py)."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

from tests.polling import wait_until
from vservo.app.browser import choose, dismiss_notifications, flange_of, status_text, type_into

# Where the guide's new part lies: 40 mm from the demo job's part (top-face centre X -390, Y 0).
PART_X_MM, PART_Y_MM = -390.0, -40.0
JOB = "shifted"
POSE = r"((?:-?[\d.]+ ){5}-?[\d.]+)"
AID_TIMEOUT_S = 180.0  # View the part and Centre the cup on the part: tens of moves over the JRC link


class PageRefused(AssertionError):
    """The page refused what a step pressed: its notice, in full."""


def press(page, button: str, done: str, timeout_s: float = 60.0) -> None:
    """Press ``button`` and wait for the page to say ``done`` (a notice or the status line)."""
    dismiss_notifications(page)
    page.get_by_role("button", name=button, exact=True).click()

    notices: list[str] = []  # every notice shown meanwhile (a refusal's closes itself after 12 s)

    def said() -> bool:
        shown = page.locator(".mantine-Notification-root").all_inner_texts()
        notices.extend(text for text in shown if text not in notices)
        refused = [text for text in shown if text.startswith(f"{button}: refused")]
        if refused:
            raise PageRefused(f"{button}: {refused[0]!r}; the status: {status_text(page)!r}")
        return re.search(done, " ".join(shown) + status_text(page)) is not None

    try:
        wait_until(said, f"{button}: the page never said {done!r}", timeout_s)
    except PageRefused:
        raise
    except AssertionError as exc:
        raise AssertionError(f"{exc}; the status: {status_text(page)!r}; the notices meanwhile: {notices!r}") from None


def offered(page, words: str) -> str:
    """The pose the Teach tab offers after ``words`` (e.g. "Cup in the pocket")."""
    line = page.get_by_text(words).first
    line.wait_for(timeout=30_000)
    return re.search(rf"{words}: {POSE}", line.inner_text()).group(1)


def move_to(page, tool: str, words: str) -> None:
    """Move to: ``tool``, the pose the tab offers after ``words``, Move there."""
    choose(page, "Move to: tool", tool)
    type_into(page, "Pose X Y Z phi theta psi (mm, deg)", offered(page, words))
    press(page, "Move there", "arrived")


def present(page, x: float, y: float, turn: float) -> None:
    type_into(page, "Part X (mm)", f"{x:g}")
    type_into(page, "Part Y (mm)", f"{y:g}")
    type_into(page, "Part turn (deg)", f"{turn:.1f}")
    press(page, "Present part here", "a new part is on the table")


def part_seen(page) -> tuple[float, float] | None:
    """The top-face centre the tab's "Part seen" says (None while not all four corners are seen)."""
    seen = page.get_by_text("Part seen").first.inner_text()
    found = re.search(r"Part seen: top-face centre X (-?[\d.]+) Y (-?[\d.]+)", seen)
    return None if found is None else (float(found.group(1)), float(found.group(2)))


def seen_at(page, x: float, y: float, within_mm: float | None) -> None:
    """Wait until the tab says Part seen, within ``within_mm`` of X, Y when given (a commissioned cell)."""

    def there() -> bool:
        centre = part_seen(page)
        return centre is not None and (within_mm is None or max(abs(centre[0] - x), abs(centre[1] - y)) < within_mm)

    wait_until(there, f"the part seen at X {x:g}, Y {y:g}; the tab says {page.get_by_text('Part seen').first.inner_text()!r}")


def jog(page, button: str, times: int, axis: int, mm: float) -> None:
    """Step 20 mm / 10 deg, ``button`` pressed ``times``, each waited for on the status line's flange pose."""
    choose(page, "Step", "20 mm / 10 deg")
    for _ in range(times):
        before = flange_of(status_text(page))[axis]
        page.get_by_role("button", name=button, exact=True).click()
        wait_until(lambda: abs(flange_of(status_text(page))[axis] - (before + mm)) < 0.05, f"the flange moved {button}")


def teach_the_guide_job(
    page, shot: Callable[[int, str], None], measured: bool, at_the_pick: Callable[[], None] | None = None
) -> None:
    """The guide's steps 1 .. 8, from (new job) to the job saved as JOB; ``shot`` takes the
    page's picture at each; ``measured``: the cell's model is commissioned (Part seen within 2 mm);
    ``at_the_pick``: what a test does first at step 4, the desired view captured."""
    # 1. Teach tab, Template (new job), Begin teaching.
    page.get_by_role("tab", name="Teach").click()
    choose(page, "Template", "(new job)")
    press(page, "Begin teaching", r"jog to the desired view")
    shot(1, "begin")

    # 2. Present the part: X -390, Y -40, turn 0.
    present(page, PART_X_MM, PART_Y_MM, 0.0)

    # 3. The desired view: the part seen, View the part, capture.
    seen_at(page, PART_X_MM, PART_Y_MM, 2.0 if measured else None)
    if not measured:
        page.get_by_text("This cell was never commissioned").first.wait_for(timeout=10_000)
    press(page, "View the part", "the part in view", AID_TIMEOUT_S)
    press(page, "Capture desired image", "desired image captured")
    shot(2, "desired-view")

    # 4. The pick: Centre the cup on the part, a test pick, set it, suction on.
    if at_the_pick is not None:
        at_the_pick()
    press(page, "Centre the cup on the part", "cup centred on the part", AID_TIMEOUT_S)
    press(page, "Test pick", "grip good")
    press(page, "Set pick pose here", "pick pose set")
    press(page, "Suction on", "reports a part on the cup")
    shot(3, "pick")

    # 5. The place: lift 40 mm, above the pocket, the cup in the pocket, set it (the place
    # check said at once), suction off.
    jog(page, "+Z", 2, axis=2, mm=20.0)
    press(page, "Go above the pocket", "arrived")
    move_to(page, "cup", "Cup in the pocket")
    press(page, "Set place pose here", r"place pose set here: the part sits 0\.\d mm and [+-]0\.\d deg from the pocket")
    assert "WARNING" not in status_text(page)
    shot(4, "place")
    press(page, "Suction off", "reports no part on the cup")

    # 6. The check view: over the placed part, capture it.
    press(page, "Go over the placed part", "arrived")
    press(page, "Capture check view", "check view captured: " + ("the part lies" if measured else "this cell was never"))
    assert "WARNING" not in status_text(page)
    shot(5, "check-view")

    # 7. The start pose: a part where parts arrive, the desired view, 20 mm along -X, set it.
    present(page, PART_X_MM, PART_Y_MM, 0.0)
    press(page, "Go to the desired view", "arrived")
    jog(page, "-X", 1, axis=0, mm=-20.0)
    press(page, "Set start pose here", "start pose set")

    # 8. A new job's settings, Apply settings; name it, Save job.
    press(page, "Apply settings", "settings changed")
    page.get_by_text("Everything is taught").wait_for(timeout=10_000)
    shot(6, "save")
    type_into(page, "Job name", JOB)
    press(page, "Save job", rf"job '{JOB}' saved")


@dataclass(frozen=True)
class Assembled:
    """One run of the guide's job as the page showed it: its number, outcome line and status."""

    run_id: int
    outcome: str  # "Run N: placed ..." and the figures under it
    status: str  # the status line at its end, with the reason

    @property
    def placed(self) -> bool:
        return f"Run {self.run_id}: placed" in self.outcome


def assemble_once(page, x: float, y: float, turn: float, last_run: int, timeout_s: float = 180.0) -> Assembled:
    """A part presented at X, Y turned ``turn`` (the Teach tab's Present part here), the job
    started on the Assemble tab, its end waited for."""
    page.get_by_role("tab", name="Teach").click()
    present(page, x, y, turn)
    page.get_by_role("tab", name="Assemble").click()
    choose(page, "Job", JOB)
    page.get_by_role("button", name="Start", exact=True).click()

    # The run's end (the fast step policy servoes in a handful of cycles: its start may pass unseen).
    def ended() -> bool:
        found = re.search(rf"(Done|FAULT|E-STOPPED) · job {JOB} · run (\d+)", status_text(page))
        return found is not None and int(found.group(2)) > last_run

    wait_until(ended, f"the run after {last_run} of job {JOB} never ended", timeout_s=timeout_s)
    status = status_text(page)
    run_id = int(re.search(r"run (\d+)", status).group(1))
    outcome = page.get_by_text(f"Run {run_id}: ").first
    outcome.wait_for(timeout=10_000)
    return Assembled(run_id, outcome.locator("xpath=..").inner_text(), status)
