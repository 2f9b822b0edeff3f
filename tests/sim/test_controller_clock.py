"""The emulated controller's clock, counted against sums done by hand."""

import pytest

from vservo.core.sim.controller_clock import ControllerClock, Ended
from vservo.core.study.cell_time_bench import phase_floors

MOVL_REQUEST_S, MOVL_REPLY_S = 0.111, 0.025  # a MOVL and its 0000 at 9600 baud
WAIT_REQUEST_S, WAIT_REPLY_S = 0.031, 0.022  # a JWAIT and its answer
READ_S = 0.05, 0.06  # an RPOSC's request and its pose


def a_move(clock: ControllerClock, motion_s: float, waits_running: int) -> None:
    """MOVL, ``waits_running`` JWAITs that find the arm moving, the JWAIT that finds it stopped."""
    clock.count("MOVL", MOVL_REQUEST_S, MOVL_REPLY_S, motion_s, Ended.SILENT)
    for _ in range(waits_running):
        clock.count("JWAIT", WAIT_REQUEST_S, 0.025, 0.0, Ended.RUNNING)
    clock.count("JWAIT", WAIT_REQUEST_S, WAIT_REPLY_S, 0.0, Ended.ENDED)


@pytest.mark.parametrize("waits_running", [0, 1, 7])
def test_a_move_counts_its_command_its_motion_and_the_answer_that_it_ended(waits_running):
    clock = ControllerClock()
    a_move(clock, 4.0, waits_running)
    assert clock.now_s == pytest.approx(MOVL_REQUEST_S + 4.0 + WAIT_REPLY_S)


def test_a_motion_shorter_than_what_crosses_meanwhile_ends_when_the_line_is_free():
    clock = ControllerClock()
    a_move(clock, 0.01, 0)
    assert clock.now_s == pytest.approx(MOVL_REQUEST_S + MOVL_REPLY_S + WAIT_REQUEST_S + WAIT_REPLY_S)


def test_a_motion_cut_short_ends_where_it_stopped_and_other_commands_count_whole():
    clock = ControllerClock()
    clock.count("RPOSC", *READ_S, 0.0, Ended.SILENT)
    clock.count("MOVL", MOVL_REQUEST_S, MOVL_REPLY_S, 4.0, Ended.SILENT)
    clock.cut(1.5)  # a hold 1.5 s into the motion
    clock.count("JWAIT", WAIT_REQUEST_S, WAIT_REPLY_S, 0.0, Ended.ENDED)
    assert clock.now_s == pytest.approx(sum(READ_S) + MOVL_REQUEST_S + 1.5 + WAIT_REPLY_S)


def test_the_floor_counts_one_pose_read_and_each_move_and_the_rest_shows_above_it():
    """Two phases, a move each; the second phase reads the pose twice more than it needs:
    the floor of each phase is its move and (the first) one read, the clock has those
    reads above it."""
    clock = ControllerClock()
    clock.count("RPOSC", *READ_S, 0.0, Ended.SILENT)
    a_move(clock, 2.0, 3)
    first_s = clock.now_s
    clock.count("RPOSC", *READ_S, 0.0, Ended.SILENT)
    clock.count("RPOSC", *READ_S, 0.0, Ended.SILENT)
    a_move(clock, 1.0, 1)
    phases = phase_floors(clock.exchanges, 0.0, {"start": first_s, "pick": clock.now_s - first_s})
    move_s = MOVL_REQUEST_S + WAIT_REPLY_S
    assert [p.moves for p in phases] == [1, 1]
    assert phases[0].floor_s == pytest.approx(sum(READ_S) + 2.0 + move_s) == pytest.approx(phases[0].measured_s)
    assert phases[1].floor_s == pytest.approx(1.0 + move_s)
    assert phases[1].measured_s - phases[1].floor_s == pytest.approx(2 * sum(READ_S))
