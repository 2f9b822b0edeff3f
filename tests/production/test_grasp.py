"""Which quarter turn of the taught view a run servoes on, and which grasp it picks and places with."""

from __future__ import annotations

import numpy as np
import pytest

from vservo.core.cell.config import load_cell
from vservo.core.cell.scene import Cube
from vservo.core.geometry.spatial import inverse, rot_x, rot_z, rotation_angle, transform
from vservo.core.production.assembly import winds_up
from vservo.core.production.grasp import (
    allowed_turns,
    grasp_choice,
    image_turn_rad,
    turned_about_cup,
    turned_desired,
    turned_goal,
    view_turns,
)


def turn_deg(bMa, bMb) -> float:
    return float(np.degrees(rotation_angle(bMa[:3, :3].T @ bMb[:3, :3])))


def about_centre(side_m: float, angle_rad: float):
    """A turn of the part's frame about its top face's vertical axis through the centre."""
    centre = transform(t=(side_m / 2, side_m / 2, 0.0))
    return centre @ transform(rot_z(angle_rad)) @ inverse(centre)


def test_the_symmetry_allows_its_quarter_turns_and_nothing_else():
    assert allowed_turns(4) == (0, 1, 2, 3) and allowed_turns(2) == (0, 2) and allowed_turns(1) == (0,)
    with pytest.raises(ValueError, match="grasp symmetry 3"):
        allowed_turns(3)


@pytest.mark.parametrize("k", [1, 2, 3])
def test_the_turned_view_is_the_image_of_the_camera_turned_about_the_part(demo, k):
    """The camera (with its laser) turned by -k quarter turns about the part's vertical axis sees
    the part's corners where the relabelled desired image puts them, and the spot where it was."""
    model, side = load_cell().nominal, demo.part_side_m
    cube = Cube(np.eye(4), side)
    cdMo = demo.desired.cdMo
    turned = turned_desired(demo.desired, side, k)
    # The turned camera: oMc' = T(-k) oMc, so c'Mo = cdMo T(k).
    ctMo = inverse(about_centre(side, -k * np.pi / 2) @ inverse(cdMo))
    np.testing.assert_allclose(ctMo, turned.cdMo, atol=1e-12)

    def seen_from(cMo):
        """The corners' pixels and the spot's pixel and depth from a camera at cMo."""
        corners_c = cube.corners_o @ cMo[:3, :3].T + cMo[:3, 3]
        normal_c = cMo[:3, 2]
        spot_c = model.laser.spot_on_plane(normal_c, float(normal_c @ cMo[:3, 3]))
        return model.camera.project(corners_c), model.camera.project(spot_c)[0], spot_c

    taught_px, taught_spot_px, taught_spot_c = seen_from(cdMo)
    turned_px, turned_spot_px, spot_c = seen_from(ctMo)
    np.testing.assert_allclose(turned_px, np.roll(taught_px, -k, axis=0), atol=1e-9)
    np.testing.assert_allclose(turned.corners_px, np.roll(demo.desired.corners_px, -k, axis=0))
    np.testing.assert_allclose(turned.corner_depths_m, np.roll(demo.desired.corner_depths_m, -k))
    # The beam, turned with the camera, meets the top face (the plane z = 0 of O) at the same pixel and depth.
    np.testing.assert_allclose(turned_spot_px, taught_spot_px, atol=1e-9)
    assert spot_c[2] == pytest.approx(taught_spot_c[2], abs=1e-12)
    assert turned.laser_spot_px is demo.desired.laser_spot_px and turned.depth_m == demo.desired.depth_m
    spot_o = inverse(ctMo) @ np.append(spot_c, 1.0)
    assert np.all((spot_o[:2] > 0) & (spot_o[:2] < side))  # still on the top face


def test_the_view_turned_least_is_chosen_from_the_corners_seen(demo):
    desired, side = demo.desired, demo.part_side_m
    centre = desired.corners_px.mean(axis=0)
    for angle_deg in (-170.0, -100.0, -44.0, 0.0, 30.0, 80.0, 135.0, 179.0):
        c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
        # The part seen turned angle_deg in the image and 40 px aside, corners labelled by its mark.
        seen = (desired.corners_px - centre) @ np.array([[c, s], [-s, c]]) + centre + (40.0, -25.0)
        best = view_turns(seen, desired, side, 4)[0]
        assert abs(np.degrees(best.image_turn_rad)) <= 45.0 + 1e-9, angle_deg
        target = turned_desired(desired, side, best.quarter_turns).corners_px
        assert np.degrees(image_turn_rad(seen, target)) == pytest.approx(np.degrees(best.image_turn_rad))
        half = view_turns(seen, desired, side, 2)
        assert [turn.quarter_turns for turn in half] in ([0, 2], [2, 0]) and abs(np.degrees(half[0].image_turn_rad)) <= 90.0
        assert [turn.quarter_turns for turn in view_turns(seen, desired, side, 1)] == [0]


def test_with_fewer_than_two_corners_seen_the_taught_view_is_kept(demo):
    seen = np.full((4, 2), np.nan)
    seen[1] = demo.desired.corners_px[1]
    turns = view_turns(seen, demo.desired, demo.part_side_m, 4)
    assert len(turns) == 1 and turns[0].quarter_turns == 0 and np.isnan(turns[0].image_turn_rad)
    seen[3] = demo.desired.corners_px[3]  # two corners fix a turn
    assert view_turns(seen, demo.desired, demo.part_side_m, 4)[0].quarter_turns == 0


def test_the_turned_goal_follows_the_part_and_turns_about_its_centre(demo):
    side = demo.part_side_m
    bMo_taught = transform(rot_z(0.3), (-0.4, 0.01, -0.15))
    moved = transform(t=(0.02, -0.01, 0.0)) @ bMo_taught @ about_centre(side, np.radians(50.0))
    for k in range(4):
        goal = turned_goal(demo.taught_bMe, bMo_taught, moved, side, k)
        # The flange keeps its pose relative to the part turned by -k quarter turns about its centre.
        np.testing.assert_allclose(
            inverse(moved @ about_centre(side, -k * np.pi / 2)) @ goal, inverse(bMo_taught) @ demo.taught_bMe, atol=1e-12
        )


def test_a_grasp_turned_about_the_cup_places_the_part_where_the_taught_one_does_whatever_the_cup_model(demo):
    """The pick and the place turned alike: bMe_place_j bMe_pick_j^-1 is the taught one's, so
    the part lands where the taught grasp puts it even with a cup model 10 mm and 5 deg off."""
    eMv = load_cell().nominal.eMv
    wrong_eMv = eMv @ transform(rot_z(np.radians(5.0)), (0.01, -0.006, 0.002))
    bMe_end = demo.taught_bMe
    bMe_pick = bMe_end @ demo.eMe_pick
    taught = demo.bMe_place @ inverse(bMe_pick)
    for cup in (eMv, wrong_eMv):
        for j in range(4):
            pick, place = turned_about_cup(bMe_pick, cup, j), turned_about_cup(demo.bMe_place, cup, j)
            np.testing.assert_allclose(place @ inverse(pick), taught, atol=1e-12)
            # The cup stays where it was (on the part's centre) and turns j quarter turns.
            np.testing.assert_allclose((pick @ eMv)[:3, 3], (bMe_pick @ eMv)[:3, 3], atol=1e-12 if cup is eMv else 0.05)
            assert turn_deg(bMe_pick, pick) == pytest.approx(90.0 * min(j, 4 - j), abs=1e-6)


def test_the_grasp_that_turns_the_flange_least_is_chosen_and_an_unreachable_one_skipped(demo):
    eMv = load_cell().nominal.eMv
    bMe_end = demo.taught_bMe
    # The demo job's cup is taught half a turn from the camera.
    assert turn_deg(bMe_end, bMe_end @ demo.eMe_pick) > 150.0
    best, refused = grasp_choice(bMe_end, demo.eMe_pick, demo.bMe_place, eMv, 4, lambda pick, place: None)
    assert best is not None and best.quarter_turns == 2 and refused == ()
    costs = []
    for j in range(4):
        pick = turned_about_cup(bMe_end @ demo.eMe_pick, eMv, j)
        place = turned_about_cup(demo.bMe_place, eMv, j)
        costs.append(np.radians(turn_deg(bMe_end, pick) + turn_deg(pick, place)))
    assert best.turn_rad == pytest.approx(min(costs))
    second, refused = grasp_choice(
        bMe_end,
        demo.eMe_pick,
        demo.bMe_place,
        eMv,
        4,
        lambda pick, place: "out of reach" if np.allclose(pick, best.bMe_pick) else None,
    )
    assert second is not None and second.quarter_turns != 2 and second.turn_rad > best.turn_rad
    assert refused == ("the grasp turned 180 deg: out of reach",) and second.refused_nearer == refused
    none, refused = grasp_choice(bMe_end, demo.eMe_pick, demo.bMe_place, eMv, 2, lambda pick, place: "joint 6")
    assert none is None and len(refused) == 2 and all("joint 6" in why for why in refused)
    taught, _ = grasp_choice(bMe_end, demo.eMe_pick, demo.bMe_place, eMv, 1, lambda pick, place: None)
    assert taught is not None and taught.quarter_turns == 0 and np.allclose(taught.bMe_pick, bMe_end @ demo.eMe_pick)


def test_a_run_whose_moves_wind_the_wrist_a_full_turn_or_may_is_told():
    def yawed(*degrees):
        return [transform(rot_z(np.radians(d))) @ transform(rot_x(np.pi)) for d in degrees]

    assert not winds_up(yawed(0.0, 30.0, -20.0, 100.0))  # turns -> +30, -50, +120, -100: none in all
    assert winds_up(yawed(0.0, 100.0, -160.0, -60.0))  # +100, +100, +100, +60: a full turn
    assert winds_up(yawed(0.0, 155.0))  # a move near a half turn may go either way round
    assert not winds_up([None, *yawed(10.0)])
