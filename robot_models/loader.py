"""Arms the project can drive, loaded as Pinocchio models from their URDF.

The UPJ comes from robot_models/upj.urdf (generated from its DH table); the UR5 and UR10
from example-robot-data, whose meshes resolve through ``package://example-robot-data/...``
against the package's installed share directory. Any other arm is a URDF file with its
flange frame named after a ``#``: ``/opt/cell/arm.urdf#tool0`` (its joint limits are the
URDF's; meshes are looked for beside it).
"""

from __future__ import annotations

import functools
import importlib.metadata
from dataclasses import dataclass
from pathlib import Path

import pinocchio as pin

ARM_NAMES: tuple[str, ...] = ("upj", "ur5", "ur10")
# example-robot-data's URDF of each UR arm; their flange is ROS-Industrial's tool0
_UR_URDFS = {"ur5": "ur5_robot.urdf", "ur10": "ur10_robot.urdf"}


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
def joint_limits(name: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The arm ``name``'s joint limits in rad, (lower, upper): its kinematic model only, no meshes."""
    _check_name(name)
    urdf, _, flange_frame = _urdf_and_package_dirs(name)
    if not urdf.is_file():
        raise FileNotFoundError(f"URDF of arm {name!r} not found at {urdf}")
    model = pin.buildModelFromUrdf(str(urdf))
    if not model.existFrame(flange_frame):
        raise ValueError(f"{urdf} has no frame {flange_frame!r} for the flange of arm {name!r}")
    return tuple(model.lowerPositionLimit), tuple(model.upperPositionLimit)
