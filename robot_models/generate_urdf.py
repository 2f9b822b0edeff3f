"""URDF of a serial arm from its standard-DH table.

Standard DH chains frame i to frame i-1 by Rz(q_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i).
A URDF joint applies its fixed origin first and its rotation about z last, so the chain
is regrouped: URDF link i is frame i-1 turned by Rz(offset_i + q_i), joint i's origin is
the previous row's constant part Tz(d_{i-1}) Tx(a_{i-1}) Rx(alpha_{i-1}) followed by
Rz(offset_i), and a fixed ``flange`` link carries the last row's constant part. The
flange link is thus exactly DH frame n, the tool flange E.

Geometry is made of primitives sized from the table: a plinth the base stands on, a
cylinder along z for each d, a box along x for each a and a drum around each joint
axis, with radii tapering from shoulder to wrist. Visual and collision shapes are the
same primitives.

``python -m vservo.robot_models.generate_urdf`` writes robot_models/upj.urdf from UPJ_DH.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from vservo.core.geometry.spatial import Matrix, rot_x, rot_z, rpy_from_rotation, transform
from vservo.robot_models.upj_dh import UPJ_DH, DhLink

UPJ_URDF_PATH = Path(__file__).with_name("upj.urdf")

# Primitive radii as fractions of the arm's span sum(|a| + |d|): 0.068 m at the
# shoulder down to 0.041 m at the wrist for the UPJ's 0.91 m.
SHOULDER_RADIUS_PER_SPAN = 0.075
WRIST_RADIUS_PER_SPAN = 0.045

MATERIALS = {"body": "0.05 0.3 0.65 1", "base": "0.25 0.25 0.28 1"}


def dh_constant_part(link: DhLink) -> Matrix:
    """Tz(d) Tx(a) Rx(alpha): the part of a standard-DH row that follows the joint rotation."""
    return transform(t=(0.0, 0.0, link.d)) @ transform(t=(link.a, 0.0, 0.0)) @ transform(rot_x(link.alpha))


def _number(value: float) -> str:
    # Shortest repr that round-trips the double; float noise around zero is snapped so
    # that the file reads "0.0" where the table has a zero.
    value = float(value)
    return repr(0.0 if abs(value) < 1e-12 else value)


def _numbers(values) -> str:
    return " ".join(_number(v) for v in values)


def _sizes(*values: float) -> str:
    # Primitive shapes are approximations: a tenth of a millimetre is plenty.
    return " ".join(_number(round(v, 4)) for v in values)


def _origin(parent: ET.Element, pMc: Matrix) -> None:
    # URDF rpy is (roll, pitch, yaw) with R = Rz(yaw) Ry(pitch) Rx(roll), the same
    # composition as eq. 2-13 whose (phi, theta, psi) are (yaw, pitch, roll).
    phi, theta, psi = rpy_from_rotation(pMc[:3, :3])
    ET.SubElement(parent, "origin", xyz=_numbers(pMc[:3, 3]), rpy=_numbers((psi, theta, phi)))


def _add_shape(link: ET.Element, material: str, center: Sequence[float], shape: str, **size: str) -> None:
    """The same primitive as a visual and a collision of ``link``, centred at ``center``."""
    for kind in ("visual", "collision"):
        element = ET.SubElement(link, kind)
        ET.SubElement(element, "origin", xyz=_sizes(*center), rpy="0 0 0")
        ET.SubElement(ET.SubElement(element, "geometry"), shape, **size)
        if kind == "visual":
            ET.SubElement(element, "material", name=material)


def _add_link_shapes(link: ET.Element, row: DhLink, radius: float, with_joint_drum: bool) -> None:
    """Primitives of one DH link in its URDF frame (DH frame i-1 turned by the joint)."""
    if with_joint_drum:
        _add_shape(link, "body", (0.0, 0.0, 0.0), "cylinder", radius=_sizes(radius), length=_sizes(2.0 * radius))
    if abs(row.d) > 1e-9:
        _add_shape(link, "body", (0.0, 0.0, row.d / 2.0), "cylinder", radius=_sizes(0.8 * radius), length=_sizes(abs(row.d)))
    if abs(row.a) > 1e-9:
        _add_shape(link, "body", (row.a / 2.0, 0.0, row.d), "box", size=_sizes(abs(row.a), 1.6 * radius, 1.6 * radius))


def urdf_from_dh(
    name: str,
    links: Sequence[DhLink],
    *,
    effort_nm: float = 50.0,
    velocity_rad_s: float = 3.0,
) -> str:
    """URDF text of the arm ``links`` (base_link, link_1..link_n, joint_1..joint_n, flange).

    effort_nm and velocity_rad_s are written as every joint's limits; the project only
    uses the kinematics, so they are nominal figures for tools that require them.
    """
    span = sum(abs(row.a) + abs(row.d) for row in links)
    radii = np.linspace(SHOULDER_RADIUS_PER_SPAN, WRIST_RADIUS_PER_SPAN, len(links)) * span

    robot = ET.Element("robot", name=name)
    for material, rgba in MATERIALS.items():
        ET.SubElement(ET.SubElement(robot, "material", name=material), "color", rgba=rgba)

    # Joint 1 turns on the plinth, which stands on the mounting plane z = 0 of frame 0.
    base = ET.SubElement(robot, "link", name="base_link")
    plinth_side, plinth_height = 3.0 * radii[0], 1.2 * radii[0]
    _add_shape(base, "base", (0.0, 0.0, plinth_height / 2.0), "box", size=_sizes(plinth_side, plinth_side, plinth_height))

    parent, parent_constant = "base_link", np.eye(4)
    for i, (row, radius) in enumerate(zip(links, radii), start=1):
        joint = ET.SubElement(robot, "joint", name=f"joint_{i}", type="revolute")
        _origin(joint, parent_constant @ transform(rot_z(row.offset)))
        ET.SubElement(joint, "parent", link=parent)
        ET.SubElement(joint, "child", link=f"link_{i}")
        ET.SubElement(joint, "axis", xyz="0 0 1")
        ET.SubElement(
            joint,
            "limit",
            lower=_number(row.lower),
            upper=_number(row.upper),
            effort=_number(effort_nm),
            velocity=_number(velocity_rad_s),
        )
        link = ET.SubElement(robot, "link", name=f"link_{i}")
        _add_link_shapes(link, row, radius, with_joint_drum=i > 1)
        parent, parent_constant = f"link_{i}", dh_constant_part(row)

    flange_joint = ET.SubElement(robot, "joint", name="flange_joint", type="fixed")
    _origin(flange_joint, parent_constant)
    ET.SubElement(flange_joint, "parent", link=parent)
    ET.SubElement(flange_joint, "child", link="flange")
    ET.SubElement(robot, "link", name="flange")

    ET.indent(robot, space="  ")
    header = (
        f"<!-- Generated by robot_models/generate_urdf.py (urdf_from_dh) from a {len(links)}-link "
        "standard-DH table. Do not edit: change the table and rerun "
        "`python -m vservo.robot_models.generate_urdf`. -->"
    )
    return f'<?xml version="1.0"?>\n{header}\n{ET.tostring(robot, encoding="unicode")}\n'


def main() -> None:
    UPJ_URDF_PATH.write_text(urdf_from_dh("upj", UPJ_DH), encoding="utf-8")
    print(f"wrote {UPJ_URDF_PATH}")


if __name__ == "__main__":
    main()
