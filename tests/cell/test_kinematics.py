"""Kinematics of the arms against computations that do not go through Pinocchio's model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vservo.core.cell.kinematics import ArmKinematics, ToolMount, UnreachableTarget
from vservo.core.geometry.spatial import inverse, rot_x, rot_y, rot_z, theta_u, transform
from vservo.robot_models.generate_urdf import UPJ_URDF_PATH, urdf_from_dh
from vservo.robot_models.loader import ARM_NAMES, load_arm
from vservo.robot_models.upj_dh import UPJ_DH

# A camera off the flange axis and tilted, so that errors in the tool frames show.
MOUNT = ToolMount(
    eMc=transform(rot_x(0.3) @ rot_z(1.0), (0.05, -0.03, 0.08)),
    eMl=transform(rot_y(-0.2), (-0.04, 0.02, 0.06)),
    eMv=transform(t=(0.0, 0.0, 0.12)),
)


@pytest.fixture(scope="module")
def arms() -> dict[str, ArmKinematics]:
    return {name: ArmKinematics(load_arm(name), MOUNT) for name in ARM_NAMES}


def random_q(arm: ArmKinematics, rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(arm.lower, arm.upper)


def dh_flange_pose(q: np.ndarray) -> np.ndarray:
    """0M6 of the UPJ as the product of standard-DH matrices (Craig/Spong form)."""
    M = np.eye(4)
    for link, qi in zip(UPJ_DH, q):
        th, al = qi + link.offset, link.alpha
        M = M @ np.array(
            [
                [np.cos(th), -np.sin(th) * np.cos(al), np.sin(th) * np.sin(al), link.a * np.cos(th)],
                [np.sin(th), np.cos(th) * np.cos(al), -np.cos(th) * np.sin(al), link.a * np.sin(th)],
                [0.0, np.sin(al), np.cos(al), link.d],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
    return M


def errors(aMb: np.ndarray, aMc: np.ndarray) -> tuple[float, float]:
    """(m, rad) between two poses; the angle from theta-u keeps precision near zero."""
    return float(np.linalg.norm(aMb[:3, 3] - aMc[:3, 3])), float(np.linalg.norm(theta_u(aMb[:3, :3].T @ aMc[:3, :3])))


def test_upj_fk_matches_dh_product(arms):
    arm, rng = arms["upj"], np.random.default_rng(1)
    worst = max(np.abs(arm.fk(q) - dh_flange_pose(q)).max() for q in (random_q(arm, rng) for _ in range(200)))
    assert worst < 1e-9


def test_committed_urdf_is_generated_from_table():
    assert UPJ_URDF_PATH.read_text(encoding="utf-8") == urdf_from_dh("upj", UPJ_DH)


def test_upj_joint_limits_come_from_table(arms):
    np.testing.assert_array_equal(arms["upj"].lower, [link.lower for link in UPJ_DH])
    np.testing.assert_array_equal(arms["upj"].upper, [link.upper for link in UPJ_DH])


@pytest.mark.parametrize("name", ARM_NAMES)
def test_tool_frames_are_mounted_on_flange(arms, name):
    arm, q = arms[name], random_q(arms[name], np.random.default_rng(2))
    bMe = arm.fk(q)
    for frame, eMx in (("camera", MOUNT.eMc), ("laser", MOUNT.eMl), ("vacuum_cup", MOUNT.eMv)):
        np.testing.assert_allclose(arm.fk(q, frame), bMe @ eMx, atol=1e-12)


@pytest.mark.parametrize("name", ARM_NAMES)
@pytest.mark.parametrize("frame", ["flange", "camera"])
def test_ik_round_trip(arms, name, frame):
    arm, rng = arms[name], np.random.default_rng(3)
    for _ in range(10):
        bMf = arm.fk(random_q(arm, rng), frame)
        solution = arm.ik(bMf, random_q(arm, rng), frame)
        translation, rotation = errors(arm.fk(solution.q, frame), bMf)
        assert translation < 1e-8 and rotation < 1e-8
        assert arm.within_limits(solution.q)


def test_ik_from_nearby_seed_stays_on_its_branch(arms):
    arm, rng = arms["upj"], np.random.default_rng(4)
    q = np.deg2rad([10.0, 45.0, 150.0, 5.0, -75.0, 20.0])
    solution = arm.ik(arm.fk(q), q + rng.normal(0.0, 0.02, 6))
    np.testing.assert_allclose(solution.q, q, atol=1e-8)


def test_far_target_is_beyond_reach(arms):
    with pytest.raises(UnreachableTarget, match=r"1\.\d+ m from the shoulder .* beyond the reach 0\.620 m"):
        arms["upj"].ik(transform(t=(1.5, 0.0, 0.3)), np.zeros(6))


def test_target_folded_against_shoulder_does_not_converge(arms):
    # 0.1 m from the shoulder is within the links' span, but the elbow cannot fold
    # that far (joint_3 >= 55 deg keeps the wrist 0.39 m from the shoulder).
    with pytest.raises(UnreachableTarget, match=r"did not converge .* mm / .* deg"):
        arms["upj"].ik(transform(rot_x(np.pi), (0.1, 0.0, 0.29)), np.deg2rad([0, 45, 150, 0, -75, 0]))


@pytest.mark.parametrize("name", ARM_NAMES)
@pytest.mark.parametrize("frame", ["flange", "camera"])
def test_body_jacobian_matches_finite_differences(arms, name, frame):
    """Column k is d/dh of the relative pose fM(q)^-1 fM(q + h e_k) at h = 0, as (t, theta u)."""
    arm, rng, h = arms[name], np.random.default_rng(5), 1e-6
    for _ in range(5):
        q = random_q(arm, rng)
        bMf_inv = inverse(arm.fk(q, frame))

        def local_motion(dq: np.ndarray) -> np.ndarray:
            fMf = bMf_inv @ arm.fk(q + dq, frame)
            return np.concatenate((fMf[:3, 3], theta_u(fMf[:3, :3])))

        columns = [(local_motion(h * e) - local_motion(-h * e)) / (2.0 * h) for e in np.eye(arm.dof)]
        np.testing.assert_allclose(arm.jacobian(q, frame), np.column_stack(columns), atol=1e-8)


def test_ur5_loads_with_meshes():
    ur5 = load_arm("ur5")
    assert ur5.flange_frame == "tool0" and ur5.model.nq == 6
    assert ur5.visual_model.ngeoms > 0 and ur5.collision_model.ngeoms > 0
    assert all(Path(g.meshPath).is_file() for g in ur5.visual_model.geometryObjects)


def test_upj_has_primitive_geometry_on_every_moving_link():
    upj = load_arm("upj")
    links_with_shapes = {upj.model.names[g.parentJoint] for g in upj.collision_model.geometryObjects}
    assert links_with_shapes == set(upj.model.names)  # universe (the plinth) and joint_1..joint_6


def test_unknown_arm_names_the_choices():
    with pytest.raises(ValueError, match=r"'kuka'.*upj, ur5"):
        load_arm("kuka")


def test_kinematics_does_not_touch_the_description():
    description = load_arm("upj")
    frames_before = description.model.nframes
    arm = ArmKinematics(description, MOUNT)
    arm.with_joint_placement_errors(np.random.default_rng(0), 1e-3, 1e-3)
    assert description.model.nframes == frames_before
    assert not description.model.existFrame("camera")


def test_joint_placement_errors(arms):
    arm = arms["upj"]
    q = np.deg2rad([10.0, 45.0, 150.0, 5.0, -75.0, 20.0])
    nominal = arm.fk(q, "camera")

    true_arm = arm.with_joint_placement_errors(np.random.default_rng(7), 1e-3, np.deg2rad(0.1))
    translation, rotation = errors(true_arm.fk(q, "camera"), nominal)
    # Six joints, 1 mm and 1.7 mrad per axis acting over ~0.5 m levers: millimetres.
    assert 5e-4 < translation < 2e-2 and 5e-4 < rotation < 2e-2
    np.testing.assert_array_equal(arm.fk(q, "camera"), nominal)

    same = arm.with_joint_placement_errors(np.random.default_rng(7), 1e-3, np.deg2rad(0.1))
    np.testing.assert_array_equal(same.fk(q, "camera"), true_arm.fk(q, "camera"))
    other = arm.with_joint_placement_errors(np.random.default_rng(8), 1e-3, np.deg2rad(0.1))
    assert np.abs(other.fk(q, "camera") - true_arm.fk(q, "camera")).max() > 1e-5


def test_with_mount_moves_only_the_tools(arms):
    arm, q = arms["upj"], np.deg2rad([10.0, 45.0, 150.0, 5.0, -75.0, 20.0])
    bare = arm.with_mount(ToolMount())
    np.testing.assert_array_equal(bare.fk(q), arm.fk(q))
    np.testing.assert_allclose(bare.fk(q, "camera"), arm.fk(q), atol=1e-15)


@pytest.mark.parametrize("method", ["fk", "jacobian", "within_limits"])
def test_wrong_length_q_is_rejected(arms, method):
    with pytest.raises(ValueError, match=r"expects q of shape \(6,\), got \(5,\)"):
        getattr(arms["upj"], method)(np.zeros(5))


def test_wrong_length_seed_is_rejected(arms):
    arm = arms["upj"]
    with pytest.raises(ValueError, match=r"got \(7,\)"):
        arm.ik(arm.fk(np.deg2rad([0, 45, 150, 0, -75, 0])), np.zeros(7))


def test_unknown_frame_is_rejected(arms):
    with pytest.raises(ValueError, match="'gripper'"):
        arms["upj"].fk(np.zeros(6), "gripper")
