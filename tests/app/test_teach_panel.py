"""The Teach tab's words and numbers, without a browser: the pose entry, the cup pose it
offers for a pick, the image direction of each jog, the next step."""

from __future__ import annotations

import numpy as np
import pytest

from vservo.app.teach_panel import (
    SAVE,
    STEP_FOLDERS,
    PoseEntryError,
    cup_on_part,
    image_direction,
    next_button,
    parse_pose_mm_deg,
    pose_words,
    teach_checklist,
)
from vservo.core.cell.config import load_cell
from vservo.core.geometry.spatial import inverse
from vservo.core.production.jobs import read_job_file
from vservo.core.production.protocol import ControllerState, Phase, Teaching, TeachStep


def test_a_typed_pose_reads_back_as_typed_and_bad_text_is_named():
    text = "-369.10 0.00 7.25 205.00 0.00 180.00"
    assert pose_words(parse_pose_mm_deg(text)) == text
    # Angles as the status line shows them, in [-90, 270): the same pose typed with -155 deg.
    assert pose_words(parse_pose_mm_deg("-369.10 0.00 7.25 -155.00 0.00 -180.00")) == text
    for bad in ("1 2 3", "1 2 3 4 5 x", "1 2 3 4 5 nan"):
        with pytest.raises(PoseEntryError, match="six numbers"):
            parse_pose_mm_deg(bad)


def test_the_cup_pose_offered_on_the_demo_part_is_the_demo_jobs_pick():
    config = load_cell()
    job = read_job_file("static/jobs/demo.json")
    bMv = cup_on_part(config.simulation.scene.cube.bMo)
    np.testing.assert_allclose(bMv @ inverse(config.nominal.eMv), job.taught_bMe @ job.eMe_pick, atol=2e-4)


def test_image_directions_follow_the_camera_looking_down():
    config = load_cell()
    job = read_job_file("static/jobs/demo.json")
    words = {button: image_direction(job.taught_bMe, config.nominal.eMc, button) for button in ("+X", "-X", "+Z", "-Z")}
    assert words["+Z"] == "part smaller" and words["-Z"] == "part larger"
    opposite = {"part left": "part right", "part right": "part left", "part up": "part down", "part down": "part up"}
    assert words["-X"] == opposite[words["+X"]]


def test_the_next_step_follows_the_operators_order():
    def teaching(*taught: TeachStep) -> ControllerState:
        return ControllerState(Phase.TEACHING, teaching=Teaching(frozenset(taught)))

    assert next_button(ControllerState(Phase.IDLE)) == "Begin teaching"
    assert next_button(teaching()) == "Capture desired image"
    state = teaching(TeachStep.DESIRED_IMAGE, TeachStep.PICK_POSE, TeachStep.PLACE_POSE)
    assert next_button(state) == "Capture check view"
    assert "Still to teach: the start pose. Optional: the check view (without it" in teach_checklist(state)
    assert next_button(teaching(*(set(TeachStep) - {TeachStep.START_POSE}))) == "Set start pose here"
    done = teaching(*TeachStep)
    assert next_button(done) == "Save job"
    assert "**Next: Save job**" in teach_checklist(done) and "no part on the cup" in teach_checklist(done)


def test_the_checklist_names_what_is_missing_in_the_drafts_order():
    text = teach_checklist(ControllerState(Phase.TEACHING, teaching=Teaching()))
    assert text.startswith(
        "Still to teach: the desired image, the start pose, the pick pose, the place pose. "
        "Optional: the check view (without it, runs report placement unknown)."
    )


def test_every_step_of_the_draft_has_its_button_in_the_table():
    taught_by = [row.teaches for _, _, rows in STEP_FOLDERS for row in rows if row.teaches]
    assert sorted(taught_by, key=list(TeachStep).index) == list(TeachStep)  # each step once


def test_a_button_is_live_from_the_typed_state_never_from_its_words():
    pick = next(row for _, _, rows in STEP_FOLDERS for row in rows if row.teaches is TeachStep.PICK_POSE)
    before = ControllerState(Phase.TEACHING, detail="desired image captured", teaching=Teaching())
    after = ControllerState(Phase.TEACHING, detail="reworded", teaching=Teaching(frozenset({TeachStep.DESIRED_IMAGE})))
    assert not pick.live(before) and pick.live(after)
    assert not SAVE.live(after) and SAVE.live(ControllerState(Phase.TEACHING, teaching=Teaching(frozenset(TeachStep))))


def test_the_next_step_follows_the_cells_state_not_the_buttons_order():
    def teaching(*taught: TeachStep, held: bool | None = None, holding: bool = False) -> ControllerState:
        return ControllerState(Phase.TEACHING, holding_part=holding, teaching=Teaching(frozenset(taught), held))

    desired = TeachStep.DESIRED_IMAGE
    assert next_button(teaching(desired)) == "Test pick"  # none tried yet
    assert next_button(teaching(desired, held=False)) == "Test pick"  # a failed test pick: the pick again
    assert next_button(teaching(desired, held=True)) == "Set pick pose here"
    picked = (desired, TeachStep.PICK_POSE)
    assert next_button(teaching(*picked)) == "Suction on"
    assert next_button(teaching(*picked, holding=True)) == "Set place pose here"
    placed = (*picked, TeachStep.PLACE_POSE)
    assert next_button(teaching(*placed, holding=True)) == "Suction off"  # the part still on the cup
    assert next_button(teaching(*placed)) == "Capture check view"
    assert next_button(teaching(*TeachStep, holding=True)) == "Suction off"
