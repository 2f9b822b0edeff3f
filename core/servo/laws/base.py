"""What every control law shares: its output, its stages, its verdicts, its safeguards.

A control law is a small immutable object holding its settings and the NOMINAL camera;
``step(features, desired, stage)`` maps one frame's features to a camera twist cVc
(v, w in the camera frame) and the stage to use next cycle. The loop carries the stage,
so a law holds no hidden state and any cycle can be replayed on its own.
Every law regulates an error e = s - s* (current features minus desired ones) with
v = -lambda L+ e (eq. 4-14), the convention of ViSP, so one sign reads the same in every law.
Following ViSP, a law that cannot act returns a zero twist with a failure, and
the loop stops the robot.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, StrEnum
from typing import Protocol

import numpy as np

from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.features import DesiredImage, ImageFeatures

# Below this ratio of smallest to largest singular value a Jacobian is singular: its
# pseudo-inverse would command huge twists for pixel-sized errors.
SINGULAR_RATIO = 1e-6


class Failure(str, Enum):
    """Why a servo run stopped without reaching the desired image."""

    FEATURES_LOST = "features_lost"
    CAMERA_RETREAT = "camera_retreat"
    NO_PROGRESS = "no_progress"
    UNREACHABLE = "unreachable"
    SINGULAR_JACOBIAN = "singular_jacobian"
    ITERATION_LIMIT = "iteration_limit"
    ROBOT_STOPPED = "robot_stopped"  # refused by the safety layer, held, in alarm, or the link failed


class Stage(StrEnum):
    """The stage a control law is in; the loop carries it from one cycle to the next.

    The switching IBVS with laser runs stages 1.A, 1.B, 2 and 3 (section 4.4; 1.C is no
    stage of its own but the translation that goes with every turn of stage 1). Every
    other law has one stage, named after it. A StrEnum, so that recordings, stored runs
    and texts show the thesis's names ("1A", "ibvs") and old recordings read back.
    """

    ALIGN_1A = "1A"  # turn the corners onto the imaginary features (eqs. 4-26 .. 4-29)
    CENTRE_1B = "1B"  # turn the visible region's centroid onto the laser spot (eq. 4-36)
    APPROACH_2 = "2"  # translate on corners and spot at the laser depth (eqs. 4-39 .. 4-49)
    FINISH_3 = "3"  # classic IBVS at the desired features (eqs. 4-50, 4-51)
    IBVS = "ibvs"
    PBVS = "pbvs"
    HYBRID_25D = "2.5d"


@dataclass(frozen=True)
class ControlOutput:
    """One control step.

    cVc: camera twist (v, w) in C, m/s and rad/s; zero when done or failed.
    stage: the stage that produced it (and the one to continue in next cycle).
    error_px: norm of the object-feature error to the desired image (8 coordinates),
      NaN when not every corner is seen: the final criterion of every method.
    stage_error: the error the current stage regulates (a switch threshold applies to it).
    converged / failure: the verdict; note says why (a switch, a lost feature, ...).
    distance_m: the law's estimate of the camera's distance to the part, NaN when it
      makes none; the loop's retreat test then reads it instead of the image area.
    """

    cVc: Matrix
    stage: Stage
    error_px: float
    stage_error: float
    converged: bool = False
    failure: Failure | None = None
    note: str = ""
    distance_m: float = float("nan")

    @classmethod
    def stop(cls, stage: Stage, error_px: float, failure: Failure, note: str) -> ControlOutput:
        return cls(np.zeros(6), stage, error_px, float("nan"), failure=failure, note=note)


class ControlLaw(Protocol):
    """A visual servo control law: one frame's features to a camera twist, e = s - s*."""

    @property
    def name(self) -> str: ...

    @property
    def final_threshold_px(self) -> float:
        """The feature error (px) at or below which it reports convergence."""
        ...

    def step(self, features: ImageFeatures, desired: DesiredImage, stage: Stage | None) -> ControlOutput: ...


class SingularJacobian(VservoError, ValueError):
    """A Jacobian too close to singular to invert."""


def checked_pinv(J: Matrix) -> Matrix:
    """Moore-Penrose pseudo-inverse of J; raises SingularJacobian near a singularity.

    One SVD serves the check and the inverse (every singular value is then well above
    zero, so all of them are inverted).
    """
    if not np.all(np.isfinite(J)):
        raise SingularJacobian("the Jacobian has non-finite entries")
    U, singular_values, Vt = np.linalg.svd(J, full_matrices=False)
    if not singular_values[-1] > SINGULAR_RATIO * singular_values[0]:  # (a zero J too)
        raise SingularJacobian(f"singular values {singular_values.min():.3g} .. {singular_values.max():.3g}")
    return (Vt.T / singular_values) @ U.T


def feature_error_px(features: ImageFeatures, desired: DesiredImage) -> float:
    """||f_d - f|| over the four corners, NaN unless all are seen."""
    if not features.all_corners_visible:
        return float("nan")
    return float(np.linalg.norm(desired.corners_px - features.corners_px))


def verdict_on_all_corners(
    stage: Stage, features: ImageFeatures, error_px: float, final_threshold_px: float
) -> ControlOutput | None:
    """The verdict a law on the four corners reaches before computing anything, or None.

    It stops (zero twist) when a corner is not seen and reports convergence once the
    feature error is below the final threshold; None means: go on and compute the twist.
    """
    if not features.all_corners_visible:
        lost = int((~features.corners_visible).sum())
        return ControlOutput.stop(stage, error_px, Failure.FEATURES_LOST, f"{lost} of 4 corners not seen")
    if error_px <= final_threshold_px:
        return ControlOutput(np.zeros(6), stage, error_px, error_px, converged=True)
    return None
