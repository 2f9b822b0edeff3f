"""Arms the project can drive, loaded as Pinocchio models from their URDF.

The UPJ comes from robot_models/upj.urdf (generated from its DH table); the UR5 from
example-robot-data, whose meshes resolve through ``package://example-robot-data/...``
against the package's installed share directory.
"""

from __future__ import annotations

import functools
import importlib.metadata
from dataclasses import dataclass
from pathlib import Path

import pinocchio as pin

ARM_NAMES: tuple[str, ...] = ("upj", "ur5")


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


def _urdf_and_package_dirs(name: str) -> tuple[Path, list[str], str]:
    if name == "upj":
        return Path(__file__).with_name("upj.urdf"), [], "flange"
    share = _example_robot_data_share()
    urdf = share / "example-robot-data" / "robots" / "ur_description" / "urdf" / "ur5_robot.urdf"
    return urdf, [str(share)], "tool0"


def load_arm(name: str) -> ArmDescription:
    """The arm ``name`` (one of ARM_NAMES) with its visual and collision geometries."""
    if name not in ARM_NAMES:
        raise ValueError(f"unknown arm {name!r}: choose one of {', '.join(ARM_NAMES)}")
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
    if name not in ARM_NAMES:
        raise ValueError(f"unknown arm {name!r}: choose one of {', '.join(ARM_NAMES)}")
    urdf, _, _ = _urdf_and_package_dirs(name)
    model = pin.buildModelFromUrdf(str(urdf))
    return tuple(model.lowerPositionLimit), tuple(model.upperPositionLimit)
