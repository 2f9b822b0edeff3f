"""A side face seen nearly edge-on along a side of the top face: the three-level edge.

Next to a side of the cube's top face the camera often sees a side face as a narrow
band, between the face's grey level and the table's. Partial-area edge location (see
``vservo.core.perception.vision.edges``) puts the edge where the strip's light says, which with a band of
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
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.vision.edges import Strips, polygon_corners, running_median, segment_medians
from vservo.core.perception.vision.least_squares import levenberg_marquardt

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
#: The kinks' shares from corner A (along t) and corner B (against t), and those directions.
_KINK_DIRECTIONS = np.array([[1.0], [-1.0]])
_KINK_SHARES = _KINK_PAIRS.T * _KINK_DIRECTIONS
_KINK_STARTS = 8
#: The starts' levels (relative), flat ones first; the flat starts' line shifts (w L,
#: the widest bands' taken as 2 px) and width parameters (b0, b1, kA, kB).
_START_LEVELS = np.concatenate([_FLAT_SHARES, _START_SHARES])
_FLAT_SHIFTS = _FLAT_SHARES * np.minimum(_FLAT_WIDTHS, 2.0)
_FLAT_WIDTH_PARAMETERS = np.column_stack([_FLAT_WIDTHS, np.zeros_like(_FLAT_WIDTHS), np.full((len(_FLAT_WIDTHS), 2), _NO_TAPER)])
#: Ridge on the kink patterns' first column, per point: strong without a taper (nothing
#: of the band shows), a trace with one.
_RIDGE_A = np.where(_KINKS_USED > 0, 1e-8, 1e-4)
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


def coverage(across: Matrix, edge: Matrix, slant: Matrix | float, blur: float = 0.0, derivative: bool = True) -> Matrix:
    """Share of each pixel (centre ``across``) beyond an edge crossing it at ``edge``
    with ``slant`` px per px along the strip, seen through a Gaussian ``blur``, and
    (unless not ``derivative``) its derivative with respect to the edge's position,
    stacked: (2, ...). "Beyond" is towards larger across; ``across`` and ``edge``
    broadcast to the result's shape, ``slant`` to it.

    Without blur exact (the pixel's box cut by a straight line: the share is the mean,
    over the pixel's extent along the strip, of the clipped distance to the edge, whose
    antiderivative A(z) = z^2 / 2 on [0, 1] and z - 1/2 beyond gives it in closed form);
    with it the pixel, slant and blur kernels together are taken as one Gaussian (of
    their summed variances).
    """
    c = across + (0.5 - edge)
    slant = np.maximum(np.abs(slant), MIN_SLANT)
    if blur >= 0.25:
        spread = np.sqrt((1.0 + slant * slant) / 12.0 + blur * blur)
        z = (c - 0.5) / spread
        share = 0.5 * (1.0 + _erf(z / math.sqrt(2.0)))
        if not derivative:
            return share
        return np.array([share, -np.exp(-0.5 * z * z) / (spread * math.sqrt(2.0 * math.pi))])
    # A(z) = z^2 / 2 on [0, 1], z - 1/2 beyond, 0 below: with z+ = max(z, 0) and
    # h = min(z+, 1), A = h (h / 2 - 1) + z+; at the pixel's two ends along the strip,
    # z = c +- slant / 2, in one array (these run in fits' inner loops: few operations).
    half = 0.5 * slant
    positive = np.empty((2,) + c.shape)
    np.add(c, half, out=positive[0])
    np.subtract(c, half, out=positive[1])
    np.maximum(positive, 0.0, out=positive)
    inside = np.minimum(positive, 1.0)
    antiderivative = 0.5 * inside
    antiderivative -= 1.0
    antiderivative *= inside
    antiderivative += positive
    if not derivative:
        area = antiderivative[0] - antiderivative[1]
        area /= slant
        return area
    result = np.empty_like(positive)
    np.subtract(antiderivative[0], antiderivative[1], out=result[0])
    np.subtract(inside[1], inside[0], out=result[1])
    result /= slant
    return result


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
    sizes = bounds[1:] - bounds[:-1]
    membership = (segment == np.arange(count)[:, None]).astype(np.float64)  # (sides, strips)
    # Every strip in the bright-positive frame (the face at the larger index), pixel-major:
    # a row per pixel across, so that what varies by strip runs along the rows.
    values = np.where(strips.bright_high[:, None], strips.values, strips.values[:, ::-1]).T.copy()
    sign = np.where(strips.bright_high, 1.0, -1.0)
    reach = len(values) // 2
    across = sign * strips.base + np.arange(-reach + 1.0, reach)[:, None]  # the inner pixels' centres
    normals = np.array([normal for normal, _ in lines])[segment]
    offsets = np.array([offset for _, offset in lines])
    # The strips' axes were chosen from the lines they were sampled along, which a 45
    # degree side may see the other way round from these.
    steep = strips.steep
    n_across = np.where(steep, normals[:, 0], normals[:, 1])
    n_along = np.where(steep, normals[:, 1], normals[:, 0])
    edge = sign * (offsets[segment] - n_along * strips.along) / n_across
    slope = n_along / n_across
    dark, bright = running_median(values[[0, -1]].T, segment).T
    noise = _noise_variance(values)
    inner = values[1:-1]
    contrasts = segment_medians(bright - dark, segment, count)
    usable = (sizes >= 8) & (contrasts >= _MIN_CONTRAST)

    def step_costs(blur: float) -> tuple[Matrix, np.ndarray]:
        """Each strip's cost as a single step, and the sides that it leaves banded."""
        residual = inner - (dark + (bright - dark) * coverage(across, edge, slope, blur, derivative=False))
        costs = np.einsum("ij,ij->j", residual, residual)
        # Well over what noise leaves of a step's pixels (with its levels and line read
        # from the same noisy pixels, a band-free side's cost runs to about twice the
        # noise's share) and than a band would have to explain to be believed.
        expected = _GATE_RATIO * sizes * len(inner) + _F_RATIO * _BAND_PARAMETERS
        return costs, usable & (membership @ costs > expected * noise)

    blur = 0.0
    strip_costs, banded = step_costs(blur)
    if not banded.any():
        return result
    blur = _edge_blur(inner, sign * strips.base - edge, slope, membership)
    if blur > 0.0:
        strip_costs, banded = step_costs(blur)
    corners = polygon_corners(lines)
    for index in np.flatnonzero(banded).tolist():
        start, stop = bounds[index], bounds[index + 1]
        # Of a long side every other strip (or fewer) is plenty: the fit costs per pixel.
        picked = slice(start, stop, -(-(stop - start) // _MAX_STRIPS))
        axis = 1 if steep[start] else 0
        ends = sorted([float(corners[index, axis]), float(corners[(index + 1) % count, axis])])
        if not (math.isfinite(ends[0]) and math.isfinite(ends[1])):
            continue
        side = _side(inner[:, picked], across[:, picked], strips.along[picked], bright[picked], dark[picked], ends, blur)
        strip_edges = edge[picked]
        step = (float(strip_edges.sum()) / len(strip_edges), -float(sign[start] * slope[start]))
        fit = _fit_band(side, step, float(strip_costs[picked].sum()), noise)
        if fit is not None:
            result[index] = _to_image(*fit, side, bool(steep[start]), float(sign[start]), lines[index][0])
    return result


#: The midpoints between a strip's inner pixels, from its base pixel (px), raised to the
#: powers 0, 1 and 2: the steps' moments about the base pixel (see ``_edge_blur``).
_MIDPOINT_POWERS = (np.arange(-4, 4) + 0.5) ** np.arange(3)[:, None]


def _edge_blur(inner: Matrix, base_from_line: Matrix, slope: Matrix, membership: Matrix) -> float:
    """The optical blur of the image (sigma of a Gaussian, px), from the top face's sides.

    ``inner`` are the strips' 9 inner pixels (bright-positive, pixel-major), each strip's
    base pixel ``base_from_line`` px from its line, which has ``slope`` along it;
    ``membership`` (sides, strips) says which side each strip is on.

    Across a straight edge the grey levels' differences spread with variance 1/6 (the
    pixel's box, twice: the edge's coverage and the differencing) plus slant^2 / 12
    plus sigma^2. The moments are summed over each side's strips before they are
    divided (the noise then averages out), within 3.5 px of the line. The second
    cleanest side decides (a side face along a side widens its profile); estimates
    under 0.45 px are within the noise and read as no blur.
    """
    # Each strip's steps' moments about its base pixel (exact: integer grey levels and
    # half-integer positions), then about its line: with x = k + o, the sums of d x and
    # d x^2 are S1 + o S0 and S2 + 2 o S1 + o^2 S0.
    s0, s1, s2 = _MIDPOINT_POWERS @ (inner[1:] - inner[:-1])
    usable = s0 > 20.0  # s0 is the strip's contrast
    contrast = np.where(usable, s0, 1.0)
    mean = s1 / contrast
    o = base_from_line
    per_strip = np.array([usable, (mean + o) * usable, (s2 / contrast + o * (2.0 * mean + o)) * usable, slope * slope * usable])
    strips_used, m1, m2, slant2 = per_strip @ membership.T
    ok = strips_used >= 6
    if not ok.any():
        return 0.0
    m0, m1, m2 = strips_used[ok], m1[ok], m2[ok]
    per_side = np.sort(m2 / m0 - (m1 / m0) ** 2 - 1.0 / 6.0 - slant2[ok] / m0 / 12.0)
    variance = float(per_side[min(1, len(per_side) - 1)])
    sigma = math.sqrt(variance) if variance > 0.0 else 0.0
    return sigma if sigma > 0.45 else 0.0


def _noise_variance(values: Matrix) -> float:
    """The image's noise variance (grey levels^2), at least the 8-bit quantisation's.

    From the two pixels at each strip's face end (bright-positive, pixel-major
    ``values``), 4 and 5 px inside the face: half the mean square of their difference,
    leaving out the few far beyond the bulk (a strip that reaches the mark, say).
    """
    difference = values[-1] - values[-2]
    middle = len(difference) // 2
    spread = 1.4826 * float(np.sort(np.abs(difference - np.sort(difference)[middle]))[middle])
    bulk = difference[np.abs(difference) <= max(3.0, 4.0 * spread)]
    return max(0.5 * float(bulk @ bulk) / max(len(bulk), 1), 1.0 / 12.0)


#: The design's rows (e, the width's bottom edge, taper A, taper B) by parameter (c0, m,
#: g, b0, b1, kA, kB): which row of ``_Side.width_basis`` multiplies it, if any.
_DESIGN_BASIS = np.array([[0, 1, 0, 0, 0, 0, 0], [0, 0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 0, 2, 0], [0, 0, 0, 0, 0, 0, 3]])
_DESIGN_MASK = np.array([[1, 1, 0, 0, 0, 0, 0], [0, 0, 0, 1, 1, 0, 0], [0, 0, 0, 0, 0, 1, 0], [0, 0, 0, 0, 0, 0, 1]], float)


@dataclass(frozen=True)
class _Side:
    """One side's strips in the bright-positive frame (the face at larger ``across``),
    pixel-major: row k holds every strip's k-th pixel, so that what varies by strip
    broadcasts along the rows (long contiguous runs, where the fits' inner loops spend
    their time)."""

    values: Matrix  # (p, n) grey levels of the modelled pixels
    across: Matrix  # (p, n) their centres
    mean_along: float  # the strips' mean along coordinate
    t: Matrix  # (n,) along coordinate relative to ``mean_along``
    ends: tuple[float, float]  # tA < tB, the face's corners at the side's ends, in t
    bright: Matrix  # (n,) the face's level just inside (running median)
    dark: Matrix  # (n,) the level beyond the band (running median)
    blur: float

    @cached_property
    def width_basis(self) -> Matrix:
        """(4, n): 1, t, t - tA, tB - t (the width's pieces are these times its parameters)."""
        t_a, t_b = self.ends
        return np.array([np.ones_like(self.t), self.t, self.t - t_a, t_b - self.t])

    # What the fit's inner loop (``_residuals_and_jacobian``) would otherwise rebuild at
    # every step.
    @cached_property
    def minus_width_basis(self) -> Matrix:
        return -self.width_basis

    @cached_property
    def design(self) -> Matrix:
        """(4 n, 7): the strips' face side e = c0 + m t and the width's pieces b0 + b1 t,
        kA (t - tA), kB (tB - t), as rows of a product with the parameters."""
        return (self.width_basis[_DESIGN_BASIS] * _DESIGN_MASK[:, :, None]).transpose(0, 2, 1).reshape(-1, 7)

    @cached_property
    def level_offsets(self) -> Matrix:
        """(2, n): bright and -dark, the levels across the face's side and the band's
        outer boundary (bright - g, g - dark) less their dependence on g."""
        return np.array([self.bright, -self.dark])

    @cached_property
    def dark_less_values(self) -> Matrix:
        return self.dark - self.values

    @cached_property
    def t_spread(self) -> Matrix:
        return np.repeat(self.t[None, :], len(self.values), axis=0)

    def every_other(self) -> _Side:
        """The side on every other strip."""
        strips = slice(None, None, 2)
        sparse = _Side(
            self.values[:, strips],
            self.across[:, strips],
            self.mean_along,
            self.t[strips],
            self.ends,
            self.bright[strips],
            self.dark[strips],
            self.blur,
        )
        # Its design's rows are this side's (set where the cached property keeps its value).
        sparse.__dict__["design"] = self.design.reshape(4, len(self.t), 7)[:, strips].reshape(-1, 7)
        return sparse


def _side(
    values: Matrix, across: Matrix, along: np.ndarray, bright: Matrix, dark: Matrix, ends: list[float], blur: float
) -> _Side:
    """One side's strips (bright-positive, pixel-major: the modelled pixels) ready for the fit."""
    mean_along = float(along.sum()) / len(along)
    t = along - mean_along
    corners = (ends[0] - mean_along, ends[1] - mean_along)
    return _Side(values.copy(), across.copy(), mean_along, t, corners, bright, dark, blur)


def _fit_band(side: _Side, step: tuple[float, float], step_cost: float, noise: float) -> tuple[Matrix, float] | None:
    """Parameters (c0, m, g, b0, b1, kA, kB) of the band model and its F statistic when it
    is significantly better than the single step at across = c0 + m t (``step``), whose
    cost over the side's pixels is ``step_cost``; else None."""
    c0, m = step
    t_low, t_high = float(side.t.min()), float(side.t.max())
    reach_t = 0.5 * (t_high - t_low) + 1.0
    # The far level where the band is narrower than the strips (the widest bands' strips
    # end on the band itself).
    dark, bright = sorted(side.dark.tolist()), sorted(side.bright.tolist())
    far, face = dark[len(dark) // 10], bright[len(bright) // 2]
    contrast = face - far
    turn = 2.5 / reach_t
    lower = np.array([c0 - _MAX_SHIFT_PX, m - turn, far + _SHARE_RANGE[0] * contrast, 0.0, -1.0, 0.0, 0.0])
    upper = np.array([c0 + _MAX_SHIFT_PX, m + turn, far + _SHARE_RANGE[1] * contrast, _MAX_WIDTH_PX, 1.0, _NO_TAPER, _NO_TAPER])
    starts = _starts(side, far, contrast)
    np.maximum(starts, lower, out=starts)
    np.minimum(starts, upper, out=starts)
    band, band_cost = _descend(side, starts[_best(side, starts)], lower, upper, reach_t)

    dof = max(side.values.size - len(band), 1)
    # The residual's variance, at least the noise's: on a clean image a slight mismatch
    # of the model would otherwise count as significant.
    improvement = ((step_cost - band_cost) / _BAND_PARAMETERS) / max(band_cost / dof, noise)
    fitted = band.tolist()
    if not (all(map(math.isfinite, fitted)) and improvement > _F_RATIO):
        return None
    if np.minimum.reduce((side.design[len(side.t) :] @ band).reshape(3, -1)).max() <= 0.05:
        return None  # no band after all
    if fitted[2] > upper[2] - 0.01 * contrast:
        return None  # a band at the face's level is only the edge moved
    # How far the fit moved the side towards the face, at the strips' ends (it is a line).
    shifts = [fitted[0] - c0 + (fitted[1] - m) * t for t in (t_low, t_high)]
    if max(shifts) > _MAX_SHIFT_PX or min(shifts) < -_OUTWARD_SLACK_PX:
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
    bright_length = ((side.values - side.dark) / (side.bright - side.dark)).sum(axis=0)
    position = side.across[-1] + 0.5 - bright_length
    # Kinks (2, K) at shares of the side from either corner (NaN: no taper at that end),
    # and how far each lies from its corner.
    kinks = np.array([[t_a], [t_b]]) + _KINK_SHARES * (t_b - t_a)
    spans = (kinks - np.array([[t_a], [t_b]])) * _KINK_DIRECTIONS
    # Besides the line's columns (1, t), columns (a, b) with L w = Lb0 a + Lb1 b: -1 and
    # -t between the kinks, ramping to zero at the corners beyond them (continuous).
    ramps = np.maximum(side.width_basis[2:, None, :] / spans[:, :, None], 0.0)
    columns = np.empty(ramps.shape)  # (2, K, n)
    np.negative(np.fmin(np.fmin(ramps[0], ramps[1]), 1.0), out=columns[0])
    np.multiply(columns[0], np.fmin(np.fmax(t, kinks[0, :, None]), kinks[1, :, None]), out=columns[1])
    # The line is common to every pattern: projected out once (Frisch-Waugh-Lovell), it
    # leaves a 2 x 2 system per pattern, solved in closed form.
    line_basis = side.width_basis[:2]
    sum_t, sum_tt = float(t.sum()), float(t @ t)
    det = n * sum_tt - sum_t * sum_t
    to_line = np.array([sum_tt - sum_t * t, n * t - sum_t]) / det  # (2, n): the line's least squares
    off_line = -(line_basis.T @ to_line)
    off_line.flat[:: n + 1] += 1.0
    projected = columns @ off_line
    target = position @ off_line
    gram = np.einsum("akn,bkn->abk", projected, projected)
    # Along a side with one taper a band widening linearly looks just like a tilted side
    # (only the partial areas are read here): the least widening is taken, the bottom
    # edge of a box's side face running nearly parallel to its top edge. Without a
    # taper nothing of the band shows, and it is left at zero.
    gram[1, 1] += 1e-4 * sum_tt
    gram[0, 0] += _RIDGE_A * n  # (a kink beyond the strips leaves the band's width unseen)
    moments = projected @ target
    det = gram[0, 0] * gram[1, 1] - gram[0, 1] * gram[1, 0]
    widths = np.array([gram[1, 1] * moments[0] - gram[0, 1] * moments[1], gram[0, 0] * moments[1] - gram[1, 0] * moments[0]])
    widths /= det  # (2, K): Lb0, Lb1
    explained = np.einsum("ak,akn->kn", widths, columns)
    residual = target - np.einsum("ak,akn->kn", widths, projected)
    cost = np.einsum("kn,kn->k", residual, residual)
    # Each kink must pay for itself (two parameters' worth of an information criterion).
    # Partial areas alone can mistake a tilted side for a taper: the few best kink
    # patterns all become starts, and the pixels decide.
    score = n * np.log(np.maximum(cost[1:] / n, 1e-8)) + 2.0 * np.log(n) * _KINKS_USED[1:]
    picked = np.concatenate([[0], score.argsort()[:_KINK_STARTS] + 1])
    lines = (position - explained[picked]) @ to_line.T  # (e0, m) of no taper and the picked patterns
    levels = far + _START_LEVELS * contrast
    starts = np.empty((len(_FLAT_WIDTHS) + _KINK_STARTS * len(_START_SHARES), 7))
    # No taper: the line is the partial area's, shifted out by w L for each width.
    flat = starts[: len(_FLAT_WIDTHS)]
    flat[:, 3:] = _FLAT_WIDTH_PARAMETERS
    flat[:, :2] = lines[0]
    flat[:, 0] += _FLAT_SHIFTS
    flat[:, 2] = levels[: len(_FLAT_WIDTHS)]
    # Tapers: each of the best kink patterns at each of a few levels.
    tapered = starts[len(_FLAT_WIDTHS) :].reshape(_KINK_STARTS, len(_START_SHARES), 7)
    tapered[:, :, :2] = lines[1:, None, :]
    tapered[:, :, 2] = levels[len(_FLAT_WIDTHS) :]
    # Their widths' parameters at each level (kA, kB from the width at the kinks).
    patterns = picked[1:]
    pattern_widths = widths[:, patterns]
    pattern_kinks = kinks[:, patterns]
    tapers = (pattern_widths[0] + pattern_widths[1] * pattern_kinks) / spans[:, patterns]
    tapered[:, :, 3:] = np.concatenate([pattern_widths, tapers]).T[:, None, :] / _START_SHARES[:, None]
    np.copyto(tapered[:, :, 5:], _NO_TAPER, where=np.isnan(pattern_kinks).T[:, None, :])
    return starts


def _best(side: _Side, starts: Matrix) -> int:
    """Index of the parameter set (rows of ``starts``) of least cost (on every other
    strip: it only ranks)."""
    sparse = side.every_other()
    residuals = _residuals(sparse, starts.T).reshape(-1, len(starts))
    return int(np.argmin(np.einsum("ig,ig->g", residuals, residuals)))


def _to_image(band: Matrix, improvement: float, side: _Side, steep: bool, sign: float, normal: Matrix) -> BandFit:
    """The fitted face's side as an image line (oriented like ``normal``) and the band."""
    c0, m, level = band[:3].tolist()
    # across - m along = c0 - m mean_along in the bright-positive frame.
    u, v = (1.0, -sign * m) if steep else (-sign * m, 1.0)
    offset = sign * (c0 - m * side.mean_along)
    scale = float(np.hypot(u, v))
    u, v, offset = u / scale, v / scale, offset / scale
    if u * normal[0] + v * normal[1] < 0.0:
        u, v, offset = -u, -v, -offset
    return BandFit((np.array([u, v]), offset), band[3:].copy(), level, improvement)


#: The slopes along the side of the width's pieces (bottom edge, taper A, taper B, none:
#: b1, kA, -kB, 0) as rows of a product with the parameters.
_PIECE_SLOPES = np.array([[0.0, 0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 0, 1, 0], [0, 0, 0, 0, 0, 0, -1], [0, 0, 0, 0, 0, 0, 0]])


def _lines(side: _Side, batch: Matrix) -> tuple[Matrix, Matrix, np.ndarray]:
    """Across coordinates (2, n, ...) of the face's side e (index 0) and of the band's
    outer boundary f = e - w (1) under parameters ``batch`` (7, ...) = (c0, m, g, b0, b1,
    kA, kB) (parameter sets as columns), the outer boundary's slope along the side
    beyond the side's own (n, ...: the width's), and which piece shapes the width (0
    bottom edge, 1 and 2 the tapers, 3 none: clipped at zero)."""
    lines = (side.design @ batch).reshape((4, len(side.t)) + batch.shape[1:])  # e, the width's pieces
    pieces = lines[1:]
    piece = pieces.argmin(axis=0)
    width = np.minimum.reduce(pieces)
    piece[width <= 0.0] = 3
    np.subtract(lines[0], np.maximum(width, 0.0), out=lines[1])
    slopes = _PIECE_SLOPES @ batch
    slope = slopes[piece] if batch.ndim == 1 else slopes[piece, np.arange(batch.shape[1])]
    return lines[:2], slope, piece


def _residuals(side: _Side, batch: Matrix) -> Matrix:
    """Residuals (p, n, G) of the grey levels (model minus image) under parameter sets
    ``batch`` (7, G) (see ``_lines``)."""
    edges, dw_dt, _ = _lines(side, batch)
    slants = np.empty_like(edges)
    slants[0] = batch[1]
    # The band's outer boundary slants with the side plus the width's change along it.
    np.subtract(batch[1], dw_dt, out=slants[1])
    cover = coverage(side.across[:, None, :, None], edges, slants, side.blur, derivative=False)  # (p, 2, n, G)
    g, dark, bright = batch[2], side.dark[:, None], side.bright[:, None]
    # D + (g - D) cover_f + (B - g) cover_e, written so that g has no effect at all where
    # the band has no width (cover_f = cover_e): such starts tie exactly, not by roundoff.
    return (dark + (bright - dark) * cover[:, 0] - side.values[:, :, None]) + (g - dark) * (cover[:, 1] - cover[:, 0])


#: Which piece of the width (0 bottom edge, 1 taper A, 2 taper B) each of b0, b1, kA, kB shapes.
_PIECE_OF_PARAMETER = np.array([[0], [0], [1], [2]])
#: How the levels across the face's side and the band's outer boundary (bright - g,
#: g - dark) change with g.
_LEVEL_SLOPES = np.array([[-1.0], [1.0]])


def _residuals_and_jacobian(side: _Side, params: Matrix) -> tuple[Matrix, Matrix]:
    """Residuals (N,) of the grey levels (model minus image) under ``params`` and their
    Jacobian (N, 7).

    The same model as ``_residuals`` for one parameter set, written for few array
    operations: it runs in the fit's inner loop.
    """
    m, g = params[1:3].tolist()
    edges, dw_dt, piece = _lines(side, params)
    slants = np.empty_like(edges)
    slants[0] = m
    # The band's outer boundary slants with the side plus the width's change along it.
    np.subtract(m, dw_dt, out=slants[1])
    covers = coverage(side.across[:, None, :], edges, slants, side.blur)  # (2, p, 2, n)
    # Each edge's share and its derivative times the levels across it (the face's over the
    # band's, the band's over the far one's), summed over the two edges: the prediction
    # less the dark level, and its derivative with respect to c0.
    weighted = covers[::-1] * (side.level_offsets + g * _LEVEL_SLOPES)
    jac = np.empty((7,) + side.values.shape)
    np.add(weighted[:, :, 0], weighted[:, :, 1], out=jac[:2])
    residual = jac[1] + side.dark_less_values
    np.multiply(jac[0], side.t_spread, out=jac[1])
    np.subtract(covers[0, :, 1], covers[0, :, 0], out=jac[2])
    # d / d (b0, b1, kA, kB): only the piece that shapes the width moves it (f = e - w).
    boundary = np.where(piece == _PIECE_OF_PARAMETER, side.minus_width_basis, 0.0)
    np.multiply(weighted[0, :, 1], boundary[:, None, :], out=jac[3:])
    return residual.ravel(), jac.reshape(7, -1).T


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
