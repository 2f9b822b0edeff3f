"""docs/operator-guide.md's "Teaching a new job", followed word for word in Chromium.

`vservo serve` as a real process, headless Chromium as the operator's browser. The test
does what the guide says, step by step, from "(new job)" (no template), with the values
the page shows (tests/e2e/guide_steps.py): it teaches a new job on a part presented 40 mm
from where the demo job's part lies, saves it, and assembles it three times, each on a
newly presented part: placed each time. Each teach step's page goes to
$VSERVO_DOC_IMAGES (docs/images: the guide's pictures are made so) or else
$VSERVO_ARTIFACTS (default test-artifacts/, not versioned) as guide-NN-step.png. Chromium
must be at /usr/bin/chromium: a missing browser fails the test, it never skips it.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.chromium import chromium_or_fail, headless_chromium
from tests.e2e.guide_steps import PART_X_MM, PART_Y_MM, assemble_once, teach_the_guide_job
from vservo.app.browser import ServeProcess, dismiss_notifications, open_pages, take_control

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


def shot(page, number: int, name: str) -> None:
    IMAGES.mkdir(parents=True, exist_ok=True)
    dismiss_notifications(page)
    page.screenshot(path=str(IMAGES / f"guide-{number:02d}-{name}.png"))


def test_teach_a_new_job_as_the_guide_says_and_assemble_it_three_times(page):
    take_control(page, TOKEN)
    teach_the_guide_job(page, lambda number, name: shot(page, number, name), measured=True)

    # Assemble it three times, each on a newly presented part.
    outcomes, run_id = [], 0
    for run, (x, y, turn) in enumerate(ARRIVALS, start=1):
        assembled = assemble_once(page, x, y, turn, run_id)
        run_id = assembled.run_id
        assert assembled.placed, (run, assembled.outcome, assembled.status)
        outcomes.append(assembled.outcome)  # the figures under the outcome
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "guide-runs.txt").write_text("\n".join(outcomes) + "\n")  # the figures, for the record
