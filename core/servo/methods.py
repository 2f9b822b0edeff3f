"""The four servo methods of the thesis and the control law each one builds on a cell.

A method's law needs only the NOMINAL cell model and a few settings, the same for the
simulation study, a replayed recording and an assembly job on the cell.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from vservo.core.cell.config import CellModel
from vservo.core.geometry.spatial import inverse
from vservo.core.servo.laws.base import ControlLaw
from vservo.core.servo.laws.hybrid import Hybrid25D
from vservo.core.servo.laws.ibvs import ClassicIbvs
from vservo.core.servo.laws.laser_ibvs import LaserIbvs
from vservo.core.servo.laws.pbvs import Pbvs
from vservo.core.servo.laws.robust_laser_ibvs import RobustLaserIbvs

METHODS = ("laser", "ibvs", "pbvs", "2.5d")


class LaserLaw(StrEnum):
    """Which switching IBVS with laser the laser method runs."""

    THESIS = "thesis"  # section 4.4 as the thesis gives it: the study's reproduction
    ROBUST = "robust"  # robust to calibration error (core/servo/laws/robust_laser_ibvs.py)


@dataclass(frozen=True)
class LawSettings:
    """What a control law may change; the defaults are the thesis's (all gains 1)."""

    method: str = "laser"
    gain: float = 1.0
    k_rotation: float = 1.0  # K2 of the laser method (eq. 4-49)
    ibvs_interaction: str = "current"
    ibvs_depth: str = "exact"
    pbvs_pose: str = "pnp"
    final_threshold_px: float = 1.0
    laser_law: LaserLaw = LaserLaw.THESIS


def build_law(model: CellModel, settings: LawSettings) -> ControlLaw:
    """The control law of ``settings.method`` on the nominal cell ``model``."""
    camera, gain, final = model.camera, settings.gain, settings.final_threshold_px
    if settings.method == "laser":
        law = RobustLaserIbvs if settings.laser_law is LaserLaw.ROBUST else LaserIbvs
        return law(
            camera,
            cTe=inverse(model.eMc)[:3, 3],
            laser=model.laser,
            k_rotation_1a=gain,
            k_rotation_1b=gain,
            k_translation=gain,
            k_rotation=settings.k_rotation * gain,
            k_final=gain,
            final_threshold_px=final,
        )
    if settings.method == "ibvs":
        return ClassicIbvs(camera, gain, settings.ibvs_interaction, settings.ibvs_depth, final)
    if settings.method == "pbvs":
        return Pbvs(camera, gain, settings.pbvs_pose, final)
    if settings.method == "2.5d":
        return Hybrid25D(camera, gain, final)
    raise ValueError(f"unknown method {settings.method!r}: choose one of {', '.join(METHODS)}")
