"""The laser's beam, measured from its spot on the board (docs/calibration.md,
"Commissioning a cell").

In each view the camera sees the spot and knows where the board lies (cMboard from the
camera calibration), so the spot's viewing ray cut with the board plane is a point of
the beam in the camera frame. Views at different distances give points along the beam;
the line through them (least squares, by SVD) is the beam. The beam is what
``LaserPointer`` needs: a line. Where along it the laser sits, and how the pointer is
turned about it, no spot can show; cMl is therefore written in a fixed form: z along the
beam (towards the scene), origin where the beam crosses the camera's plane z_c = 0, y the
camera's y made orthogonal to the beam. For the thesis's in-plane laser this is exactly
``LaserPointer.in_plane(d, alpha)`` (eqs. 4-18 .. 4-21), and d and alpha are reported
for any beam: d the distance from the camera centre to that origin, alpha the angle
between the beam and the baseline back to the camera centre.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from vservo.core.calibration.cell_calibration import Verdict, read_only
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.spatial import Matrix, transform

# A line through points a few centimetres apart tilts by their noise over that span:
# 0.1 mm over 50 mm is 0.1 deg. The spot's noise (~0.3 px) puts each point ~0.1 mm off
# at 300 mm; beyond 0.5 mm RMS a spot was misfound or the board's pose is wrong.
MIN_DEPTH_SPAN_MM = 50.0
MAX_LINE_RMS_MM = 0.5
MIN_SPOTS = 3


@dataclass(frozen=True, eq=False)
class LaserCalibration:
    """The beam as cMl (module docstring), d (m) and alpha (rad), the points it was fitted
    to (N, 3) in the camera frame, their RMS distance from it (mm), their depth span
    (mm), and the verdict."""

    cMl: Matrix
    baseline_m: float
    alpha_rad: float
    points_c: Matrix
    rms_mm: float
    depth_span_mm: float
    verdict: Verdict


def beam_cMl(origin_c: Matrix, direction_c: Matrix) -> Matrix:
    """cMl of the line origin + s direction (module docstring): z along the beam, pointing
    away from the camera plane, origin on z_c = 0, y the camera's y orthogonal to z."""
    z = np.asarray(direction_c, dtype=float) / np.linalg.norm(direction_c)
    if z[2] < 0.0:
        z = -z
    if z[2] < 1e-6:
        raise ValueError("the beam runs parallel to the camera's plane: it never reaches the scene in view")
    origin = np.asarray(origin_c, dtype=float)
    origin = origin - (origin[2] / z[2]) * z
    y = np.array([0.0, 1.0, 0.0]) - z[1] * z
    if np.linalg.norm(y) < 1e-6:
        raise ValueError("the beam runs along the camera's y axis: it never reaches the scene in view")
    y /= np.linalg.norm(y)
    return transform(np.column_stack((np.cross(y, z), y, z)), origin)


def fit_laser_beam(camera: CameraModel, spots_px: Matrix, cMboard_list: Sequence[Matrix]) -> LaserCalibration:
    """The beam through the spots seen on the board (module docstring).

    ``spots_px`` (N, 2): the spot in each view; ``cMboard_list``: the board's pose in that
    view. A ValueError when a spot's ray misses its board or there are fewer than
    ``MIN_SPOTS``. Verdict: retake when the points span less than ``MIN_DEPTH_SPAN_MM`` of
    depth (the direction is then poorly fixed) or lie more than ``MAX_LINE_RMS_MM`` RMS
    from the line.
    """
    spots = np.atleast_2d(np.asarray(spots_px, dtype=float))
    if len(spots) != len(cMboard_list):
        raise ValueError(f"one board pose per spot: {len(spots)} spots, {len(cMboard_list)} board poses")
    if len(spots) < MIN_SPOTS:
        raise ValueError(f"a beam needs at least {MIN_SPOTS} spots (a line through two has no residual), got {len(spots)}")
    rays = np.column_stack((camera.pixel_to_normalized(spots), np.ones(len(spots))))
    points = np.empty((len(spots), 3))
    for k, (ray, cMboard) in enumerate(zip(rays, cMboard_list)):
        normal, origin = np.asarray(cMboard, dtype=float)[:3, 2], np.asarray(cMboard, dtype=float)[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = float(normal @ origin) / float(normal @ ray)
        if not (np.isfinite(s) and s > 0.0):
            raise ValueError(f"the viewing ray of spot {k} at {spots[k].tolist()} px does not meet its view's board")
        points[k] = s * ray
    centre = points.mean(axis=0)
    _, _, Vt = np.linalg.svd(points - centre)
    cMl = beam_cMl(centre, Vt[0])
    direction, origin = cMl[:3, 2], cMl[:3, 3]
    offsets = points - centre
    rms_mm = 1000.0 * float(np.sqrt(np.mean(np.sum((offsets - np.outer(offsets @ direction, direction)) ** 2, axis=1))))
    span_mm = 1000.0 * float(np.ptp(points[:, 2]))
    baseline = float(np.linalg.norm(origin))
    alpha = float(np.arccos(np.clip(-direction @ origin / baseline, -1.0, 1.0)))
    faults = []
    if span_mm < MIN_DEPTH_SPAN_MM:
        faults.append(
            f"the spots span {span_mm:.0f} mm of depth (at least {MIN_DEPTH_SPAN_MM:.0f}): "
            "take views nearer to and farther from the board"
        )
    if rms_mm > MAX_LINE_RMS_MM:
        faults.append(
            f"the points lie {rms_mm:.2f} mm RMS from one line (at most {MAX_LINE_RMS_MM}): "
            "a spot was misfound or the board's pose is off"
        )
    verdict = Verdict.of(
        faults,
        f"line RMS {rms_mm:.3f} mm over {span_mm:.0f} mm of depth, d {1000 * baseline:.1f} mm, alpha {np.degrees(alpha):.2f} deg",
    )
    return LaserCalibration(read_only(cMl), baseline, alpha, read_only(points), rms_mm, span_mm, verdict)


def beam_line_error(cMl_a: Matrix, cMl_b: Matrix, depth_m: float) -> tuple[float, float]:
    """(angle between the two beams in deg, distance in mm between where they cross the
    plane z_c = depth_m): how differently two calibrations put the spot at that depth."""
    crossings = []
    for cMl in (np.asarray(cMl_a, dtype=float), np.asarray(cMl_b, dtype=float)):
        origin, direction = cMl[:3, 3], cMl[:3, 2]
        if abs(direction[2]) < 1e-9:
            raise ValueError("a beam parallel to the camera's plane never crosses z_c = depth")
        crossings.append(origin + ((depth_m - origin[2]) / direction[2]) * direction)
    a, b = np.asarray(cMl_a, dtype=float)[:3, 2], np.asarray(cMl_b, dtype=float)[:3, 2]
    # atan2 of sine and cosine keeps small angles that an arccos of the cosine rounds away.
    angle = np.arctan2(np.linalg.norm(np.cross(a, b)), float(a @ b))
    return float(np.degrees(angle)), 1000.0 * float(np.linalg.norm(crossings[0] - crossings[1]))
