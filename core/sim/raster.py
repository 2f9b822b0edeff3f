"""Rasterising: the scene's boxes drawn into a float frame with exact pixel coverage.

Pixel convention (OpenCV's): an integer pixel coordinate is the CENTRE of that pixel,
so pixel (row r, column c) covers u in [c - 0.5, c + 0.5] and v in [r - 0.5, r + 0.5].
Internally the rasteriser works in "edge" coordinates X = u + 0.5, Y = v + 0.5, in
which pixel (r, c) is the unit cell [c, c + 1] x [r, r + 1].

How the scene becomes a frame (the sensor's effects come after, in sensor.py):

1. Every box of the scene (table, cube, the five boxes of the metal part) is taken into
   the camera frame; faces whose outward normal points away from the eye are culled.
   The remaining faces (and what is printed on a top face: the cube's orientation mark,
   a many-sided polygon of the disc's area, and the laid board's white sheet and black
   squares on the table) are clipped in 3-D against the near plane and against
   the viewing frustum of the image (grown by a margin), so geometry behind the camera
   or far outside the field never reaches the lens model, whose polynomial folds over
   far from the calibrated field.
2. The clipped polygons are projected to undistorted normalized coordinates (where a
   3-D edge is still straight), their edges subdivided every ``edge_segment_px``, and
   the vertices pushed through the lens distortion: straight edges become the right
   curves.
3. Each box is rasterised with EXACT area coverage (signed-area accumulation, as in
   font rasterisers: every edge deposits, cell by cell, the area to its right; a prefix
   sum along each row gives each pixel's covered fraction). The visible faces of one
   convex box tile its silhouette without overlap, so a box is composited in one step:
   image = image * (1 - coverage) + sum(face coverage * face grey). That makes the
   edges shared by two faces of a box exact (no background bleeding through), and the
   silhouette exactly anti-aliased against what lies behind. A printed polygon (the mark,
   the sheet, a square) has coverage weight 0 and grey weight (its grey - the grey under
   it) inside the top face, so a board's squares are as exactly anti-aliased as the
   box edges.
4. Boxes are drawn back to front. Boxes are convex and disjoint, so for two boxes a
   face plane of one that has the other wholly outside decides which can hide which
   (the eye's side of that plane); a topological sort of that relation, ties broken by
   distance, gives the painter's order. This is right where sorting faces by depth is
   not, e.g. the far inner wall of the pocket versus the pocket floor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

from vservo.core.cell.scene import Box, Cube, MetalPart, Scene
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.spatial import inverse, transform
from vservo.core.sim.render_settings import RenderSettings

# Local sign patterns of the four corners of each box face, for (axis, sign) pairs.
_FACES: tuple[tuple[int, float], ...] = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0), (2, 1.0), (2, -1.0))
# Touching boxes (cube on table, walls on the floor) share planes: a vertex this close
# to a plane counts as on its outer side.
_PLANE_TOLERANCE_M = 1e-7
# Margin (px) by which the clipping frustum exceeds the rendered canvas.
_FRUSTUM_MARGIN_PX = 16.0


def _next(a: np.ndarray) -> np.ndarray:
    """The rows shifted up by one, the first moved to the end: np.roll(a, -1, 0), faster."""
    return np.concatenate((a[1:], a[:1]))


def _face_patterns() -> np.ndarray:
    patterns = np.zeros((6, 4, 3))
    for k, (axis, sign) in enumerate(_FACES):
        b, c = [a for a in range(3) if a != axis]
        for j, (sb, sc) in enumerate(((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0))):
            patterns[k, j, axis] = sign
            patterns[k, j, b] = sb
            patterns[k, j, c] = sc
    return patterns


_FACE_PATTERNS = _face_patterns()


def rasterize(polygons: list[np.ndarray], weights: np.ndarray, x0: int, y0: int, width: int, height: int) -> np.ndarray:
    """Exact area coverage of polygons on a window of pixel cells.

    ``polygons`` are (n, 2) vertex arrays in edge coordinates (cell (r, c) is
    [c, c+1] x [r, r+1]); ``weights`` (P, C) gives each polygon C channel weights.
    Returns (C, height, width): for each channel the sum over polygons of weight times
    the fraction of each cell of the window [x0, x0+width) x [y0, y0+height) the polygon
    covers (counter-clockwise polygons, in the y-down image, count positive; callers
    orient them). Coverage is by winding number, so holes and overlaps add linearly.
    """
    weights = np.atleast_2d(np.asarray(weights, dtype=float))
    channels = weights.shape[1]
    if not polygons:
        return np.zeros((channels, height, width))
    lengths = np.array([len(p) for p in polygons])
    start = np.concatenate(polygons)
    end = np.concatenate([_next(p) for p in polygons])
    seg_weights = np.repeat(weights, lengths, axis=0)
    xa, ya, xb, yb = start[:, 0], start[:, 1], end[:, 0], end[:, 1]
    y_low, y_high = np.minimum(ya, yb), np.maximum(ya, yb)
    x_right = x0 + width
    keep = (y_high > y_low) & (y_high > y0) & (y_low < y0 + height) & (np.minimum(xa, xb) < x_right)
    keep &= np.isfinite(xa) & np.isfinite(ya) & np.isfinite(xb) & np.isfinite(yb)
    xa, ya, xb, yb, seg_weights = xa[keep], ya[keep], xb[keep], yb[keep], seg_weights[keep]
    y_low, y_high = y_low[keep], y_high[keep]
    dx, dy = xb - xa, yb - ya
    n = len(xa)
    if n == 0:
        return np.zeros((channels, height, width))

    def crossings(low: np.ndarray, high: np.ndarray, first: int, last: int, origin: np.ndarray, delta: np.ndarray):
        # Integer lines k strictly inside (low, high) and within [first, last].
        k_lo = np.maximum(np.floor(low) + 1.0, first)
        k_hi = np.minimum(np.ceil(high) - 1.0, last)
        count = np.maximum(k_hi - k_lo + 1.0, 0.0).astype(np.int64)
        seg = np.repeat(np.arange(n), count)
        offsets = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        k = k_lo[seg] + offsets
        return seg, (k - origin[seg]) / delta[seg]

    x_low, x_high = np.minimum(xa, xb), np.maximum(xa, xb)
    seg_x, t_x = crossings(x_low, x_high, x0, x_right, xa, dx)
    seg_y, t_y = crossings(y_low, y_high, y0, y0 + height, ya, dy)
    ids = np.arange(n)
    seg = np.concatenate((ids, ids, seg_x, seg_y))
    t = np.concatenate((np.zeros(n), np.ones(n), t_x, t_y))
    order = np.lexsort((t, seg))
    seg, t = seg[order], t[order]
    same = seg[1:] == seg[:-1]
    s, ta, tb = seg[:-1][same], t[:-1][same], t[1:][same]
    # Every piece now lies in one cell column (or wholly left / right of the window) and
    # one cell row.
    pya, pyb = ya[s] + ta * dy[s], ya[s] + tb * dy[s]
    xm = xa[s] + 0.5 * (ta + tb) * dx[s]
    ym = 0.5 * (pya + pyb)
    piece_dy = pyb - pya
    row = np.floor(ym).astype(np.int64) - y0
    valid = (row >= 0) & (row < height) & (xm < x_right) & (piece_dy != 0.0)
    row, xm, piece_dy, s = row[valid], xm[valid], piece_dy[valid], s[valid]
    # A piece left of the window puts its whole height into the first column.
    left = xm < x0
    column = np.floor(xm).astype(np.int64)
    frac = xm - column
    column -= x0
    column[left] = 0
    frac[left] = 0.0
    stride = width + 1
    index = row * stride + column
    size = height * stride
    # Cell (row, column) gets the area right of the piece inside it, (1 - frac) dy; the
    # next cell gets the rest, frac dy, so that after the prefix sum every cell further
    # right holds the piece's full height dy.
    heights = piece_dy[None, :] * seg_weights[s].T  # (C, pieces)
    channel_base = (np.arange(channels) * size)[:, None]
    flat = (index[None, :] + channel_base).ravel()
    acc = np.bincount(
        np.concatenate((flat, flat + 1)),
        weights=np.concatenate(((heights * (1.0 - frac)).ravel(), (heights * frac).ravel())),
        minlength=channels * size + 1,
    )
    # bincount returns integers when no piece falls in the window, whatever the weights.
    acc = acc.astype(np.float64, copy=False)
    return np.cumsum(acc[: channels * size].reshape(channels, height, stride), axis=2)[:, :, :width]


@dataclass
class _Group:
    """One convex box prepared for compositing."""

    centre_c: np.ndarray
    rotation_c: np.ndarray
    half: np.ndarray
    polygons: list[np.ndarray] = field(default_factory=list)  # normalized, then canvas coords
    weights: list[tuple[float, float]] = field(default_factory=list)
    fills_view: float | None = None  # grey if one face covers the whole canvas
    bbox: tuple[float, float, float, float] | None = None


class SceneRasterizer:
    """Draws a scene as the camera sees it, before any sensor effect (module docstring)."""

    def __init__(self, camera: CameraModel, settings: RenderSettings) -> None:
        self.camera = camera
        self.settings = settings
        self._frustum_cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        # The canvas is reused from frame to frame: a fresh 1 MB array costs more in page
        # faults than the arithmetic done in it.
        self._canvases: dict[tuple[int, int], np.ndarray] = {}
        az = math.radians(settings.light_azimuth_deg)
        self._light_b = np.array([math.cos(az), math.sin(az), 0.0])

    def _frustum(self, pad: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Clip planes (5, 3) with offsets (5,) in C, and the rectangle (xmin, xmax, ymin, ymax)
        of undistorted normalized coordinates that contains the padded canvas."""
        if pad in self._frustum_cache:
            return self._frustum_cache[pad]
        width, height = self.camera.image_size
        k = self.camera.intrinsics
        lo_u, hi_u = -pad - 0.5, width + pad - 0.5
        lo_v, hi_v = -pad - 0.5, height + pad - 0.5
        s = np.linspace(0.0, 1.0, 129)
        border = np.concatenate(
            (
                np.column_stack((lo_u + s * (hi_u - lo_u), np.full_like(s, lo_v))),
                np.column_stack((lo_u + s * (hi_u - lo_u), np.full_like(s, hi_v))),
                np.column_stack((np.full_like(s, lo_u), lo_v + s * (hi_v - lo_v))),
                np.column_stack((np.full_like(s, hi_u), lo_v + s * (hi_v - lo_v))),
            )
        )
        xn = self.camera.pixel_to_normalized(border)
        if np.all(np.isfinite(xn)):
            inner = np.array([xn[:, 0].min(), xn[:, 0].max(), xn[:, 1].min(), xn[:, 1].max()])
        else:  # the lens model does not invert out there: fall back on the pinhole box
            inner = np.array([(lo_u - k.u0) / k.fx, (hi_u - k.u0) / k.fx, (lo_v - k.v0) / k.fy, (hi_v - k.v0) / k.fy])
        mx, my = _FRUSTUM_MARGIN_PX / k.fx, _FRUSTUM_MARGIN_PX / k.fy
        xmin, xmax, ymin, ymax = inner[0] - mx, inner[1] + mx, inner[2] - my, inner[3] + my
        # Clipped polygons run along this rectangle's sides, outside the canvas only if the
        # lens model does not fold over before them.
        side = np.linspace(0.0, 1.0, 257)[:, None]
        rectangle = np.concatenate(
            [
                a + side * (b - a)
                for a, b in (
                    (np.array([xmin, ymin]), np.array([xmax, ymin])),
                    (np.array([xmax, ymin]), np.array([xmax, ymax])),
                    (np.array([xmax, ymax]), np.array([xmin, ymax])),
                    (np.array([xmin, ymax]), np.array([xmin, ymin])),
                )
            ]
        )
        uv = self.camera.normalized_to_pixel(rectangle)
        inside = (uv[:, 0] > lo_u) & (uv[:, 0] < hi_u) & (uv[:, 1] > lo_v) & (uv[:, 1] < hi_v)
        if np.any(inside):
            raise ValueError("the lens distortion folds over within the image: it cannot be rendered")
        planes = np.array([[1.0, 0.0, -xmin], [-1.0, 0.0, xmax], [0.0, 1.0, -ymin], [0.0, -1.0, ymax], [0.0, 0.0, 1.0]])
        offsets = np.array([0.0, 0.0, 0.0, 0.0, -self.settings.near_m])
        self._frustum_cache[pad] = (planes, offsets, inner)
        return planes, offsets, inner

    @staticmethod
    def _clip(poly: np.ndarray, planes: np.ndarray, offsets: np.ndarray) -> np.ndarray | None:
        """Sutherland-Hodgman clip of a 3-D polygon (n, 3) to planes . p + offset >= 0."""
        # (ndarray methods, not np.all: this runs for every face of every frame)
        d_all = poly @ planes.T + offsets
        if d_all.min() >= 0.0:
            return poly
        if (d_all.max(axis=0) < 0.0).any():
            return None
        for k in range(len(planes)):
            d = poly @ planes[k] + offsets[k]
            if d.min() >= 0.0:
                continue
            if d.max() < 0.0:
                return None
            out = []
            count = len(poly)
            for i in range(count):
                j = (i + 1) % count
                di, dj = d[i], d[j]
                if di >= 0.0:
                    out.append(poly[i])
                if (di >= 0.0) != (dj >= 0.0):
                    out.append(poly[i] + (di / (di - dj)) * (poly[j] - poly[i]))
            if len(out) < 3:
                return None
            poly = np.array(out)
        return poly

    def _face_grey(self, kind: str, axis: int, sign: float, normal_b: np.ndarray) -> float:
        st = self.settings
        light = float(normal_b @ self._light_b)
        if kind == "table":
            return st.table_grey
        if kind == "cube":
            if axis == 2 and sign > 0:
                return st.top_grey
            return st.side_grey_dark + (st.side_grey_bright - st.side_grey_dark) * (0.5 + 0.5 * light)
        if kind == "pocket_floor" and axis == 2 and sign > 0:
            return st.pocket_floor_grey
        if axis == 2 and sign > 0:
            return st.metal_grey
        return st.metal_grey * (1.0 + st.metal_side_shading * light)

    def _prepare(
        self, box: Box, kind: str, cMb: np.ndarray, planes, offsets, inner, decals: tuple[tuple[np.ndarray, float], ...] = ()
    ) -> _Group | None:
        """The box's visible faces; ``decals`` are (polygon in C, grey added) printed on
        its top face, each over the ones before it (the cube's mark, the board's sheet
        and squares)."""
        cRx = cMb[:3, :3] @ box.bMx[:3, :3]
        centre = cMb[:3, :3] @ box.bMx[:3, 3] + cMb[:3, 3]
        half = np.asarray(box.half_extents, dtype=float)
        group = _Group(centre, cRx, half)
        corners = centre + (_FACE_PATTERNS * half) @ cRx.T  # (6, 4, 3)
        bRx = box.bMx[:3, :3]
        for k, (axis, sign) in enumerate(_FACES):
            normal_c = cRx[:, axis] * sign
            face_centre = centre + normal_c * half[axis]
            if float(normal_c @ face_centre) >= 0.0:  # back face (or edge-on)
                continue
            face = corners[k]
            poly = self._clip(face, planes, offsets)
            if poly is None:
                continue
            grey = self._face_grey(kind, axis, sign, bRx[:, axis] * sign)
            xn = poly[:, :2] / poly[:, 2:3]
            # Only a face cut by the frustum can cover the whole view.
            if poly is not face and _covers_rectangle(xn, inner):
                group.fills_view = grey
            group.polygons.append(xn)
            group.weights.append((1.0, grey))
            if axis == 2 and sign > 0:
                for decal, added_grey in decals:
                    decal_poly = self._clip(decal, planes, offsets)
                    if decal_poly is not None:
                        group.polygons.append(decal_poly[:, :2] / decal_poly[:, 2:3])
                        group.weights.append((0.0, added_grey))
        return group if group.polygons else None

    def _prepare_metal(
        self, part: MetalPart, cube: Cube, cMb: np.ndarray, planes, offsets, inner
    ) -> _Group | Literal[False] | None:
        """The metal part as ONE group: the outer box with a hole in its top, and the
        pocket's inside seen through that hole (clipped to the pyramid from the eye
        through the hole's rim). Drawing its five boxes one by one would leave faint
        seams where their coplanar faces meet (each box's anti-aliased edge lets a little
        of the table through). Returns False when that model cannot be used: the cube is
        not clear of the part's outer box (it is in or on the pocket and must be ordered
        against each wall), or the opening reaches behind the camera.
        """
        hp, depth, floor = part.pocket_side_m / 2.0, part.pocket_depth_m, part.floor_m
        outer = hp + part.wall_m
        hull = Box(
            "metal_part",
            part.bMp @ transform(t=(0.0, 0.0, (depth - floor) / 2.0)),
            np.array([outer, outer, (depth + floor) / 2.0]),
        )
        if not _boxes_separated(hull, cube.box):
            return False
        group = self._prepare(hull, "metal", cMb, planes, offsets, inner)
        if group is None:
            return None
        cMp = cMb @ part.bMp
        top_normal = cMp[:3, 2]
        rim_c = cMp[:3, :3] @ np.array([0.0, 0.0, depth]) + cMp[:3, 3]
        if float(top_normal @ rim_c) >= 0.0:  # the top is not seen: neither is the pocket
            return group
        opening_p = np.array([[-hp, -hp, depth], [hp, -hp, depth], [hp, hp, depth], [-hp, hp, depth]])
        opening = opening_p @ cMp[:3, :3].T + cMp[:3, 3]
        if np.any(opening[:, 2] <= self.settings.near_m):
            return False
        hole = self._clip(opening, planes, offsets)
        if hole is None:
            return group
        top_grey = self.settings.metal_grey
        group.polygons.append(hole[:, :2] / hole[:, 2:3])
        group.weights.append((-1.0, -top_grey))
        # Pyramid from the eye through the opening: n . p >= 0 inside.
        centre = opening.mean(axis=0)
        pyramid = np.cross(opening, _next(opening))
        pyramid *= np.sign(pyramid @ centre)[:, None]
        all_planes = np.vstack((planes, pyramid))
        all_offsets = np.concatenate((offsets, np.zeros(4)))
        cavity = Box("pocket", part.bMp @ transform(t=(0.0, 0.0, depth / 2.0)), np.array([hp, hp, depth / 2.0]))
        cRx = cMb[:3, :3] @ cavity.bMx[:3, :3]
        middle = cMb[:3, :3] @ cavity.bMx[:3, 3] + cMb[:3, 3]
        corners = middle + (_FACE_PATTERNS * cavity.half_extents) @ cRx.T
        for k, (axis, sign) in enumerate(_FACES):
            if axis == 2 and sign > 0:  # the opening itself
                continue
            normal_c = cRx[:, axis] * sign  # out of the cavity, i.e. into the metal
            face_centre = middle + normal_c * cavity.half_extents[axis]
            if float(normal_c @ face_centre) <= 0.0:  # seen from inside only if it faces away
                continue
            poly = self._clip(corners[k], all_planes, all_offsets)
            if poly is None:
                continue
            if axis == 2:
                grey = self.settings.pocket_floor_grey
            else:
                grey = self._face_grey("metal", axis, -sign, -cavity.bMx[:3, axis] * sign)
            group.polygons.append(poly[:, :2] / poly[:, 2:3])
            group.weights.append((1.0, grey))
        return group

    def draw(self, scene: Scene, bMc: np.ndarray, pad: int) -> np.ndarray:
        """The float32 frame of ``scene`` from a camera at ``bMc``, grown by ``pad`` pixels
        on every side (the margin that blur and smear read from)."""
        st = self.settings
        k = int(st.supersample)
        width, height = self.camera.image_size
        canvas_w, canvas_h = k * (width + 2 * pad), k * (height + 2 * pad)
        if (canvas_h, canvas_w) not in self._canvases:
            self._canvases[canvas_h, canvas_w] = np.empty((canvas_h, canvas_w), dtype=np.float32)
        canvas = self._canvases[canvas_h, canvas_w]
        canvas.fill(st.background_grey)
        cMb = inverse(bMc)
        planes, offsets, inner = self._frustum(pad)

        groups: list[_Group] = []
        for box in scene.boxes:
            if box.name in ("cube", "metal_part"):
                continue
            decals = self._board_decals(scene, cMb) if box.name == "table" else ()
            group = self._prepare(box, "table" if box.name == "table" else "other", cMb, planes, offsets, inner, decals)
            if group is not None:
                groups.append(group)
        if not scene.parts_on_table:  # the table was cleared to lay the board
            return self._finish(canvas, groups, pad, k)
        cube = scene.cube
        n = st.mark_vertices
        angles = 2.0 * np.pi * np.arange(n) / n
        # The polygon with the disc's area, so the mark's integrated darkness is exact.
        radius = cube.mark_radius_m * math.sqrt(2.0 * math.pi / (n * math.sin(2.0 * math.pi / n)))
        mark_o = cube.mark_o + radius * np.column_stack((np.cos(angles), np.sin(angles), np.zeros(n)))
        cMo = cMb @ cube.bMo
        mark_c = mark_o @ cMo[:3, :3].T + cMo[:3, 3]
        group = self._prepare(cube.box, "cube", cMb, planes, offsets, inner, ((mark_c, st.mark_grey - st.top_grey),))
        if group is not None:
            groups.append(group)
        metal = self._prepare_metal(scene.metal_part, cube, cMb, planes, offsets, inner)
        if metal is False:  # the cube is in the pocket: five boxes, ordered one by one
            for i, box in enumerate(_metal_part_boxes(scene.metal_part)):
                group = self._prepare(box, "pocket_floor" if i == 0 else "metal", cMb, planes, offsets, inner)
                if group is not None:
                    groups.append(group)
        elif metal is not None:
            groups.append(metal)
        return self._finish(canvas, groups, pad, k)

    def _finish(self, canvas: np.ndarray, groups: list[_Group], pad: int, k: int) -> np.ndarray:
        if groups:
            self._to_canvas(groups, pad, k)
            for group in _painter_order(groups):
                self._composite(canvas, group)
        return self._downsample(canvas, k)

    def _board_decals(self, scene: Scene, cMb: np.ndarray) -> tuple[tuple[np.ndarray, float], ...]:
        """The laid board as decals on the table's top: the white sheet, then its black squares."""
        board = scene.board
        if board is None:
            return ()
        st = self.settings
        sheet = board.sheet_b @ cMb[:3, :3].T + cMb[:3, 3]
        squares = board.black_squares_b @ cMb[:3, :3].T + cMb[:3, 3]
        black = st.board_black_grey - st.board_white_grey
        return ((sheet, st.board_white_grey - st.table_grey), *((square, black) for square in squares))

    def _to_canvas(self, groups: list[_Group], pad: int, k: int) -> None:
        """Subdivide, distort and scale every polygon of every group into canvas
        coordinates, and orient the weights (the rasteriser counts clockwise-on-screen
        polygons, negative shoelace area in the y-down image, as positive)."""
        intr = self.camera.intrinsics
        polygons = [xn for group in groups for xn in group.polygons]
        lengths = np.array([len(xn) for xn in polygons])
        points = np.concatenate(polygons)
        starts = np.cumsum(lengths) - lengths
        following = np.arange(1, len(points) + 1)
        following[starts + lengths - 1] = starts
        if not self.camera.distortion.is_zero:
            # Chords of edge_segment_px along each straight (undistorted) edge.
            nxt = points[following]
            seg_len = np.hypot((nxt[:, 0] - points[:, 0]) * intr.fx, (nxt[:, 1] - points[:, 1]) * intr.fy)
            count = np.clip(np.ceil(seg_len / self.settings.edge_segment_px), 1, 4096).astype(np.int64)
            edge = np.repeat(np.arange(len(points)), count)
            t = (np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)) / count[edge]
            points = points[edge] + t[:, None] * (nxt[edge] - points[edge])
            lengths = np.add.reduceat(count, starts)
            starts = np.cumsum(lengths) - lengths
            following = np.arange(1, len(points) + 1)
            following[starts + lengths - 1] = starts
        pixels = self.camera.normalized_to_pixel(points)
        pixels = k * (pixels + (0.5 + pad))
        x, y = pixels[:, 0], pixels[:, 1]
        area2 = np.add.reduceat(x * y[following] - x[following] * y, starts)
        signs = np.where(area2 > 0.0, -1.0, 1.0)
        pieces = np.split(pixels, starts[1:])
        index = 0
        for group in groups:
            count = len(group.polygons)
            group.polygons = pieces[index : index + count]
            group.weights = [(sg * wc, sg * wg) for sg, (wc, wg) in zip(signs[index : index + count], group.weights)]
            index += count
            allpts = pixels[starts[index - count] : starts[index - 1] + lengths[index - 1]]
            group.bbox = (allpts[:, 0].min(), allpts[:, 0].max(), allpts[:, 1].min(), allpts[:, 1].max())

    @staticmethod
    def _composite(canvas: np.ndarray, group: _Group) -> None:
        canvas_h, canvas_w = canvas.shape
        if group.fills_view is not None and len(group.polygons) == 1:
            canvas.fill(group.fills_view)
            return
        xmin, xmax, ymin, ymax = group.bbox  # type: ignore[misc]
        x0, x1 = max(int(math.floor(xmin)), 0), min(int(math.ceil(xmax)), canvas_w)
        y0, y1 = max(int(math.floor(ymin)), 0), min(int(math.ceil(ymax)), canvas_h)
        if x1 <= x0 or y1 <= y0:
            return
        cov, grey = rasterize(group.polygons, np.array(group.weights), x0, y0, x1 - x0, y1 - y0)
        np.clip(cov, 0.0, 1.0, out=cov)
        window = canvas[y0:y1, x0:x1]
        window *= 1.0 - cov
        window += grey

    @staticmethod
    def _downsample(canvas: np.ndarray, k: int) -> np.ndarray:
        if k == 1:
            return canvas
        h, w = canvas.shape[0] // k, canvas.shape[1] // k
        return cv2.resize(canvas, (w, h), interpolation=cv2.INTER_AREA)


def _covers_rectangle(xn: np.ndarray, rect: np.ndarray) -> bool:
    """True if the convex polygon xn (n, 2) contains the rectangle (xmin, xmax, ymin, ymax)."""
    corners = np.array([[rect[0], rect[2]], [rect[1], rect[2]], [rect[1], rect[3]], [rect[0], rect[3]]])
    edges = _next(xn) - xn
    rel = corners[:, None, :] - xn[None, :, :]
    cross = edges[None, :, 0] * rel[:, :, 1] - edges[None, :, 1] * rel[:, :, 0]
    return bool(np.all(cross > 0.0) or np.all(cross < 0.0))


def _metal_part_boxes(part: MetalPart) -> tuple[Box, ...]:
    """The metal part as five boxes for drawing: the pocket floor, then four full-height walls.

    The same solid as ``MetalPart.boxes``, cut differently: the walls run from the
    bottom of the part to the rim, so no seam crosses the outer faces halfway up (the
    only seams left are the short vertical ones where two walls meet).
    """
    hp, depth, floor, wall = part.pocket_side_m / 2.0, part.pocket_depth_m, part.floor_m, part.wall_m
    outer = hp + wall
    mid_z, half_z = (depth - floor) / 2.0, (depth + floor) / 2.0
    boxes = [Box("metal_part", part.bMp @ transform(t=(0.0, 0.0, -floor / 2.0)), np.array([hp, hp, floor / 2.0]))]
    for sign in (-1.0, 1.0):
        centre = sign * (hp + wall / 2.0)
        boxes.append(Box("metal_part", part.bMp @ transform(t=(centre, 0.0, mid_z)), np.array([wall / 2.0, outer, half_z])))
        boxes.append(Box("metal_part", part.bMp @ transform(t=(0.0, centre, mid_z)), np.array([hp, wall / 2.0, half_z])))
    return tuple(boxes)


def _boxes_separated(a: Box, b: Box) -> bool:
    """True if a face plane of one box has the other wholly on its outer side."""
    for first, second in ((a, b), (b, a)):
        verts = second.bMx[:3, 3] + (_BOX_CORNERS * second.half_extents) @ second.bMx[:3, :3].T
        local = (verts - first.bMx[:3, 3]) @ first.bMx[:3, :3]
        for sign in (1.0, -1.0):
            if np.any(np.all(sign * local - first.half_extents >= -_PLANE_TOLERANCE_M, axis=0)):
                return True
    return False


def _painter_order(groups: list[_Group]) -> list[_Group]:
    """Back-to-front order of convex, disjoint boxes (camera at the origin of C).

    For each pair whose image boxes overlap, a face plane of one with the other wholly
    on its outer side separates them; the box on the eye's side of it is drawn later.
    """
    n = len(groups)
    if n == 1:
        return groups
    later: list[set[int]] = [set() for _ in range(n)]
    indegree = [0] * n

    def overlap(a: _Group, b: _Group) -> bool:
        return not (a.bbox[1] < b.bbox[0] or b.bbox[1] < a.bbox[0] or a.bbox[3] < b.bbox[2] or b.bbox[3] < a.bbox[2])  # type: ignore[index]

    def separated(a: _Group, b: _Group) -> bool | None:
        """True if a must be drawn before b, False if after, None if a's faces cannot tell."""
        verts_b = b.centre_c + (_BOX_CORNERS * b.half) @ b.rotation_c.T
        local = (verts_b - a.centre_c) @ a.rotation_c
        eye = (-a.centre_c) @ a.rotation_c
        for axis in range(3):
            for sign in (1.0, -1.0):
                if np.all(sign * local[:, axis] - a.half[axis] >= -_PLANE_TOLERANCE_M):
                    return bool(sign * eye[axis] - a.half[axis] > 0.0)
        return None

    for i in range(n):
        for j in range(i + 1, n):
            if not overlap(groups[i], groups[j]):
                continue
            first = separated(groups[i], groups[j])
            if first is None:
                second = separated(groups[j], groups[i])
                first = None if second is None else not second
            if first is None:
                continue
            a, b = (i, j) if first else (j, i)
            later[a].add(b)
            indegree[b] += 1
    distance = [float(np.linalg.norm(g.centre_c)) for g in groups]
    remaining = set(range(n))
    order = []
    while remaining:
        ready = [i for i in remaining if indegree[i] == 0] or list(remaining)
        pick = max(ready, key=lambda i: distance[i])
        remaining.discard(pick)
        order.append(groups[pick])
        for b in later[pick]:
            indegree[b] -= 1
    return order


_BOX_CORNERS = np.array([[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0) for sz in (-1.0, 1.0)])
