"""The state at a glance and the live buttons (app/banner.py's two maps of the phase), no made-up
or leftover poses: without a browser."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from vservo.app.banner import Button, Kind, Situation, banner_for, live_buttons, stage_words
from vservo.app.scene3d import PartTracker
from vservo.app.session import Session
from vservo.app.status import flange_text, status_markdown
from vservo.core.cell.config import load_cell
from vservo.core.geometry.spatial import matrix_from_pose, pose_from_mm_deg, transform
from vservo.core.production.protocol import ControllerState, Outcome, Phase, RunFigures, RunOutcome
from vservo.core.production.protocol.catalogue import Action, RunEnd, explain
from vservo.core.servo.laws.base import Stage


def _done(outcome: Outcome, reason: str) -> ControllerState:
    return ControllerState(Phase.DONE, job="bracket", last_outcome=RunOutcome(outcome, reason))


def _servoing(stage: str) -> ControllerState:
    return ControllerState(Phase.SERVOING, job="bracket", run=RunFigures(1, Stage(stage)))


@pytest.mark.parametrize(
    ("state", "kind", "title", "next_words"),
    [
        (ControllerState(Phase.IDLE), Kind.READY, "READY", "press Start"),
        (ControllerState(Phase.TEACHING, job=None), Kind.BUSY, "TEACHING", "Teach tab"),
        (ControllerState(Phase.COMMISSIONING), Kind.BUSY, "COMMISSIONING", "keep clear"),
        (_servoing("1A"), Kind.BUSY, "RUNNING job bracket: turning to face the part", "keep clear"),
        (_servoing("2"), Kind.BUSY, "RUNNING job bracket: approaching with the laser", "keep clear"),
        (_servoing("3"), Kind.BUSY, "RUNNING job bracket: final alignment", "keep clear"),
        (ControllerState(Phase.PICKING, job="bracket"), Kind.BUSY, "RUNNING job bracket: picking the part", "keep clear"),
        (_done(Outcome.PLACED, "0.2 mm off"), Kind.PLACED, "PLACED: job bracket", "present the next part"),
        (_done(Outcome.MISSED, "2.2 mm off"), Kind.MISSED, "MISSED: job bracket", "Take the part out"),
        (ControllerState(Phase.FAULT, "the vacuum sensor reports no part"), Kind.FAULT, "FAULT", "press Reset"),
        (ControllerState(Phase.ESTOPPED, "e-stop pressed"), Kind.ESTOPPED, "E-STOPPED", "press Reset"),
    ],
)
def test_every_phase_has_its_banner_with_what_to_do_next(state, kind, title, next_words):
    banner = banner_for(state)
    assert (banner.kind, banner.title) == (kind, title)
    assert next_words in banner.next_step
    assert f"background:{kind.value}" in banner.html() and title in banner.html()


def test_the_banner_says_what_failed_and_how_a_run_ended():
    fault = banner_for(ControllerState(Phase.FAULT, "the vacuum sensor reports no part on the cup"))
    assert fault.detail == "the vacuum sensor reports no part on the cup" and "press Reset" in fault.next_step
    missed = banner_for(_done(Outcome.MISSED, "part seen 2.2 mm from its taught place"))
    assert missed.detail == "part seen 2.2 mm from its taught place"
    assert banner_for(ControllerState(Phase.IDLE), controller_gone="exit code 1").kind == Kind.FAULT
    assert "&lt;b&gt;" in banner_for(ControllerState(Phase.FAULT, "<b>")).html()  # the controller's words are text


def test_colours_tell_the_outcomes_apart():
    colours = {kind.value for kind in Kind}
    assert len(colours) == len(Kind)
    assert banner_for(_done(Outcome.PLACED, "")).kind != banner_for(_done(Outcome.MISSED, "")).kind


def test_stage_words_are_plain():
    assert stage_words("1B") == "turning the laser onto the part" and stage_words("9Z") == "9Z"


@pytest.mark.parametrize(
    ("phase", "start", "reset"),
    [
        (Phase.IDLE, True, False),
        (Phase.TEACHING, False, False),
        (Phase.COMMISSIONING, False, False),
        (Phase.SERVOING, False, False),
        (Phase.PICKING, False, False),
        (Phase.PLACING, False, False),
        (Phase.DONE, True, True),
        (Phase.FAULT, True, True),
        (Phase.ESTOPPED, False, True),
    ],
)
def test_start_and_reset_are_live_only_where_the_controller_takes_them(phase, start, reset):
    live = live_buttons(phase, Situation(can_present_part=True))
    assert (Button.START in live) == start
    assert (Button.PRESENT_PART in live) == (start or phase is Phase.TEACHING)  # a part to teach on
    assert (Button.START_COMMISSIONING in live) == start
    assert (Button.RESET in live) == reset


def test_the_apps_own_facts_decide_the_rest():
    assert Button.PRESENT_PART not in live_buttons(Phase.IDLE)  # no part feeder on this cell
    assert Button.APPLY_COMMISSIONING not in live_buttons(Phase.IDLE)
    assert Button.APPLY_COMMISSIONING in live_buttons(Phase.IDLE, Situation(commissioning_to_apply=True))
    assert Button.APPLY_COMMISSIONING not in live_buttons(Phase.SERVOING, Situation(commissioning_to_apply=True))
    idle, calibrating = live_buttons(Phase.IDLE), live_buttons(Phase.IDLE, Situation(calibrating=True))
    assert Button.RUN_CALIBRATION in idle and Button.STOP_CALIBRATION not in idle
    assert Button.STOP_CALIBRATION in calibrating and Button.RUN_CALIBRATION not in calibrating
    assert Button.REPLAY not in idle and Button.REPLAY in live_buttons(Phase.SERVOING, Situation(has_runs=True))


def test_no_flange_pose_is_shown_before_the_robot_was_read():
    text = status_markdown(ControllerState(Phase.IDLE, bMe=np.eye(4), q=np.zeros(0)), operator_present=False)
    assert "flange pose not known yet" in text and "X 0.00" not in text


def test_angles_near_a_half_turn_do_not_flip():
    either_side = [
        flange_text(matrix_from_pose(pose_from_mm_deg([-400.0, 0.0, 300.0, psi, 0.0, 0.0]))) for psi in (179.99, -179.99)
    ]
    assert either_side == [
        "flange X -400.00 Y 0.00 Z 300.00 mm, phi 179.99 theta 0.00 psi 0.00 deg",
        "flange X -400.00 Y 0.00 Z 300.00 mm, phi 180.01 theta 0.00 psi 0.00 deg",
    ]


def test_a_released_part_is_shown_in_the_pocket_not_beside_it():
    config = load_cell()
    tracker = PartTracker(config.nominal.mount, config.nominal.camera)
    side = 0.020
    bMe = matrix_from_pose(pose_from_mm_deg([-400.0, 100.0, 60.0, 180.0, 0.0, 30.0]))
    bMp = transform(t=(-0.395, 0.104, 0.0))  # the pocket, a few mm off where the cup let go
    tracker.update(ControllerState(Phase.PLACING, bMe=bMe, holding_part=True), None, side, bMp)
    released = tracker.update(ControllerState(Phase.PLACING, bMe=bMe, holding_part=False), None, side, bMp)
    bottom_centre = (released @ transform(t=(side / 2, side / 2, -side)))[:3, 3]
    assert bottom_centre == pytest.approx(bMp[:3, 3], abs=1e-9)
    done = tracker.update(ControllerState(Phase.DONE, bMe=bMe, holding_part=False), None, side, bMp)
    assert np.allclose(done, released)


def test_a_new_teach_clears_the_last_runs_charts_and_path():
    session = Session()
    for k in range(1, 4):
        session.on_state(
            ControllerState(
                Phase.SERVOING,
                run=RunFigures(1, None, k, 10.0 / k, np.zeros(6)),
                time_s=float(k),
                bMe=transform(t=(0.01 * k, 0.0, 0.0)),
            )
        )
    assert len(session.view().trace.errors_px) == 3 and len(session.view().trace.path_m) == 3
    session.on_state(ControllerState(Phase.TEACHING, run=RunFigures(1), time_s=5.0))
    assert len(session.view().trace.errors_px) == 0 and len(session.view().trace.path_m) == 0


def test_a_run_fault_is_said_in_the_catalogues_words_with_what_to_do():
    reason = "servo failed: camera_retreat (corner area 4920 px^2, first 8403 px^2)"
    last = RunOutcome(Outcome.FAULT, reason, end=RunEnd.CAMERA_RETREAT)
    for state in (ControllerState(Phase.FAULT, reason, job="demo", last_outcome=last), _done(Outcome.FAULT, reason)):
        banner = banner_for(replace(state, last_outcome=last))
        assert banner.detail == explain(RunEnd.CAMERA_RETREAT).sentence and banner.next_step == Action.COMMISSION.value
        assert "camera_retreat" not in banner.html()  # the engineer's words are the Engineering fold's
    status = status_markdown(ControllerState(Phase.FAULT, reason, job="demo", last_outcome=last), True)
    assert explain(RunEnd.CAMERA_RETREAT).sentence in status and "camera_retreat" not in status


def test_the_running_banner_has_no_empty_stage_and_no_formulas():
    starting = banner_for(ControllerState(Phase.SERVOING, "moving to the start pose", job="shifted", run=RunFigures(3)))
    assert starting.title == "RUNNING job shifted" and starting.detail == "moving to the start pose"
    note = "1A -> 2: ||f_id - f|| = 9.36 px"
    servo = banner_for(ControllerState(Phase.SERVOING, note, job="shifted", run=RunFigures(3, Stage("2"), 12, 9.36)))
    assert servo.detail == "" and "||" not in servo.html()  # the banner stays still: cycles are the status line's


def test_manual_mode_has_its_banner():
    banner = banner_for(ControllerState(Phase.MANUAL))
    assert banner.title == "MANUAL" and "Leave manual mode" in banner.next_step
