"""The sensor's effects on a rasterised frame, and the frame grabber's faults.

In this order: uneven lighting (multiplicative, smooth), the laser spot, optical blur,
motion smear, sensor noise and 8-bit quantisation. A grabber fault replaces the whole
frame (dropped: all black; repeat: the previous frame again) or smears it.

The laser spot is a sampled Gaussian added to the surface, I = I + A exp(-d^2 / (2
sigma^2)), with an amplitude A far above the 8-bit range: a laser outshines the scene
and saturates the sensor over a small core, wherever its centre falls between pixel
centres and whatever surface it lands on, which is what lets a fixed-level threshold
find it (section 4.3). The saturated plateau is symmetric about the true centre, so its
centroid stays within a few hundredths of a pixel of the projected spot.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import cv2
import numpy as np

from vservo.core.sim.render_settings import RenderSettings


class FaultKind(enum.Enum):
    DROPPED = "dropped"  # the grabber delivers an all-black frame
    REPEAT = "repeat"  # the grabber delivers the previous frame again
    SMEAR = "smear"  # the camera moved during the exposure: motion blur


@dataclass(frozen=True)
class FrameFault:
    """A frame-grabber or exposure fault to impose on one ``render`` call.

    Use the constructors: ``FrameFault.dropped()`` (all-black frame),
    ``FrameFault.repeat()`` (the renderer's previous good frame again, black if there is
    none) and ``FrameFault.smear(length_px, angle_rad)`` (motion blur: the frame is
    averaged along a segment of ``length_px`` centred on each point, at ``angle_rad``
    from the image's +u axis towards +v).
    """

    kind: FaultKind
    smear_px: float = 0.0
    smear_angle_rad: float = 0.0

    def __post_init__(self) -> None:
        if self.kind is FaultKind.SMEAR and not (np.isfinite(self.smear_px) and self.smear_px >= 0.0):
            raise ValueError(f"smear_px must be finite and >= 0, got {self.smear_px!r}")

    @classmethod
    def dropped(cls) -> FrameFault:
        return cls(FaultKind.DROPPED)

    @classmethod
    def repeat(cls) -> FrameFault:
        return cls(FaultKind.REPEAT)

    @classmethod
    def smear(cls, length_px: float, angle_rad: float = 0.0) -> FrameFault:
        return cls(FaultKind.SMEAR, float(length_px), float(angle_rad))


def smear_kernel(length_px: float, angle_rad: float) -> np.ndarray:
    """Normalised float32 kernel of a line of ``length_px`` through the kernel centre.

    The line is sampled densely and splatted bilinearly, so sub-pixel lengths and any
    direction are anti-aliased; the kernel is point-symmetric, so smearing moves no
    centroid.
    """
    half = 0.5 * float(length_px)
    radius = int(math.ceil(half)) + 1
    size = 2 * radius + 1
    samples = max(2, int(math.ceil(8.0 * length_px)) + 1)
    s = np.linspace(-half, half, samples)
    x = radius + s * math.cos(angle_rad)
    y = radius + s * math.sin(angle_rad)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    kernel = np.zeros((size + 1, size + 1))
    np.add.at(kernel, (y0, x0), (1 - fx) * (1 - fy))
    np.add.at(kernel, (y0, x0 + 1), fx * (1 - fy))
    np.add.at(kernel, (y0 + 1, x0), (1 - fx) * fy)
    np.add.at(kernel, (y0 + 1, x0 + 1), fx * fy)
    kernel = kernel[:size, :size]
    return (kernel / kernel.sum()).astype(np.float32)


class SensorEffects:
    """Turns the rasteriser's float frame into the sensor's 8-bit frame (module docstring)."""

    def __init__(self, image_size: tuple[int, int], settings: RenderSettings) -> None:
        self.image_size = image_size
        self.settings = settings
        # Frame-sized float buffers reused from frame to frame: a fresh 1 MB array costs
        # more in page faults than the arithmetic done in it.
        self._buffers: dict[tuple[str, tuple[int, ...]], np.ndarray] = {}
        self._lighting_cache: dict[int, np.ndarray] = {}

    def margin_px(self, smear_px: float) -> int:
        """Pixels to render beyond each side of the image, so that blur and smear read
        the scene there rather than a replicated border."""
        if self.settings.blur_sigma_px > 0.0 or smear_px > 0.0:
            return int(math.ceil(4.0 * self.settings.blur_sigma_px + 0.5 * smear_px)) + 2
        return 0

    def expose(
        self,
        image: np.ndarray,
        pad: int,
        spot_uv: np.ndarray | None,
        smear: FrameFault | None,
        rng: np.random.Generator,
    ) -> np.ndarray:
        """The (height, width) uint8 frame from ``image``, the float32 raster grown by ``pad``.

        ``spot_uv`` is the laser spot's pixel (None when it is hidden); ``smear`` a SMEAR
        fault or None. All randomness (sensor noise) comes from ``rng``.
        """
        width, height = self.image_size
        st = self.settings
        if st.lighting_gradient > 0.0:
            image *= self._lighting(pad, image.shape)
            np.minimum(image, 255.0, out=image)
        if spot_uv is not None:
            self._draw_spot(image, spot_uv, pad)
        if st.blur_sigma_px > 0.0:
            blurred = self._buffer("blurred", image.shape)
            image = cv2.GaussianBlur(image, (0, 0), st.blur_sigma_px, dst=blurred, borderType=cv2.BORDER_REPLICATE)
        if smear is not None and smear.smear_px > 0.0:
            kernel = smear_kernel(smear.smear_px, smear.smear_angle_rad)
            smeared = self._buffer("smeared", image.shape)
            image = cv2.filter2D(image, -1, kernel, dst=smeared, borderType=cv2.BORDER_REPLICATE)
        if pad:
            image = image[pad : pad + height, pad : pad + width]
        if st.noise_sigma > 0.0:
            # OpenCV's generator, seeded from rng (one draw per frame), fills the frame about
            # four times faster than numpy's; the noise is still fully determined by rng.
            noise = self._buffer("noise", (height, width))
            cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
            # OpenCV's stubs type mean and stddev as arrays; randn takes plain numbers (Scalars) as well.
            cv2.randn(noise, 0.0, float(st.noise_sigma))  # type: ignore[call-overload]
            np.add(image, noise, out=image)
        np.clip(image, 0.0, 255.0, out=image)
        image += 0.5
        return image.astype(np.uint8)

    def _buffer(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        """The float32 work array ``name`` of ``shape`` (its content is stale)."""
        key = (name, shape)
        if key not in self._buffers:
            self._buffers[key] = np.empty(shape, dtype=np.float32)
        return self._buffers[key]

    def _lighting(self, pad: int, shape: tuple[int, ...]) -> np.ndarray:
        if pad not in self._lighting_cache:
            width, height = self.image_size
            v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
            u -= pad + (width - 1) / 2.0
            v -= pad + (height - 1) / 2.0
            angle = math.radians(self.settings.lighting_angle_deg)
            half_w, half_h = width / 2.0, height / 2.0
            ramp = (u * math.cos(angle) + v * math.sin(angle)) / (abs(math.cos(angle)) * half_w + abs(math.sin(angle)) * half_h)
            r2 = (u * u + v * v) / (half_w * half_w + half_h * half_h)
            s = self.settings.lighting_gradient
            self._lighting_cache[pad] = (1.0 + s * (0.5 * np.clip(ramp, -1, 1) - 0.5 * np.minimum(r2, 1.0))).astype(np.float32)
        return self._lighting_cache[pad]

    def _draw_spot(self, image: np.ndarray, uv: np.ndarray, pad: int) -> None:
        if not np.all(np.isfinite(uv)):
            return
        st = self.settings
        u, v = uv[0] + pad, uv[1] + pad
        radius = int(math.ceil(5.0 * st.spot_sigma_px)) + 1
        h, w = image.shape
        c0, c1 = max(int(round(u)) - radius, 0), min(int(round(u)) + radius + 1, w)
        r0, r1 = max(int(round(v)) - radius, 0), min(int(round(v)) + radius + 1, h)
        if c1 <= c0 or r1 <= r0:
            return
        gx = np.exp(-((np.arange(c0, c1) - u) ** 2) / (2.0 * st.spot_sigma_px**2))
        gy = np.exp(-((np.arange(r0, r1) - v) ** 2) / (2.0 * st.spot_sigma_px**2))
        image[r0:r1, c0:c1] += (st.spot_amplitude * np.outer(gy, gx)).astype(np.float32)
