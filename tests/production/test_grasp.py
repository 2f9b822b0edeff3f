"""Which of a square part's quarter-turned grasps a run picks and places it with."""

from __future__ import annotations

import numpy as np
import pytest

from vservo.core.cell.config import load_cell
from vservo.core.geometry.spatial import rotation_angle
from vservo.core.production.grasp import grasp_choice, turned_grasp


@pytest.fixture(scope="module")
def pick(demo):
    """(the flange at the servo's end, the taught pick from there, the part in the pick flange)."""
    model = load_cell().nominal
    bMe_end = demo.taught_bMe
    pMo = np.linalg.inv(demo.eMe_pick) @ model.eMc @ demo.desired.cdMo
    return bMe_end, bMe_end @ demo.eMe_pick, pMo


def turn_deg(bMa, bMb) -> float:
    return float(np.degrees(rotation_angle(bMa[:3, :3].T @ bMb[:3, :3])))


def test_a_turned_grasp_holds_the_part_at_the_same_point_the_same_way_up(demo, pick):
    _, bMe_pick, pMo = pick
    centre_o = np.array([demo.part_side_m / 2, demo.part_side_m / 2, 0.0, 1.0])
    for k in range(4):
        bMe_k = turned_grasp(bMe_pick, pMo, demo.part_side_m, 4, k)
        assert np.allclose(bMe_k @ pMo @ centre_o, bMe_pick @ pMo @ centre_o, atol=1e-12)
        assert np.allclose((bMe_k @ pMo)[:3, 2], (bMe_pick @ pMo)[:3, 2], atol=1e-12)  # the face's normal
        assert turn_deg(bMe_pick, bMe_k) == pytest.approx(90.0 * min(k, 4 - k), abs=1e-6)


def test_the_grasp_that_turns_the_flange_least_is_chosen(demo, pick):
    bMe_end, bMe_pick, pMo = pick
    # The demo job's cup is taught half a turn from the camera.
    assert turn_deg(bMe_end, bMe_pick) > 150.0
    choice = grasp_choice(bMe_pick, pMo, demo.part_side_m, 4, bMe_end, reachable=lambda bMe: True)
    assert choice.turns == 2 and choice.unreachable_nearer == 0
    assert np.degrees(choice.turn_rad) == pytest.approx(turn_deg(bMe_end, choice.bMe)) and choice.turn_rad < np.pi / 4
    others = [turn_deg(bMe_end, turned_grasp(bMe_pick, pMo, demo.part_side_m, 4, k)) for k in range(4)]
    assert np.degrees(choice.turn_rad) == pytest.approx(min(others))


def test_an_unreachable_grasp_is_skipped_for_the_next_least_turning(demo, pick):
    bMe_end, bMe_pick, pMo = pick
    best = grasp_choice(bMe_pick, pMo, demo.part_side_m, 4, bMe_end, reachable=lambda bMe: True)
    choice = grasp_choice(bMe_pick, pMo, demo.part_side_m, 4, bMe_end, reachable=lambda bMe: not np.allclose(bMe, best.bMe))
    assert choice.turns in (1, 3) and choice.unreachable_nearer == 1
    assert choice.turn_rad > best.turn_rad


def test_with_no_grasp_in_reach_the_taught_one_is_kept_for_its_move_to_say_why(demo, pick):
    bMe_end, bMe_pick, pMo = pick
    choice = grasp_choice(bMe_pick, pMo, demo.part_side_m, 4, bMe_end, reachable=lambda bMe: False)
    assert choice.turns == 0 and choice.unreachable_nearer == 4
    assert np.allclose(choice.bMe, bMe_pick)


def test_the_next_pose_counts_in_the_turn(demo, pick):
    """A place is chosen for the turn to it and on to the check pose after it."""
    _, bMe_pick, pMo = pick
    side = demo.part_side_m
    bMe_from = turned_grasp(bMe_pick, pMo, side, 9, 1)  # 40 deg on the way to the first quarter turn
    alone = grasp_choice(bMe_pick, pMo, side, 4, bMe_from, reachable=lambda bMe: True)
    onward = grasp_choice(
        bMe_pick, pMo, side, 4, bMe_from, reachable=lambda bMe: True, bMe_next=turned_grasp(bMe_pick, pMo, side, 4, 1)
    )
    assert alone.turns == 0 and np.degrees(alone.turn_rad) == pytest.approx(40.0)
    assert onward.turns == 1 and np.degrees(onward.turn_rad) == pytest.approx(50.0)


def test_a_part_without_symmetry_keeps_its_taught_grasp(demo, pick):
    bMe_end, bMe_pick, pMo = pick
    choice = grasp_choice(bMe_pick, pMo, demo.part_side_m, 1, bMe_end, reachable=lambda bMe: True)
    assert choice.turns == 0 and np.allclose(choice.bMe, bMe_pick)
    half = grasp_choice(bMe_pick, pMo, demo.part_side_m, 2, bMe_end, reachable=lambda bMe: True)
    assert half.turns == 1 and turn_deg(bMe_end, half.bMe) < 45.0
    with pytest.raises(ValueError, match="grasp symmetry 3"):
        grasp_choice(bMe_pick, pMo, demo.part_side_m, 3, bMe_end, reachable=lambda bMe: True)
