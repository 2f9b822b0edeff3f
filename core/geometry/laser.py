"""The laser pointer mounted rigidly next to the camera, and depth from its spot.

The beam leaves the origin of the laser frame L along L's +z axis; ``cMl`` is the pose
of L in the camera frame C (the thesis's cHl). Where the beam hits the part, the
camera sees a spot; the viewing ray through that spot and the beam itself cross at the
spot, which gives the depth Z the interaction matrix needs.

In the thesis configuration (Fig. 4-2) the laser sits on the camera's x axis at the
baseline d and the beam stays in the camera's x-z plane, tilted towards the optical
axis so that it makes the angle alpha with the baseline. ``LaserPointer.in_plane``
builds that pose and ``in_plane_range`` is the closed form of eqs. 4-18 .. 4-21;
``LaserPointer.triangulate`` handles any calibrated cMl.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.spatial import Matrix, rot_y, transform

# A spot's pixel (u, v), as a pair of numbers or a 2-vector.
Pixel = Sequence[float] | Matrix

# Below this sine of the angle between two lines (about 1e-6 rad) they are parallel
# for any purpose: the crossing point would sit kilometres away.
_PARALLEL_SIN2 = 1e-12


def _frozen(values: ArrayLike, shape: tuple[int, ...], name: str) -> Matrix:
    """A read-only float copy of ``values``, so frozen dataclasses really are frozen."""
    array = np.array(values, dtype=float)
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    array.flags.writeable = False
    return array


@dataclass(frozen=True, eq=False)
class Ray:
    """A half-line origin + s * direction, s >= 0, in whatever frame its owner says.

    ``direction`` is normalised on construction, so s is a distance in metres.
    """

    origin: Matrix
    direction: Matrix

    def __post_init__(self) -> None:
        direction = np.asarray(self.direction, dtype=float)
        norm = float(np.linalg.norm(direction))
        if not norm > 0.0:
            raise ValueError(f"a ray needs a non-zero direction, got {self.direction}")
        object.__setattr__(self, "origin", _frozen(self.origin, (3,), "origin"))
        object.__setattr__(self, "direction", _frozen(direction / norm, (3,), "direction"))

    def point_at(self, s: ArrayLike) -> Matrix:
        """The point (3,) at distance s along the ray, or the points (N, 3) for s of shape (N,)."""
        s = np.asarray(s, dtype=float)
        return self.origin + s[..., np.newaxis] * self.direction

    def transformed(self, aMb: ArrayLike) -> Ray:
        """This ray, given in frame b, expressed in frame a."""
        aMb = np.asarray(aMb, dtype=float)
        return Ray(aMb[:3, :3] @ self.origin + aMb[:3, 3], aMb[:3, :3] @ self.direction)

    def intersect_plane(self, normal: ArrayLike, offset: float) -> float | None:
        """Distance s >= 0 at which the ray meets the plane {p : normal . p = offset}.

        ``normal`` need not be unit. None when the ray is parallel to the plane or the
        plane lies behind the origin: the ray misses, which is an ordinary outcome when
        casting rays into a scene, not an error.
        """
        normal = np.asarray(normal, dtype=float)
        approach = float(normal @ self.direction)
        if abs(approach) <= 1e-12 * float(np.linalg.norm(normal)):
            return None
        s = (offset - float(normal @ self.origin)) / approach
        return s if s >= 0.0 else None


@dataclass(frozen=True, eq=False)
class LaserDepth:
    """The spot triangulated from the camera's viewing ray and the laser beam.

    ``point_c`` is the point of the viewing ray closest to the beam, in the camera frame:
    the detection is what was measured, the beam is what was calibrated.
    ``depth_m`` is its Z, ``range_m`` its distance from the camera centre along the
    viewing ray, and ``ray_gap_m`` the distance between the two lines at their closest
    points: zero for a perfect calibration and detection, so a growing gap says that
    cMl, the intrinsics, or the spot detector is off.
    """

    depth_m: float
    range_m: float
    point_c: Matrix
    ray_gap_m: float


@dataclass(frozen=True, eq=False)
class LaserPointer:
    """A laser pointer at pose cMl in the camera frame; the beam runs along L's +z axis."""

    cMl: Matrix

    def __post_init__(self) -> None:
        cMl = _frozen(self.cMl, (4, 4), "cMl")
        R = cMl[:3, :3]
        if not (np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0.0):
            raise ValueError("cMl must hold a rotation matrix (orthonormal, det +1)")
        object.__setattr__(self, "cMl", cMl)

    @classmethod
    def in_plane(cls, baseline_m: float, alpha_rad: float) -> LaserPointer:
        """The thesis configuration (Fig. 4-2): laser at (d, 0, 0) in C, beam in C's x-z plane.

        The beam makes the angle alpha with the baseline (from the laser back towards the
        lens), so it leans towards the optical axis and crosses it at Z = d tan(alpha):
        cMl = transl(d, 0, 0) Ry(alpha - pi/2), and the beam direction is
        (-cos alpha, 0, sin alpha). The thesis cHl = [30 0 0 0 -10 0] (mm, deg) is
        in_plane(0.030, radians(80)).
        """
        return cls(transform(rot_y(alpha_rad - np.pi / 2.0), (baseline_m, 0.0, 0.0)))

    @property
    def origin_c(self) -> Matrix:
        """Where the beam leaves the laser, in the camera frame (m)."""
        return self.cMl[:3, 3]

    @property
    def direction_c(self) -> Matrix:
        """Unit direction of the beam in the camera frame."""
        return self.cMl[:3, 2]

    def beam(self, wMc: ArrayLike | None = None) -> Ray:
        """The beam as a ray in frame w, given the camera pose wMc; in the camera frame if omitted."""
        beam_c = Ray(self.origin_c, self.direction_c)
        return beam_c if wMc is None else beam_c.transformed(wMc)

    def spot_on_plane(self, n_c: ArrayLike, offset_c: float) -> Matrix | None:
        """Where the beam hits the plane {p : n_c . p = offset_c}, as a point (3,) in the camera frame.

        None when the beam misses: it runs parallel to the plane, or the plane is behind the laser.
        """
        beam_c = self.beam()
        s = beam_c.intersect_plane(n_c, offset_c)
        return None if s is None else beam_c.point_at(s)

    def triangulate(self, camera: CameraModel, spot_px: Pixel) -> LaserDepth:
        """Depth of the laser spot seen at pixel ``spot_px`` (2,), for any calibrated cMl.

        The viewing ray r through the undistorted spot and the beam o + s b are two lines
        that should meet at the spot. With k = r . b, the closest points are at
            t = (r . o - k b . o) / (1 - k^2)  along the viewing ray,
            s = t k - b . o                    along the beam.

        Raises ValueError when the two lines are parallel (no crossing), or when they
        cross behind the camera (t <= 0) or behind the laser (s <= 0): neither spot
        could have been made by this beam, so the detection or the calibration is wrong.
        """
        r = camera.ray(spot_px)[0]
        if np.isnan(r).any():
            raise ValueError(f"pixel {spot_px} has no viewing ray (undistortion failed)")
        o, b = self.origin_c, self.direction_c
        k = float(r @ b)
        sin2 = 1.0 - k * k
        if sin2 < _PARALLEL_SIN2:
            raise ValueError(f"the viewing ray through {spot_px} is parallel to the laser beam")
        t = (float(r @ o) - k * float(b @ o)) / sin2
        s = t * k - float(b @ o)
        if t <= 0.0:
            raise ValueError(f"the viewing ray through {spot_px} meets the beam behind the camera")
        if s <= 0.0:
            raise ValueError(f"the viewing ray through {spot_px} meets the beam behind the laser")
        point_c = t * r
        point_c.flags.writeable = False
        return LaserDepth(
            depth_m=float(point_c[2]),
            range_m=t,
            point_c=point_c,
            ray_gap_m=float(np.linalg.norm(point_c - (o + s * b))),
        )


def in_plane_range(spot_px: Pixel, camera: CameraModel, baseline_m: float, alpha_rad: float) -> tuple[float, float]:
    """(range_m, depth_m) of the spot for the in-plane laser of Fig. 4-2, eqs. 4-18 .. 4-21.

    The spot's image radius r along the baseline (signed, positive on the laser's side,
    which is +x in OpenCV's axes) sets the angle of the viewing ray to the optical axis,
    beta = atan(r / lambda); with
    r / lambda = (u - u0) s_x / lambda this is the undistorted normalized x of the spot.
    The law of sines in the triangle lens - spot - laser then gives
        Z = d sin(alpha) / cos(alpha - beta)                         (eq. 4-21)
    where the thesis's Z is the distance from the lens to the spot *along the viewing
    ray*, i.e. the range. The depth along the optical axis is Z cos(beta).

    The model assumes the beam lies in the camera's x-z plane, so the spot's offset
    across the baseline (v - v0) is ignored. ``baseline_m`` must be positive (laser on
    the camera's +x side) and alpha in (0, pi). Raises ValueError when the viewing ray
    and the beam do not meet in front of the camera.
    """
    if not baseline_m > 0.0:
        raise ValueError(f"baseline_m must be positive (laser on the camera's +x side), got {baseline_m}")
    if not 0.0 < alpha_rad < np.pi:
        raise ValueError(f"alpha_rad must lie in (0, pi), got {alpha_rad}")
    tan_beta = camera.pixel_to_normalized(spot_px)[0, 0]
    beta = float(np.arctan(tan_beta))
    cos_at_spot = float(np.cos(alpha_rad - beta))
    if not cos_at_spot > 0.0:
        raise ValueError(f"the viewing ray through {spot_px} does not meet the beam in front of the camera")
    range_m = baseline_m * float(np.sin(alpha_rad)) / cos_at_spot
    return range_m, range_m * float(np.cos(beta))
