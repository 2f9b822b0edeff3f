"""Denavit-Hartenberg table of the Motoman UPJ, the single source of its geometry.

Standard DH as in the thesis, Appendix A, where the arm is built with the Matlab
Robotics Toolbox ``link([alpha a theta d sigma offset])``: frame i follows frame i-1
by Rz(q_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i), and the joint limits bound q_i
(not q_i + offset_i). Lengths in m, angles in rad.

Frame 0 is the robot base (on the mounting plane, z up along axis 1) and frame 6 the
tool flange E. ``robot_models/upj.urdf`` is generated from this table.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import pi, radians


@dataclass(frozen=True)
class DhLink:
    """One row of a standard DH table, with the limits of its joint variable q."""

    alpha: float
    a: float
    d: float
    offset: float
    lower: float
    upper: float


UPJ_DH: tuple[DhLink, ...] = (
    DhLink(alpha=pi / 2, a=0.0, d=0.29, offset=0.0, lower=radians(-160), upper=radians(160)),
    DhLink(alpha=0.0, a=0.26, d=0.0, offset=pi / 2, lower=radians(-85), upper=radians(90)),
    DhLink(alpha=pi / 2, a=0.0, d=0.0, offset=0.0, lower=radians(55), upper=radians(175)),
    DhLink(alpha=pi / 2, a=0.0, d=0.27, offset=0.0, lower=radians(-170), upper=radians(170)),
    DhLink(alpha=-pi / 2, a=0.0, d=0.0, offset=0.0, lower=radians(-120), upper=radians(120)),
    DhLink(alpha=0.0, a=0.0, d=0.09, offset=0.0, lower=radians(-360), upper=radians(360)),
)
