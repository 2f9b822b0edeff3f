"""A side face seen nearly edge-on along a side of the top face: the three-level edge.

Next to a side of the cube's top face the camera often sees a side face as a narrow
band, between the face's grey level and the table's. Partial-area edge location (see
``core.vision.edges``) puts the edge where the strip's light says, which with a band of
width w and relative level L is w L outside the face's true side: up to a pixel for a
band under a pixel wide, which a strip cannot tell from the edge itself.

Here the whole side is fitted at once, pixel by pixel, as box-filtered steps (exact
area coverage, see ``coverage``) in strips across it:

    I = D + (g - D) cover(f) + (B - g) cover(e)

with e = c0 + m t the face's side along the strips' axis t (the line wanted), f = e - w(t)
the band's outer boundary, g the band's grey level, and B and D the face's level and the
level beyond the band, read at the strips' ends (running medians along the side).

The band is a side face of a box, a quadrilateral on the face's side: its outer
boundary is the bottom edge, cut near the face's corners by the vertical edges, which
start AT those corners. So across the strips

    w(t) = max(0, min(b0 + b1 t, kA (t - tA), kB (tB - t)))

with tA, tB the corners' along coordinates: a sliver of constant or changing width that
may taper to nothing at either corner (kA, kB large: no taper at that end). The taper's
pinning to the corner is what separates a thin bright band from a wider dimmer one along
a side nearly aligned with the pixel grid, where the pixels alone cannot.

The band model is taken only when it explains the pixels significantly better than a
single step (an F-test against the fit's own residual, which is at least the noise's), so
a side without a band keeps its partial-area line, and noise does not invent bands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from core.spatial import Matrix
from core.vision.edges import Strips, polygon_corners, running_median, segment_medians
from core.vision.least_squares import levenberg_marquardt

#: Least slant (px per px) of a modelled edge, so that its coverage has a gradient everywhere.
MIN_SLANT = 0.01
#: Widest band (px) the model may take (beyond the strips it has no effect).
_MAX_WIDTH_PX = 8.0
#: A taper this steep (px of width per px along) is none: the vertical edge leaves the
#: corner outwards, away from the side.
_NO_TAPER = 50.0
#: How many times its share of the residual the band model must explain to be believed.
_F_RATIO = 12.0
#: How many times the noise's share of a side's pixels its cost as a single step must
#: exceed before a band is looked for.
_GATE_RATIO = 3.0
#: Parameters of the band model beyond the single step's (c0, m): g, b0, b1, kA, kB.
_BAND_PARAMETERS = 5
#: Farthest (px) the band fit may move a side from the partial-area line (inwards), and
#: how far outwards it may put it (the partial-area line's own noise).
_MAX_SHIFT_PX = 3.5
_OUTWARD_SLACK_PX = 0.25
#: Least contrast (grey levels) between the face and the level beyond for a side to be fitted.
_MIN_CONTRAST = 20.0
#: Levenberg-Marquardt iterations of the band model.
_ITERATIONS = 7
#: Most strips of one side the band fit reads.
_MAX_STRIPS = 16
#: Starting widths (px) and relative levels of the band (its cost has poor minima in them),
#: and where a taper starting at a corner may meet the bottom edge (share of the side).
_START_SHARES = np.array([0.3, 0.4, 0.5, 0.6, 0.7, 0.8])
_FLAT_WIDTHS = np.repeat([0.5, 1.0, 2.0, 3.5], 3)
_FLAT_SHARES = np.tile([0.35, 0.55, 0.75], 4)
_KINKS = (0.0, 0.15, 0.3, 0.45, 0.6, 0.75, 0.9)  # 0: none
#: (share from corner A, share from corner B) of the kink patterns, NaN for no taper at
#: that end; the first is no taper at all.
_KINK_PAIRS = np.array(
    [(np.nan, np.nan)] + [(a or np.nan, b or np.nan) for a in _KINKS for b in _KINKS if (a or b) and a + b < 1.0]
)
_KINKS_USED = np.isfinite(_KINK_PAIRS).sum(axis=1)
_KINK_STARTS = 8
#: The band's level relative to the far level (0) and the face's (1).
_SHARE_RANGE = (0.1, 0.9)


@dataclass(frozen=True)
class BandFit:
    """The three-level fit of one side (see the module docstring).

    line: (unit normal, offset) of the face's side in the image, oriented like the input.
    width_px: (b0, b1, kA, kB) of the band's width along the strips' axis.
    level: the band's grey level.
    improvement: the F statistic of the band model against a single step.
    """

    line: tuple[Matrix, float]
    width_px: Matrix
    level: float
    improvement: float


def coverage(across: Matrix, edge: Matrix, slant: Matrix | float, blur: float = 0.0) -> tuple[Matrix, Matrix]:
    """Share of each pixel (centre ``across``) beyond an edge crossing it at ``edge``
    with ``slant`` px per px along the strip, seen through a Gaussian ``blur``, and its
    derivative with respect to the edge's position. "Beyond" is towards larger across;
    the arguments broadcast.

    Without blur exact (the pixel's box cut by a straight line: the share is the mean,
    over the pixel's extent along the strip, of the clipped distance to the edge, whose
    antiderivative A(z) = z^2 / 2 on [0, 1] and z - 1/2 beyond gives it in closed form);
    with it the pixel, slant and blur kernels together are taken as one Gaussian (of
    their summed variances).
    """
    c = across + (0.5 - edge)
    # The slant spread to the full shape once: broadcast against a short last axis (a
    # strip's few pixels) every operation would loop over that axis alone, which costs
    # several times the arithmetic. (Plain ufuncs: this runs in fits' inner loops.)
    spread_slant = np.empty_like(c)
    spread_slant[...] = np.maximum(np.abs(slant), MIN_SLANT)
    slant = spread_slant
    if blur >= 0.25:
        spread = np.sqrt((1.0 + slant * slant) / 12.0 + blur * blur)
        z = (c - 0.5) / spread
        return 0.5 * (1.0 + _erf(z / math.sqrt(2.0))), -np.exp(-0.5 * z * z) / (spread * math.sqrt(2.0 * math.pi))
    half = 0.5 * slant
    # A(z) = z^2 / 2 on [0, 1], z - 1/2 beyond, 0 below: with z+ = max(z, 0) and
    # h = min(z+, 1), A = h (h / 2 - 1) + z+.
    high, low = np.maximum(c + half, 0.0), np.maximum(c - half, 0.0)
    inside_high, inside_low = np.minimum(high, 1.0), np.minimum(low, 1.0)
    area = inside_high * (0.5 * inside_high - 1.0) + high - inside_low * (0.5 * inside_low - 1.0) - low
    return area / slant, (inside_low - inside_high) / slant


def _erf(x: Matrix) -> Matrix:
    """The error function (Abramowitz and Stegun 7.1.26, error below 1.5e-7)."""
    a = np.abs(x)
    t = 1.0 / (1.0 + 0.3275911 * a)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    return np.sign(x) * (1.0 - poly * np.exp(-a * a))


def banded_lines(strips: Strips, lines: list[tuple[Matrix, float]]) -> list[BandFit | None]:
    """Each side's three-level fit when a band runs along it, else None.

    ``strips`` are wide strips across the sides (``sample_strips``, one level pixel at
    each end), ``lines`` the four sides' partial-area lines in order around the face
    (unit normal from dark to bright, offset): side i runs from its crossing with side
    i - 1 to its crossing with side i + 1.

    First every side at once as a single step at its line: a side whose pixels that
    step explains to within the noise has no band worth fitting. The step is first
    taken sharp; only if a side then looks banded is the image's blur measured (a
    blurred image makes every side look so) and the test repeated with it.
    """
    count = len(lines)
    result: list[BandFit | None] = [None] * count
    segment = strips.segment
    bounds = np.searchsorted(segment, np.arange(count + 1))
    # Every strip in the bright-positive frame: the face at the larger index.
    values = np.where(strips.bright_high[:, None], strips.values, strips.values[:, ::-1])
    sign = np.where(strips.bright_high, 1.0, -1.0)
    reach = values.shape[1] // 2
    across = (sign * strips.base)[:, None] + np.arange(-reach + 1, reach)[None, :]
    normals = np.array([normal for normal, _ in lines])
    offsets = np.array([offset for _, offset in lines])
    # The strips' axes were chosen from the lines they were sampled along, which a 45
    # degree side may see the other way round from these.
    steep = strips.steep
    n_across = np.where(steep, normals[segment, 0], normals[segment, 1])
    n_along = np.where(steep, normals[segment, 1], normals[segment, 0])
    edge = sign * (offsets[segment] - n_along * strips.along) / n_across
    slope = n_along / n_across
    dark, bright = running_median(values[:, [0, -1]], segment).T
    noise = _noise_variance(values)
    pixels = values.shape[1] - 2
    contrasts = segment_medians(bright - dark, segment, count)
    sizes = np.diff(bounds)
    usable = (sizes >= 8) & (contrasts >= _MIN_CONTRAST)

    def step_costs(blur: float) -> tuple[Matrix, np.ndarray]:
        """Each strip's cost as a single step, and the sides that it leaves banded."""
        cover = coverage(across, edge[:, None], slope[:, None], blur)[0]
        residual = values[:, 1:-1] - (dark[:, None] + (bright - dark)[:, None] * cover)
        costs = (residual * residual).sum(axis=1)
        side_costs = np.add.reduceat(costs, np.minimum(bounds[:-1], len(costs) - 1)) * (sizes > 0)
        # Well over what noise leaves of a step's pixels (with its levels and line read
        # from the same noisy pixels, a band-free side's cost runs to about twice the
        # noise's share) and than a band would have to explain to be believed.
        expected = _GATE_RATIO * sizes * pixels + _F_RATIO * _BAND_PARAMETERS
        return costs, usable & (side_costs > expected * noise)

    blur = 0.0
    strip_costs, banded = step_costs(blur)
    if banded.any():
        blur = _edge_blur(strips, lines)
        if blur > 0.0:
            strip_costs, banded = step_costs(blur)
    corners = polygon_corners(lines)
    for index in np.flatnonzero(banded):
        # Of a long side every other strip (or fewer) is plenty: the fit costs per pixel.
        picked = np.arange(bounds[index], bounds[index + 1], -(-sizes[index] // _MAX_STRIPS))
        first = picked[0]
        axis = 1 if steep[first] else 0
        ends = [corners[index, axis], corners[(index + 1) % count, axis]]
        if not np.all(np.isfinite(ends)):
            continue
        side = _side(values[picked], across[picked], strips.along[picked], bright[picked], dark[picked], sorted(ends), blur)
        step = (float(edge[picked].mean()), -float(sign[first] * slope[first]))
        fit = _fit_band(side, step, float(strip_costs[picked].sum()), noise)
        if fit is not None:
            result[index] = _to_image(*fit, side, bool(steep[first]), float(sign[first]), lines[index][0])
    return result


def _edge_blur(strips: Strips, lines: list[tuple[Matrix, float]]) -> float:
    """The optical blur of the image (sigma of a Gaussian, px), from the top face's sides.

    Across a straight edge the grey levels' differences spread with variance 1/6 (the
    pixel's box, twice: the edge's coverage and the differencing) plus slant^2 / 12
    plus sigma^2. The moments are summed over each side's strips before they are
    divided (the noise then averages out), within 3.5 px of the line. The second
    cleanest side decides (a side face along a side widens its profile); estimates
    under 0.45 px are within the noise and read as no blur.
    """
    values = strips.values[:, 1:-1]  # 4 px each side
    sign = np.where(strips.bright_high, 1.0, -1.0)
    normals = np.array([normal for normal, _ in lines])[strips.segment]
    offsets = np.array([offset for _, offset in lines])[strips.segment]
    n_across = np.where(strips.steep, normals[:, 0], normals[:, 1])
    n_along = np.where(strips.steep, normals[:, 1], normals[:, 0])
    line_at = (offsets - n_along * strips.along) / n_across  # across coordinate of the line
    # Differences between neighbours, at the midpoints, in the bright-positive frame.
    steps = sign[:, None] * np.diff(values, axis=1)
    position = sign[:, None] * (strips.base[:, None] + np.arange(-4, 4)[None, :] + 0.5 - line_at[:, None])
    contrast = sign * (values[:, -1] - values[:, 0])
    usable = contrast > 20.0
    count = len(lines)
    # Each side's moments of the normalised steps in one pass (bincount by side).
    d = np.where(usable[:, None], steps / np.where(usable, contrast, 1.0)[:, None], 0.0)
    segment = strips.segment
    m0 = np.bincount(segment, d.sum(axis=1), count)
    m1 = np.bincount(segment, (d * position).sum(axis=1), count)
    m2 = np.bincount(segment, (d * position * position).sum(axis=1), count)
    slant2 = np.bincount(segment, (n_along / n_across) ** 2 * usable, count)
    strips_used = np.bincount(segment, usable, count)
    ok = (strips_used >= 6) & (m0 > 0.0)
    if not ok.any():
        return 0.0
    m0, m1, m2 = m0[ok], m1[ok], m2[ok]
    per_side = np.sort(m2 / m0 - (m1 / m0) ** 2 - 1.0 / 6.0 - slant2[ok] / strips_used[ok] / 12.0)
    variance = float(per_side[min(1, len(per_side) - 1)])
    sigma = math.sqrt(variance) if variance > 0.0 else 0.0
    return sigma if sigma > 0.45 else 0.0


def _noise_variance(values: Matrix) -> float:
    """The image's noise variance (grey levels^2), at least the 8-bit quantisation's.

    From the two pixels at each strip's face end (bright-positive ``values``), 4 and 5
    px inside the face: half the mean square of their difference, leaving out the few
    far beyond the bulk (a strip that reaches the mark, say).
    """
    difference = values[:, -1] - values[:, -2]
    middle = len(difference) // 2
    spread = 1.4826 * float(np.sort(np.abs(difference - np.sort(difference)[middle]))[middle])
    bulk = difference[np.abs(difference) <= max(3.0, 4.0 * spread)]
    return max(0.5 * float(bulk @ bulk) / max(len(bulk), 1), 1.0 / 12.0)


@dataclass(frozen=True)
class _Side:
    """One side's strips in the bright-positive frame (the face at larger ``across``)."""

    values: Matrix  # (n, p) grey levels of the modelled pixels
    across: Matrix  # (n, p) their centres
    mean_along: float  # the strips' mean along coordinate
    t: Matrix  # (n,) along coordinate relative to ``mean_along``
    ends: tuple[float, float]  # tA < tB, the face's corners at the side's ends, in t
    bright: Matrix  # (n,) the face's level just inside (running median)
    dark: Matrix  # (n,) the level beyond the band (running median)
    blur: float
    # Derived arrays the fit's inner loop would otherwise rebuild at every step.
    t_column: Matrix = field(init=False)
    dark_column: Matrix = field(init=False)
    bright_column: Matrix = field(init=False)
    strip_index: np.ndarray = field(init=False)
    width_basis: Matrix = field(init=False)  # (n, 4): 1, t, t - tA, tB - t

    def __post_init__(self) -> None:
        t_a, t_b = self.ends
        object.__setattr__(self, "t_column", self.t[:, None])
        object.__setattr__(self, "dark_column", self.dark[:, None])
        object.__setattr__(self, "bright_column", self.bright[:, None])
        object.__setattr__(self, "strip_index", np.arange(len(self.t)))
        object.__setattr__(self, "width_basis", np.column_stack([np.ones_like(self.t), self.t, self.t - t_a, t_b - self.t]))


def _side(
    values: Matrix, across: Matrix, along: np.ndarray, bright: Matrix, dark: Matrix, ends: list[float], blur: float
) -> _Side:
    """One side's strips (bright-positive, level pixels at the ends) ready for the fit."""
    mean_along = float(along.mean())
    t = along.astype(np.float64) - mean_along
    corners = (ends[0] - mean_along, ends[1] - mean_along)
    return _Side(values[:, 1:-1], across.astype(np.float64), mean_along, t, corners, bright, dark, blur)


def _fit_band(side: _Side, step: tuple[float, float], step_cost: float, noise: float) -> tuple[Matrix, float] | None:
    """Parameters (c0, m, g, b0, b1, kA, kB) of the band model and its F statistic when it
    is significantly better than the single step at across = c0 + m t (``step``), whose
    cost over the side's pixels is ``step_cost``; else None."""
    c0, m = step
    reach_t = 0.5 * float(side.t.max() - side.t.min()) + 1.0
    # The far level where the band is narrower than the strips (the widest bands' strips
    # end on the band itself).
    dark, bright = np.sort(side.dark), np.sort(side.bright)
    far, face = float(dark[len(dark) // 10]), float(bright[len(bright) // 2])
    contrast = face - far
    turn = 2.5 / reach_t
    lower = np.array([c0 - _MAX_SHIFT_PX, m - turn, far + _SHARE_RANGE[0] * contrast, 0.0, -1.0, 0.0, 0.0])
    upper = np.array([c0 + _MAX_SHIFT_PX, m + turn, far + _SHARE_RANGE[1] * contrast, _MAX_WIDTH_PX, 1.0, _NO_TAPER, _NO_TAPER])
    starts = _starts(side, far, contrast)
    starts = np.minimum(np.maximum(starts, lower), upper)
    band, band_cost = _descend(side, starts[_best(side, starts)], lower, upper, reach_t)

    dof = max(side.values.size - len(band), 1)
    # The residual's variance, at least the noise's: on a clean image a slight mismatch
    # of the model would otherwise count as significant.
    improvement = ((step_cost - band_cost) / _BAND_PARAMETERS) / max(band_cost / dof, noise)
    if not (np.isfinite(band).all() and improvement > _F_RATIO and _width(side, band[None])[0].max() > 0.05):
        return None
    if band[2] > upper[2] - 0.01 * contrast:
        return None  # a band at the face's level is only the edge moved
    shift = band[0] - c0 + (band[1] - m) * side.t  # towards the face
    if shift.max() > _MAX_SHIFT_PX or shift.min() < -_OUTWARD_SLACK_PX:
        # More than a band can explain, or the side moved outwards where a band (lighter
        # than the far level) can only have pulled the partial-area line out: the fit
        # found something else, a local minimum beside a band wider than the strips
        # that measured the line (which then already saw the face's own edge).
        return None
    return band, float(improvement)


def _starts(side: _Side, far: float, contrast: float) -> Matrix:
    """Starting parameter sets (G, 7) for the band fit, from the strips' partial areas.

    A strip's light puts its edge at M = e - L w (L = (g - D) / (B - D), the band's
    relative level), so along the side M(t) is the face's line minus L w(t): a line,
    or a line with kinks where w(t) turns into a taper that ends at a corner. Fitting
    M(t) for each pair of kink positions (a linear least-squares problem each) finds
    the line and L w(t); a few levels L then give the starts. Without a taper the line
    and a constant L w cannot be told apart: the widths' grid then supplies them.
    """
    t, (t_a, t_b) = side.t, side.ends
    n = len(t)
    bright_length = ((side.values - side.dark[:, None]) / (side.bright - side.dark)[:, None]).sum(axis=1)
    position = side.across[:, -1] + 0.5 - bright_length
    # Kinks at shares of the side from either corner (NaN: no taper at that end).
    kink_a = (t_a + _KINK_PAIRS[:, 0] * (t_b - t_a))[:, None]
    kink_b = (t_b - _KINK_PAIRS[:, 1] * (t_b - t_a))[:, None]
    # Columns (1, t, a, b) with L w = Lb0 a + Lb1 b, continuous at the kinks.
    ramp_a = np.maximum((t - t_a) / (kink_a - t_a), 0.0)
    ramp_b = np.maximum((t_b - t) / (t_b - kink_b), 0.0)
    below, above = t < kink_a, t > kink_b
    design = np.empty((len(_KINK_PAIRS), n, 4))
    design[:, :, 0], design[:, :, 1] = 1.0, t
    design[:, :, 2] = np.where(below, -ramp_a, np.where(above, -ramp_b, -1.0))
    design[:, :, 3] = np.where(below, -kink_a * ramp_a, np.where(above, -kink_b * ramp_b, -t))
    # Along a side with one taper a band widening linearly looks just like a tilted side
    # (only the partial areas are read here): the least widening is taken, the bottom
    # edge of a box's side face running nearly parallel to its top edge. Without a
    # taper nothing of the band shows, and it is left at zero.
    ridge = np.zeros((len(_KINK_PAIRS), 4, 4))
    ridge[:, 3, 3] = 1e-4 * float(t @ t)
    ridge[:, 2, 2] = 1e-8 * n  # (a kink beyond the strips leaves the band's width unseen)
    ridge[0, 2, 2] = 1e-4 * n
    transposed = design.transpose(0, 2, 1)
    coef = np.linalg.solve(transposed @ design + ridge, transposed @ position[:, None])  # (K, 4, 1)
    residual = position[:, None] - design @ coef
    cost = (residual * residual).sum(axis=(1, 2))
    coef = coef[:, :, 0]
    # Each kink must pay for itself (two parameters' worth of an information criterion).
    # Partial areas alone can mistake a tilted side for a taper: the few best kink
    # patterns all become starts, and the pixels decide.
    score = n * np.log(np.maximum(cost / n, 1e-8)) + 2.0 * np.log(n) * _KINKS_USED
    # No taper: the line is the partial area's, shifted out by w L for each width.
    flat = np.zeros((len(_FLAT_WIDTHS), 7))
    flat[:, 0] = coef[0, 0] + _FLAT_SHARES * np.minimum(_FLAT_WIDTHS, 2.0)
    flat[:, 1] = coef[0, 1]
    flat[:, 2] = far + _FLAT_SHARES * contrast
    flat[:, 3] = _FLAT_WIDTHS
    flat[:, 5:] = _NO_TAPER
    # Tapers: each of the best kink patterns at each of a few levels.
    picked = np.repeat(np.argsort(score[1:])[:_KINK_STARTS] + 1, len(_START_SHARES))
    share = np.tile(_START_SHARES, _KINK_STARTS)[: len(picked)]
    e0, m, lb0, lb1 = coef[picked].T
    kink_a, kink_b = kink_a[picked, 0], kink_b[picked, 0]
    tapered = np.empty((len(picked), 7))
    tapered[:, 0], tapered[:, 1] = e0, m
    tapered[:, 2] = far + share * contrast
    tapered[:, 3], tapered[:, 4] = lb0 / share, lb1 / share
    tapered[:, 5] = np.where(np.isnan(kink_a), _NO_TAPER, (lb0 + lb1 * kink_a) / (kink_a - t_a) / share)
    tapered[:, 6] = np.where(np.isnan(kink_b), _NO_TAPER, (lb0 + lb1 * kink_b) / (t_b - kink_b) / share)
    return np.concatenate([flat, tapered])


def _best(side: _Side, starts: Matrix) -> int:
    """Index of the parameter set of least cost (on every other strip: it only ranks)."""
    sparse = _Side(
        side.values[::2], side.across[::2], side.mean_along, side.t[::2], side.ends, side.bright[::2], side.dark[::2], side.blur
    )
    residuals = _residuals(sparse, starts)
    return int(np.argmin(np.einsum("gi,gi->g", residuals, residuals)))


def _to_image(band: Matrix, improvement: float, side: _Side, steep: bool, sign: float, normal: Matrix) -> BandFit:
    """The fitted face's side as an image line (oriented like ``normal``) and the band."""
    c0, m = float(band[0]), float(band[1])
    # across - m along = c0 - m mean_along in the bright-positive frame.
    new_normal = np.array([1.0, -sign * m]) if steep else np.array([-sign * m, 1.0])
    new_offset = sign * (c0 - m * side.mean_along)
    scale = float(np.hypot(*new_normal))
    new_normal, new_offset = new_normal / scale, new_offset / scale
    if new_normal @ normal < 0.0:
        new_normal, new_offset = -new_normal, -new_offset
    return BandFit((new_normal, float(new_offset)), band[3:].copy(), float(band[2]), improvement)


def _width(side: _Side, batch: Matrix) -> tuple[Matrix, Matrix, np.ndarray]:
    """The band's width w(t) (G, n) under parameter sets (G, 7), its slope along the
    side, and which piece shapes it (0 bottom edge, 1 and 2 the tapers, 3 none)."""
    t_a, t_b = side.ends
    b0, b1, k_a, k_b = (batch[:, i, None] for i in range(3, 7))
    bottom, taper_a, taper_b = b0 + b1 * side.t, k_a * (side.t - t_a), k_b * (t_b - side.t)
    width = np.minimum(np.minimum(bottom, taper_a), taper_b)
    piece = np.where(width == bottom, 0, np.where(width == taper_a, 1, 2))
    piece[width <= 0.0] = 3
    slopes = np.concatenate([b1, k_a, -k_b, np.zeros_like(b1)], axis=1)  # (G, 4)
    return np.maximum(width, 0.0), np.take_along_axis(slopes, piece, axis=1), piece


def _geometry(side: _Side, batch: Matrix) -> tuple[Matrix, Matrix, np.ndarray]:
    """Coverages (2, G, n, p) of the face's side (index 0) and of the band's outer
    boundary (1) under parameter sets ``batch`` (G, 7) = (c0, m, g, b0, b1, kA, kB), their
    derivatives with respect to the edges' positions, and the width's active piece."""
    c0, m = batch[:, 0, None], batch[:, 1, None]  # (G, 1)
    width, dw_dt, active = _width(side, batch)
    edges = np.empty(width.shape + (1,), dtype=np.float64)[None].repeat(2, axis=0)  # (2, G, n, 1)
    edges[0, ..., 0] = c0 + m * side.t
    edges[1, ..., 0] = edges[0, ..., 0] - width
    slants = np.empty_like(edges)
    slants[0, ..., 0] = m
    # The band's outer boundary slants with the side plus the width's change along it.
    slants[1, ..., 0] = m - dw_dt
    cover, d_cover = coverage(side.across, edges, slants, side.blur)
    return cover, d_cover, active


def _residuals(side: _Side, batch: Matrix) -> Matrix:
    """Residuals (G, N) of the grey levels under G parameter sets (see ``_geometry``)."""
    cover = _geometry(side, batch)[0]
    dark, bright, g = side.dark[:, None], side.bright[:, None], batch[:, 2, None, None]
    return (side.values - (dark + (g - dark) * cover[1] + (bright - g) * cover[0])).reshape(len(batch), -1)


#: Which of d w / d (b0, b1, kA, kB) each piece of the width (bottom edge, taper A,
#: taper B, none) has: 1 or t, (t - tA), (tB - t) by ``_Side.width_basis``.
_PIECE_DERIVATIVES = np.array([[1.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0]])


def _residuals_and_jacobian(side: _Side, params: Matrix) -> tuple[Matrix, Matrix]:
    """Residuals (N,) of the grey levels under ``params`` and their Jacobian (N, 7).

    The same model as ``_residuals`` for one parameter set, written for few array
    operations: it runs in the fit's inner loop.
    """
    c0, m, g, b0, b1, k_a, k_b = params.tolist()
    n = len(side.t)
    pieces = np.empty((3, n))
    pieces[0] = b0 + b1 * side.t
    pieces[1] = k_a * side.width_basis[:, 2]
    pieces[2] = k_b * side.width_basis[:, 3]
    piece = pieces.argmin(axis=0)
    width = pieces[piece, side.strip_index]
    piece[width <= 0.0] = 3  # clipped at zero: no piece moves it
    edges, slants = np.empty((2, n, 1)), np.empty((2, n, 1))
    edges[0, :, 0] = c0 + m * side.t
    edges[1, :, 0] = edges[0, :, 0] - np.maximum(width, 0.0)
    slants[0] = m
    # The band's outer boundary slants with the side plus the width's change along it.
    slants[1, :, 0] = m - np.array([b1, k_a, -k_b, 0.0])[piece]
    (cover_e, cover_f), (d_e, d_f) = coverage(side.across, edges, slants, side.blur)
    residual = side.values - (side.dark_column + (g - side.dark_column) * cover_f + (side.bright_column - g) * cover_e)
    d_far = (g - side.dark_column) * d_f
    d_edge = d_far + (side.bright_column - g) * d_e  # d prediction / d c0
    jac = np.empty(cover_e.shape + (7,))
    jac[..., 0] = d_edge
    jac[..., 1] = d_edge * side.t_column
    jac[..., 2] = cover_f - cover_e
    # d w / d (b0, b1, kA, kB): only the piece that shapes the width moves it.
    jac[..., 3:] = -d_far[..., None] * (side.width_basis * _PIECE_DERIVATIVES[piece])[:, None, :]
    return residual.ravel(), -jac.reshape(-1, 7)


def _descend(side: _Side, params: Matrix, lower: Matrix, upper: Matrix, reach_t: float) -> tuple[Matrix, float]:
    """The band model's least squares within the bounds: (params, cost)."""
    params, residual = levenberg_marquardt(
        lambda p: _residuals_and_jacobian(side, p),
        params,
        lower,
        upper,
        iterations=_ITERATIONS,
        # The face's side (the line wanted) has settled, whatever the band still does.
        settled=lambda old, new: abs(new[0] - old[0]) + abs(new[1] - old[1]) * reach_t < 5e-3,
    )
    return params, float(residual @ residual)
