"""Pinhole camera with lens distortion: the sensor on the robot flange.

Conventions (OpenCV's, not the thesis's):

* Camera frame C: z along the optical axis (forward), x to the right of the image,
  y down. A point cP = (X, Y, Z) has normalized coordinates x = X/Z, y = Y/Z and
  pixel coordinates u = fx x + u0, v = fy y + v0. The thesis flips its image axes
  (eq. 2-6: x_d = -(u - u0) s_x); nothing here does.
* Distortion maps *undistorted* normalized coordinates to *distorted* ones with
  OpenCV's radial-tangential model (k1, k2, p1, p2, k3), so the coefficients of
  ``cv2.calibrateCamera`` drop straight in. The thesis writes the opposite direction
  in metric image units (x_u = x_d + k1 x_d r_d^2, eqs. 2-4, 2-5); those coefficients
  are not interchangeable with these.
* Pixel coordinates follow OpenCV: the pixel in row r and column c has its centre at
  (u, v) = (c, r), so the image covers [-0.5, width - 0.5] x [-0.5, height - 0.5]. The
  renderer and the detectors use the same convention. (The thesis's principal point
  (320, 240) is then half a pixel off the sensor's centre, well within any calibration.)

Shapes: every function takes N points as an (N, k) array or a single point as a (k,)
array, and always returns the 2-D (N, ...) result (N = 1 for a single point).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from vservo.core.geometry.spatial import Matrix

# Newton on the distortion model converges quadratically; this many steps is far more
# than a realistic lens needs to reach machine precision anywhere inside the image.
_UNDISTORT_MAX_STEPS = 30
_UNDISTORT_TOLERANCE = 1e-14


def as_points(values: ArrayLike, dim: int, name: str = "points") -> Matrix:
    """``values`` as an (N, dim) float array; a single (dim,) point becomes (1, dim)."""
    points = np.atleast_2d(np.asarray(values, dtype=float))
    if points.ndim != 2 or points.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}) or ({dim},), got {np.shape(values)}")
    return points


def _require_positive(name: str, value: float) -> None:
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be positive and finite, got {value!r}")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels: focal lengths (fx, fy), principal point (u0, v0), image size."""

    fx: float
    fy: float
    u0: float
    v0: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "width", "height"):
            _require_positive(name, getattr(self, name))

    @classmethod
    def from_sensor(
        cls,
        focal_length_m: float,
        pixel_size_m: tuple[float, float],
        principal_point_px: tuple[float, float],
        image_size_px: tuple[int, int],
    ) -> Intrinsics:
        """Intrinsics from a data sheet: lens focal length lambda and pixel pitch (s_x, s_y).

        fx = lambda / s_x and fy = lambda / s_y (eq. 2-6 without the thesis's sign flip).
        ``image_size_px`` is (width, height).
        """
        _require_positive("focal_length_m", focal_length_m)
        sx, sy = pixel_size_m
        _require_positive("pixel_size_m[0]", sx)
        _require_positive("pixel_size_m[1]", sy)
        width, height = image_size_px
        _require_positive("image_size_px[0] (width)", width)
        _require_positive("image_size_px[1] (height)", height)
        u0, v0 = principal_point_px
        return cls(
            fx=focal_length_m / sx,
            fy=focal_length_m / sy,
            u0=float(u0),
            v0=float(v0),
            width=int(width),
            height=int(height),
        )

    @property
    def K(self) -> Matrix:
        """The 3x3 camera matrix [[fx, 0, u0], [0, fy, v0], [0, 0, 1]]."""
        return np.array([[self.fx, 0.0, self.u0], [0.0, self.fy, self.v0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Distortion:
    """OpenCV radial (k1, k2, k3) and tangential (p1, p2) coefficients, on normalized coordinates."""

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    def as_opencv(self) -> Matrix:
        """The coefficient vector (k1, k2, p1, p2, k3) that OpenCV functions expect."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def is_zero(self) -> bool:
        return not np.any(self.as_opencv())


@dataclass(frozen=True)
class CameraModel:
    """A calibrated camera: intrinsics plus lens distortion (see the module docstring)."""

    intrinsics: Intrinsics
    distortion: Distortion = field(default_factory=Distortion)

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.intrinsics.width, self.intrinsics.height

    def project(self, cP: ArrayLike) -> Matrix:
        """Pixels (N, 2), distortion included, of points cP (N, 3) or (3,) in the camera frame.

        Points on or behind the camera plane (Z <= 0) have no image: their rows are NaN.
        """
        cP = as_points(cP, 3, "cP")
        Z = cP[:, 2:3]
        in_front = Z > 0.0
        xn = np.where(in_front, cP[:, :2] / np.where(in_front, Z, 1.0), np.nan)
        return self.normalized_to_pixel(xn)

    def distort(self, xn: ArrayLike) -> Matrix:
        """Distorted normalized coordinates (N, 2) of undistorted ones xn (N, 2) or (2,).

        OpenCV's model, with r^2 = x^2 + y^2:
        x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
        y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
        """
        xn = as_points(xn, 2, "xn")
        d = self.distortion
        x, y = xn[:, 0], xn[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))
        xd = x * radial + 2.0 * d.p1 * x * y + d.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * x * y
        return np.column_stack((xd, yd))

    def undistort(self, xd: ArrayLike) -> Matrix:
        """Undistorted normalized coordinates (N, 2) of distorted ones xd (N, 2) or (2,).

        The model has no closed-form inverse: Newton's method on distort(x) = xd with the
        analytic 2x2 Jacobian, started at x = xd, to a residual of 1e-14. Points where it
        does not converge (strong distortion far outside the calibrated field, where the
        model folds over) come back as NaN rather than as a wrong answer.
        """
        xd = as_points(xd, 2, "xd")
        if self.distortion.is_zero:
            return xd.copy()
        d = self.distortion
        xn = xd.copy()
        # Diverging points overflow on their way to NaN; that is reported by the NaN itself.
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            for _ in range(_UNDISTORT_MAX_STEPS):
                residual = self.distort(xn) - xd
                # NaN compares False: points without an image do not keep the loop going.
                if not np.any(np.abs(residual) > _UNDISTORT_TOLERANCE):
                    break
                x, y = xn[:, 0], xn[:, 1]
                r2 = x * x + y * y
                radial = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))
                radial_dr2 = d.k1 + r2 * (2.0 * d.k2 + 3.0 * r2 * d.k3)
                dxx = radial + 2.0 * x * x * radial_dr2 + 2.0 * d.p1 * y + 6.0 * d.p2 * x
                dyy = radial + 2.0 * y * y * radial_dr2 + 6.0 * d.p1 * y + 2.0 * d.p2 * x
                dxy = 2.0 * x * y * radial_dr2 + 2.0 * d.p1 * x + 2.0 * d.p2 * y
                # The Jacobian [[dxx, dxy], [dxy, dyy]] is symmetric: invert it in closed form.
                det = dxx * dyy - dxy * dxy
                xn[:, 0] -= (dyy * residual[:, 0] - dxy * residual[:, 1]) / det
                xn[:, 1] -= (dxx * residual[:, 1] - dxy * residual[:, 0]) / det
            unconverged = ~np.all(np.abs(self.distort(xn) - xd) <= _UNDISTORT_TOLERANCE, axis=1)
        xn[unconverged] = np.nan
        return xn

    def pixel_to_normalized(self, uv: ArrayLike) -> Matrix:
        """Undistorted normalized coordinates (N, 2) of pixels uv (N, 2) or (2,)."""
        uv = as_points(uv, 2, "uv")
        k = self.intrinsics
        xd = np.column_stack(((uv[:, 0] - k.u0) / k.fx, (uv[:, 1] - k.v0) / k.fy))
        return self.undistort(xd)

    def normalized_to_pixel(self, xn: ArrayLike) -> Matrix:
        """Pixels (N, 2), distortion included, of undistorted normalized coordinates xn (N, 2) or (2,)."""
        xd = self.distort(xn)
        k = self.intrinsics
        return np.column_stack((k.fx * xd[:, 0] + k.u0, k.fy * xd[:, 1] + k.v0))

    def ray(self, uv: ArrayLike) -> Matrix:
        """Unit viewing directions (N, 3) in the camera frame through pixels uv (N, 2) or (2,)."""
        xn = self.pixel_to_normalized(uv)
        directions = np.column_stack((xn, np.ones(len(xn))))
        return directions / np.linalg.norm(directions, axis=1, keepdims=True)

    def in_view(self, uv: ArrayLike, margin_px: float = 0.0) -> NDArray[np.bool_]:
        """(N,) mask of points on the sensor, [-0.5, size - 0.5], shrunk by ``margin_px``; NaN is outside."""
        uv = as_points(uv, 2, "uv")
        width, height = self.image_size
        low = margin_px - 0.5
        # NaN compares False, so points without an image are never in view.
        return (
            (uv[:, 0] >= low) & (uv[:, 0] <= width - 0.5 - margin_px) & (uv[:, 1] >= low) & (uv[:, 1] <= height - 0.5 - margin_px)
        )


def sony_xc55() -> CameraModel:
    """The thesis camera, Sony XC-55 (Table 3-1): 6 mm lens, 7.4 um square pixels, 640 x 480.

    The principal point is the image centre and distortion is neglected, as in the
    thesis, so fx = fy = 6 / 0.0074 = 810.8 px.
    """
    intrinsics = Intrinsics.from_sensor(
        focal_length_m=6e-3,
        pixel_size_m=(7.4e-6, 7.4e-6),
        principal_point_px=(320.0, 240.0),
        image_size_px=(640, 480),
    )
    return CameraModel(intrinsics)
