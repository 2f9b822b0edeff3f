"""Arms the project can drive, loaded as Pinocchio models from their URDF.

The UPJ comes from robot_models/upj.urdf (generated from its DH table); the UR5 and UR10
from example-robot-data, whose meshes resolve through ``package://example-robot-data/...``
against the package's installed share directory. Any other arm is a URDF file with its
flange frame named after a ``#``: ``/opt/cell/arm.urdf#tool0`` (its joint limits are the
URDF's; meshes are looked for beside it).

The model's root frame b is vservo's base frame. A robot controller may speak its poses
in a frame of its own, u: a Universal Robots controller's ``Base`` is a half turn about z
from the root ``base_link`` of ROS-Industrial's UR descriptions, which name that frame
``base`` (CONTROLLER_BASE_FRAME). ``controller_base`` gives bMu, the identity for an arm
without such a frame (the UPJ, whose JRC speaks in its root).
"""

from __future__ import annotations

import functools
import importlib.metadata
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

ARM_NAMES: tuple[str, ...] = ("upj", "ur5", "ur10")
# example-robot-data's URDF of each UR arm; their flange is ROS-Industrial's tool0
_UR_URDFS = {"ur5": "ur5_robot.urdf", "ur10": "ur10_robot.urdf"}
# ROS-Industrial's name for the frame the arm's controller reports its poses in, fixed to the root
CONTROLLER_BASE_FRAME = "base"


@dataclass(frozen=True)
class ArmDescription:
    """Kinematic tree and geometries of one arm; flange_frame is the tool flange E."""

    name: str
    model: pin.Model
    visual_model: pin.GeometryModel
    collision_model: pin.GeometryModel
    flange_frame: str


def _example_robot_data_share() -> Path:
    # The wheel installs its data under <site-packages>/cmeel.prefix/share; asking the
    # distribution where that lies works for any site or virtual environment.
    # (locate_file is typed as returning a protocol of path-like things; str() of it is its path.)
    try:
        return Path(str(importlib.metadata.distribution("example-robot-data").locate_file("cmeel.prefix/share")))
    except importlib.metadata.PackageNotFoundError as error:
        raise FileNotFoundError("the example-robot-data package is not installed") from error


def is_urdf_arm(name: str) -> bool:
    """Whether ``name`` is a URDF file with its flange frame (``path.urdf#frame``)."""
    path, hash_sign, frame = name.rpartition("#")
    return bool(hash_sign and frame and path.endswith(".urdf"))


def _urdf_and_package_dirs(name: str) -> tuple[Path, list[str], str]:
    if name == "upj":
        return Path(__file__).with_name("upj.urdf"), [], "flange"
    if is_urdf_arm(name):
        path, _, frame = name.rpartition("#")
        return Path(path), [str(Path(path).parent)], frame
    share = _example_robot_data_share()
    urdf = share / "example-robot-data" / "robots" / "ur_description" / "urdf" / _UR_URDFS[name]
    return urdf, [str(share)], "tool0"


def _check_name(name: str) -> None:
    if name not in ARM_NAMES and not is_urdf_arm(name):
        raise ValueError(
            f"unknown arm {name!r}: choose one of {', '.join(ARM_NAMES)}, or a URDF file and its flange frame: path.urdf#frame"
        )


def load_arm(name: str) -> ArmDescription:
    """The arm ``name`` (one of ARM_NAMES, or ``path.urdf#flange_frame``) with its visual and collision geometries."""
    _check_name(name)
    urdf, package_dirs, flange_frame = _urdf_and_package_dirs(name)
    if not urdf.is_file():
        hint = " (run `python -m vservo.robot_models.generate_urdf`)" if name == "upj" else ""
        raise FileNotFoundError(f"URDF of arm {name!r} not found at {urdf}{hint}")
    model, collision_model, visual_model = pin.buildModelsFromUrdf(str(urdf), package_dirs=package_dirs)
    if not model.existFrame(flange_frame):
        raise ValueError(f"{urdf} has no frame {flange_frame!r} for the flange of arm {name!r}")
    return ArmDescription(name, model, visual_model, collision_model, flange_frame)


@functools.cache
def _kinematic_model(name: str) -> tuple[pin.Model, str]:
    """The arm ``name``'s kinematic model (no meshes) and its flange frame."""
    _check_name(name)
    urdf, _, flange_frame = _urdf_and_package_dirs(name)
    if not urdf.is_file():
        raise FileNotFoundError(f"URDF of arm {name!r} not found at {urdf}")
    model = pin.buildModelFromUrdf(str(urdf))
    if not model.existFrame(flange_frame):
        raise ValueError(f"{urdf} has no frame {flange_frame!r} for the flange of arm {name!r}")
    return model, flange_frame


def joint_limits(name: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The arm ``name``'s joint limits in rad, (lower, upper)."""
    model, _ = _kinematic_model(name)
    return tuple(model.lowerPositionLimit), tuple(model.upperPositionLimit)


def controller_base(name: str) -> np.ndarray:
    """bMu: the pose in the model's root frame b of the frame u the arm's controller reports
    and takes its poses in, the URDF's CONTROLLER_BASE_FRAME (identity when it has none).
    A UR5's zero joints put tool0 at (817.25, 191.45, -5.49) mm in b, and the controller
    shows (-817.25, -191.45, -5.49) mm: uMe = inverse(bMu) @ bMe."""
    model, _ = _kinematic_model(name)
    if not model.existFrame(CONTROLLER_BASE_FRAME):
        return np.eye(4)
    frame = model.frames[model.getFrameId(CONTROLLER_BASE_FRAME)]
    if frame.parentJoint != 0:
        raise ValueError(f"arm {name!r}: its frame {CONTROLLER_BASE_FRAME!r} moves with joint {model.names[frame.parentJoint]!r}")
    return np.array(frame.placement.homogeneous)
