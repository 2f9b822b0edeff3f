"""The operator guide on a cell never commissioned: issue 26's end-to-end proof.

`vservo virtual-cell --truth static/truths/table-5-5.toml`: the true cell is Table 5-5's
errors away from its cell file (the intrinsics 20 % off, the principal point 60 px off, the
hand-eye 20 mm and 5 deg off, the laser 2 mm and 4 deg off); `vservo serve` on the nominal
cell file it prints, never commissioned. In Chromium, the operator teaches a new job from
(new job) following docs/operator-guide.md word for word (tests/e2e/guide_steps.py), then
assembles it 20 times on parts presented up to 30 mm from where it was taught and turned
anywhere on the circle: at least 19 end inside the pocket within 0.3 mm by the virtual
cell's gauge (the truth), and any other is refused before the pick with what to do. The
demo job, taught on the shipped simulated cell, is refused before anything moves, saying
to commission the cell or teach the job again. The figures go to
$VSERVO_ARTIFACTS/guide-uncommissioned-runs.txt.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest

from tests.e2e.gauged_cell import GAUGE_MM, gauged_virtual_cell, operator_page_on
from tests.e2e.guide_steps import PART_X_MM, PART_Y_MM, assemble_once, teach_the_guide_job
from vservo.app.browser import choose, status_text, wait_for_status
from vservo.core.production.protocol.catalogue import Refusal, explain

TOKEN = "guide-uncommissioned-token"
TRUTH = Path(__file__).resolve().parents[2] / "static" / "truths" / "table-5-5.toml"
ARTIFACTS = Path(os.environ.get("VSERVO_ARTIFACTS", Path(__file__).resolve().parents[2] / "test-artifacts"))
RUNS = 20
OFFSET_MM = 30.0


@pytest.fixture(scope="module")
def virtual_cell():
    with gauged_virtual_cell("--seed", "5", "--truth", str(TRUTH)) as cell_and_gauge:
        yield cell_and_gauge


@pytest.fixture(scope="module")
def page(virtual_cell, tmp_path_factory, chromium):
    with operator_page_on(virtual_cell[0], tmp_path_factory.mktemp("serve-data"), chromium, TOKEN) as operator:
        yield operator


def test_the_demo_job_of_the_shipped_cell_is_refused_before_moving(page):
    page.get_by_role("tab", name="Assemble").click()
    choose(page, "Job", "demo")
    before = status_text(page)
    page.get_by_role("button", name="Start", exact=True).click()
    explanation = explain(Refusal.CELL_NOT_COMMISSIONED)  # the notice, in the catalogue's words
    page.get_by_text(explanation.sentence).first.wait_for(timeout=30_000)
    assert explanation.action.value in " ".join(page.locator(".mantine-Notification-root").all_inner_texts())
    refusal = page.get_by_text("was taught on another cell").first  # the controller's own words, in the Engineering fold
    refusal.wait_for(state="attached", timeout=10_000)
    words = refusal.text_content() or ""
    assert "commission this cell" in words and "teach the job again" in words, words
    assert "Servoing" not in status_text(page), (before, status_text(page))


# Under load the check view once judged placed parts about 52 mm off: a busy host handed it
# a frame from before the move to the check pose. A miss is now confirmed on a second look a
# second later (docs/vision.md, "A host too busy to read its camera"); 20 of 20 placed at
# load averages of 9 to 19 since (docs/benchmarks.md).
def test_a_job_taught_as_the_guide_says_places_parts_turned_anyhow_on_a_cell_never_commissioned(page, virtual_cell):
    _, gauge = virtual_cell
    teach_the_guide_job(page, lambda number, name: None, measured=False)
    gauge.releases(2.0)  # the test picks' and the place's, while teaching
    rng = np.random.default_rng(26)
    lines, errors, wrong, run_id = [], [], [], 0
    for run in range(1, RUNS + 1):
        radius, angle = OFFSET_MM * np.sqrt(rng.uniform()), rng.uniform(0.0, 2.0 * np.pi)
        x, y, turn = PART_X_MM + radius * np.cos(angle), PART_Y_MM + radius * np.sin(angle), rng.uniform(-180.0, 180.0)
        assembled = assemble_once(page, round(x, 1), round(y, 1), round(turn, 1), run_id)
        run_id = assembled.run_id
        gauged = gauge.releases(10.0 if assembled.placed else 1.0)
        where = f"run {run}: part {radius:.1f} mm off, turned {turn:+.1f} deg"
        said = assembled.outcome.splitlines()[0]
        if assembled.placed and len(gauged) == 1 and gauged[0]["inside"] and gauged[0]["placement_error_mm"] <= GAUGE_MM:
            errors.append(float(gauged[0]["placement_error_mm"]))
            lines.append(f"{where}: placed, gauge {errors[-1]:.3f} mm")
        else:
            lines.append(f"{where}: {said}; gauge {gauged}")
            # Anything but a placement: refused before the pick, saying what to do, nothing released.
            if assembled.placed or gauged or "refused before" not in said or "present the part nearer" not in said:
                wrong.append(lines[-1])
        if "FAULT" in assembled.status:
            page.get_by_role("button", name=re.compile("^Reset")).click()
            wait_for_status(page, r"Idle")
    lines.append(
        f"placed {len(errors)} of {RUNS}; gauge min {min(errors):.3f}, median {float(np.median(errors)):.3f}, "
        f"max {max(errors):.3f} mm"
    )
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "guide-uncommissioned-runs.txt").write_text("\n".join(lines) + "\n")
    assert len(errors) >= RUNS - 1 and not wrong, lines
