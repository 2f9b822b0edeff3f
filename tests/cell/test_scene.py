"""Scene geometry: box ray casting against a face-by-face solve and dense sampling,
the cube's frame convention, the metal part's pocket, and occlusion in the cell."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.reference import homogeneous, random_unit, rodrigues
from vservo.core.cell.scene import Box, Cube, MetalPart, Scene
from vservo.core.geometry.laser import Ray
from vservo.core.geometry.spatial import transform

# ---------------------------------------------------------------------------------------
# Independent references (no vservo.core.geometry.spatial beyond building inputs)
# ---------------------------------------------------------------------------------------


def to_box_frame(box, points):
    """Points (N, 3) in B into the box's centre frame, by a general matrix inverse."""
    xMb = np.linalg.inv(box.bMx)
    return np.asarray(points) @ xMb[:3, :3].T + xMb[:3, 3]


def inside(box, points, margin=0.0):
    """Which points (N, 3) in B lie in the box grown by ``margin``."""
    local = to_box_frame(box, np.atleast_2d(points))
    return np.all(np.abs(local) <= box.half_extents + margin, axis=1)


def face_solve(box, origin, direction):
    """First forward crossing of the box surface, one face plane at a time.

    For an origin outside the box this is the entry, for one inside the exit (a ray from
    inside a convex body crosses its surface once). None when no face is crossed.
    """
    xMb = np.linalg.inv(box.bMx)
    o = xMb[:3, :3] @ origin + xMb[:3, 3]
    d = xMb[:3, :3] @ direction
    h = box.half_extents
    best = None
    for axis in range(3):
        if d[axis] == 0.0:
            continue
        for sign in (-1.0, 1.0):
            s = (sign * h[axis] - o[axis]) / d[axis]
            if s < 0.0:
                continue
            p = o + s * d
            others = [i for i in range(3) if i != axis]
            if np.all(np.abs(p[others]) <= h[others] * (1 + 1e-12)):
                best = s if best is None else min(best, s)
    return best


def random_box(rng, name="box"):
    bMx = homogeneous(rodrigues(random_unit(rng) * rng.uniform(0, np.pi)), rng.uniform(-1, 1, 3))
    return Box(name, bMx, rng.uniform(0.01, 0.5, 3))


@pytest.fixture
def rng():
    return np.random.default_rng(7)


# ---------------------------------------------------------------------------------------
# Box.intersect
# ---------------------------------------------------------------------------------------


def test_box_intersect_against_face_solve_and_sampling(rng):
    hits = misses = insides = 0
    samples = np.linspace(0.0, 1.0, 4001)
    for _ in range(400):
        box = random_box(rng)
        centre = box.bMx[:3, 3]
        if rng.random() < 0.2:
            # Start inside the box.
            origin = box.bMx[:3, :3] @ (rng.uniform(-0.95, 0.95, 3) * box.half_extents) + centre
        else:
            origin = centre + random_unit(rng) * rng.uniform(0.6, 2.0)
        # Aim roughly at the box so that about half the rays hit it.
        direction = (centre + rng.normal(scale=0.4, size=3)) - origin
        ray = Ray(origin, direction)
        got = box.intersect(ray)
        expected = face_solve(box, ray.origin, ray.direction)
        started_inside = bool(inside(box, ray.origin)[0])
        # Dense sampling of the ray far beyond the box.
        length = float(np.linalg.norm(origin - centre) + 2 * np.linalg.norm(box.half_extents))
        sampled = ray.point_at(samples * length)
        sampled_inside = inside(box, sampled)
        if expected is None:
            misses += 1
            assert got is None
            assert not sampled_inside.any()
            continue
        assert got == pytest.approx(expected, abs=1e-12)
        # The returned point lies on the surface.
        local = to_box_frame(box, ray.point_at(got)[None])[0]
        assert np.max(np.abs(local) / box.half_extents) == pytest.approx(1.0, abs=1e-9)
        before = sampled_inside[samples * length < got - 1e-9]
        after_pt = ray.point_at(got + 1e-6)
        before_pt = ray.point_at(max(got - 1e-6, 0.0))
        if started_inside:
            insides += 1
            assert before.all()  # inside all along to the exit
            assert not inside(box, after_pt)[0]
        else:
            hits += 1
            assert not before.any()  # outside all along to the entry
            assert not inside(box, before_pt)[0]
            # Entering: just past the entry is inside, unless the chord is shorter than that.
            far = ray.point_at(length)
            chord_end = length - face_solve(box, far, -ray.direction)
            assert chord_end >= got - 1e-12
            if chord_end - got > 2e-6:
                assert inside(box, after_pt)[0]
            assert sampled_inside[(samples * length > got + 1e-9) & (samples * length < chord_end - 1e-9)].all()
    assert hits > 50 and misses > 50 and insides > 30


def test_box_intersect_misses_behind_and_beside(rng):
    for _ in range(50):
        box = random_box(rng)
        centre = box.bMx[:3, 3]
        away = random_unit(rng)
        origin = centre + away * (np.linalg.norm(box.half_extents) + 0.1)
        # Pointing away from the box: a convex body behind the origin is never hit.
        assert box.intersect(Ray(origin, away)) is None
        # Pointing at it: hit, at no more than the distance to the centre.
        distance = box.intersect(Ray(origin, -away))
        assert distance is not None
        assert 0.1 - 1e-12 <= distance <= np.linalg.norm(origin - centre)


def test_box_intersect_from_inside_returns_exit(rng):
    for _ in range(50):
        box = random_box(rng)
        local_origin = rng.uniform(-0.9, 0.9, 3) * box.half_extents
        origin = box.bMx[:3, :3] @ local_origin + box.bMx[:3, 3]
        direction = random_unit(rng)
        forward = box.intersect(Ray(origin, direction))
        backward = box.intersect(Ray(origin, -direction))
        assert forward is not None and backward is not None
        assert forward > 0 and backward > 0
        # The chord through the box, solved from the far end back in: same length.
        far = origin + forward * direction
        start = far + direction * 1.0
        entry = box.intersect(Ray(start, -direction))
        assert entry == pytest.approx(1.0, abs=1e-12)
        exit_back = box.intersect(Ray(origin - backward * direction - direction, direction))
        assert exit_back == pytest.approx(1.0, abs=1e-12)


def test_box_intersect_axis_parallel_rays():
    box = Box("b", transform(t=(1.0, 2.0, 3.0)), np.array([0.1, 0.2, 0.3]))
    for axis in range(3):
        for sign in (1.0, -1.0):
            direction = np.zeros(3)
            direction[axis] = sign
            # From outside, within the other two slabs: hits the near face.
            origin = np.array([1.0, 2.0, 3.0])
            origin[axis] -= sign * 2.0
            offset = np.array([0.05, -0.1, 0.2])
            offset[axis] = 0.0
            d = box.intersect(Ray(origin + offset, direction))
            assert d == pytest.approx(2.0 - box.half_extents[axis], abs=1e-12)
            # Outside one of the other slabs: parallel to it, never enters.
            for other in range(3):
                if other == axis:
                    continue
                shifted = origin.copy()
                shifted[other] += box.half_extents[other] + 1e-3
                assert box.intersect(Ray(shifted, direction)) is None
            # From the centre: exits at the half extent.
            assert box.intersect(Ray(np.array([1.0, 2.0, 3.0]), direction)) == pytest.approx(box.half_extents[axis], abs=1e-12)
            # Pointing away from the box along the axis: miss.
            assert box.intersect(Ray(origin, -direction)) is None


def test_box_intersect_axis_parallel_in_rotated_box(rng):
    """Along a face normal of a rotated box the other direction components are ~1e-17."""
    for _ in range(30):
        box = random_box(rng)
        R, centre = box.bMx[:3, :3], box.bMx[:3, 3]
        axis = int(rng.integers(3))
        lateral = rng.uniform(-0.9, 0.9, 3) * box.half_extents
        lateral[axis] = -box.half_extents[axis] - 0.5
        origin = R @ lateral + centre
        d = box.intersect(Ray(origin, R[:, axis]))
        assert d == pytest.approx(0.5, abs=1e-12)
        lateral[(axis + 1) % 3] = 1.1 * box.half_extents[(axis + 1) % 3]
        assert box.intersect(Ray(R @ lateral + centre, R[:, axis])) is None


def test_box_intersect_leaving_its_surface_reports_zero():
    box = Box("b", np.eye(4), np.array([0.1, 0.1, 0.1]))
    assert box.intersect(Ray(np.array([0.0, 0.0, 0.1]), np.array([0.0, 0.0, 1.0]))) == 0.0
    assert box.intersect(Ray(np.array([0.0, 0.0, 0.1 + 1e-9]), np.array([0.0, 0.0, 1.0]))) is None


# ---------------------------------------------------------------------------------------
# Cube
# ---------------------------------------------------------------------------------------


def random_cube(rng, side=0.020):
    bMo = homogeneous(rodrigues(random_unit(rng) * rng.uniform(0, np.pi)), rng.uniform(-0.5, 0.5, 3))
    return Cube(bMo, side)


def test_cube_corners(rng):
    for _ in range(30):
        side = rng.uniform(0.005, 0.05)
        cube = random_cube(rng, side)
        R, t = cube.bMo[:3, :3], cube.bMo[:3, 3]
        x, y = R[:, 0], R[:, 1]
        expected = np.array([t, t + side * x, t + side * (x + y), t + side * y])
        np.testing.assert_allclose(cube.corners_b, expected, atol=1e-15)
        np.testing.assert_allclose(cube.corners_o, [[0, 0, 0], [side, 0, 0], [side, side, 0], [0, side, 0]])
        # Consecutive corners one side apart, diagonals side * sqrt(2): a square.
        c = cube.corners_b
        for i in range(4):
            assert np.linalg.norm(c[(i + 1) % 4] - c[i]) == pytest.approx(side, rel=1e-12)
        assert np.linalg.norm(c[2] - c[0]) == pytest.approx(side * math.sqrt(2), rel=1e-12)
        assert np.linalg.norm(c[3] - c[1]) == pytest.approx(side * math.sqrt(2), rel=1e-12)
        # They lie on the top face: the cube body is on the -z side of O, and a ray cast
        # down -z of O from just above each corner (nudged into the face) meets the cube there.
        centre = t + R @ np.array([side / 2, side / 2, -side / 2])
        assert (centre - t) @ R[:, 2] == pytest.approx(-side / 2)
        for corner in c:
            nudge = 1e-6 * (centre - corner)
            nudge -= (nudge @ R[:, 2]) * R[:, 2]  # stay in the face plane
            start = corner + nudge + 0.1 * R[:, 2]
            assert cube.box.intersect(Ray(start, -R[:, 2])) == pytest.approx(0.1, abs=1e-12)
        # Moving the cube moves everything with it.
        moved = cube.moved_to(homogeneous(np.eye(3), [1.0, 2.0, 3.0]))
        np.testing.assert_allclose(moved.corners_b[2], [1.0 + side, 2.0 + side, 3.0])
        assert moved.side_m == side


def test_cube_box_is_the_region_below_its_top_face(rng):
    """Inside iff 0 <= x, y <= s and -s <= z <= 0 in O, tested only through intersect.

    For a point outside a convex body, the ray pointing away from any interior point (here
    the cube centre) misses it; for a point inside, every ray hits (at the exit).
    """
    n_in = n_out = 0
    for _ in range(20):
        side = rng.uniform(0.01, 0.05)
        cube = random_cube(rng, side)
        box = cube.box
        R, t = cube.bMo[:3, :3], cube.bMo[:3, 3]
        centre_o = np.array([side / 2, side / 2, -side / 2])
        centre_b = R @ centre_o + t
        for _ in range(60):
            p_o = rng.uniform([-0.5 * side, -0.5 * side, -1.5 * side], [1.5 * side, 1.5 * side, 0.5 * side])
            lower, upper = np.array([0.0, 0.0, -side]), np.array([side, side, 0.0])
            if np.min(np.abs(np.concatenate((p_o - lower, upper - p_o)))) < 1e-9:
                continue  # too close to the surface to call
            expected_inside = bool(np.all(p_o >= lower) and np.all(p_o <= upper))
            p_b = R @ p_o + t
            hit = box.intersect(Ray(p_b, p_b - centre_b))
            assert (hit is not None) == expected_inside
            if expected_inside:
                n_in += 1
                # The exit point lies on the boundary of the region, in O.
                exit_o = R.T @ (p_b + hit * (p_b - centre_b) / np.linalg.norm(p_b - centre_b) - t)
                assert np.all(exit_o >= lower - 1e-12) and np.all(exit_o <= upper + 1e-12)
                assert np.min(np.abs(np.concatenate((exit_o - lower, upper - exit_o)))) < 1e-12
                # And any other direction out of an inside point also hits.
                assert box.intersect(Ray(p_b, random_unit(rng))) is not None
            else:
                n_out += 1
    assert n_in > 100 and n_out > 300


# ---------------------------------------------------------------------------------------
# MetalPart
# ---------------------------------------------------------------------------------------


def first_hit(boxes, ray):
    distances = [d for d in (b.intersect(ray) for b in boxes) if d is not None]
    return min(distances) if distances else None


PARTS = [
    pytest.param(homogeneous(rodrigues([0, 0, 0.4]), [0.5, -0.2, 0.01]), id="upright"),
    pytest.param(homogeneous(rodrigues([0.3, -0.2, 1.1]), [0.4, 0.1, 0.2]), id="tilted"),
]


@pytest.mark.parametrize("bMp", PARTS)
def test_metal_part_pocket_floor_and_walls(bMp):
    part = MetalPart(bMp)
    R, origin = bMp[:3, :3], bMp[:3, 3]
    down = -R[:, 2]
    height = 0.2

    def cast_down(x, y):
        start = R @ np.array([x, y, height]) + origin
        ray = Ray(start, down)
        d = first_hit(part.boxes, ray)
        return None if d is None else ray.point_at(d)

    # Straight down the pocket centre: lands on the floor, at the pocket frame origin.
    np.testing.assert_allclose(cast_down(0.0, 0.0), origin, atol=1e-12)
    if np.allclose(R[:, 2], [0, 0, 1]):
        assert cast_down(0.0, 0.0)[2] == pytest.approx(bMp[2, 3], abs=1e-12)

    half_pocket, wall, depth = part.pocket_side_m / 2, part.wall_m, part.pocket_depth_m
    outer = half_pocket + wall
    # Anywhere inside the pocket opening: the floor, depth below the wall tops.
    for x, y in [(half_pocket - 1e-4, 0.0), (0.0, -(half_pocket - 1e-4)), (0.7 * half_pocket, -0.7 * half_pocket)]:
        p = cast_down(x, y)
        np.testing.assert_allclose(R.T @ (p - origin), [x, y, 0.0], atol=1e-12)
    # Through each wall, and the outer corners: the wall top, pocket_depth above the floor.
    mid = half_pocket + wall / 2
    for x, y in [(mid, 0.0), (-mid, 0.0), (0.0, mid), (0.0, -mid), (mid, mid), (-mid, mid), (0.5 * mid, -mid)]:
        p = cast_down(x, y)
        np.testing.assert_allclose(R.T @ (p - origin), [x, y, depth], atol=1e-12)
    # Just outside the block: nothing of the part is hit.
    for x, y in [(outer + 1e-4, 0.0), (0.0, -outer - 1e-4), (outer + 1e-4, outer + 1e-4)]:
        assert cast_down(x, y) is None


@pytest.mark.parametrize("bMp", PARTS)
def test_metal_part_height_map(bMp):
    """Cast down on a grid over the part: floor inside the pocket, wall tops around it."""
    part = MetalPart(bMp)
    R, origin = bMp[:3, :3], bMp[:3, 3]
    half_pocket = part.pocket_side_m / 2
    outer = half_pocket + part.wall_m
    for x in np.linspace(-outer - 0.002, outer + 0.002, 47):
        for y in np.linspace(-outer - 0.002, outer + 0.002, 47):
            if min(abs(abs(x) - half_pocket), abs(abs(y) - half_pocket), abs(abs(x) - outer), abs(abs(y) - outer)) < 1e-6:
                continue  # on an edge
            ray = Ray(R @ np.array([x, y, 0.1]) + origin, -R[:, 2])
            d = first_hit(part.boxes, ray)
            if abs(x) > outer or abs(y) > outer:
                assert d is None
                continue
            expected_z = 0.0 if abs(x) < half_pocket and abs(y) < half_pocket else part.pocket_depth_m
            assert d == pytest.approx(0.1 - expected_z, abs=1e-12), (x, y)


def test_metal_part_pocket_walls_are_closed():
    """A horizontal ray from the pocket centre meets a wall at the pocket edge in every direction."""
    part = MetalPart(np.eye(4))
    for angle in np.linspace(0, 2 * np.pi, 37):
        direction = np.array([math.cos(angle), math.sin(angle), 0.0])
        ray = Ray(np.array([0.0, 0.0, part.pocket_depth_m / 2]), direction)
        d = first_hit(part.boxes, ray)
        expected = (part.pocket_side_m / 2) / max(abs(direction[0]), abs(direction[1]))
        assert d == pytest.approx(expected, abs=1e-12)


# ---------------------------------------------------------------------------------------
# Scene
# ---------------------------------------------------------------------------------------

TABLE_Z = -0.05
SIDE = 0.020


@pytest.fixture
def scene():
    # The cube sits on the table (top face at TABLE_Z + SIDE), the part further along x.
    bMo = homogeneous(rodrigues([0, 0, 0.3]), [0.40, 0.10, TABLE_Z + SIDE])
    part = MetalPart(homogeneous(np.eye(3), [0.60, -0.20, TABLE_Z + 0.010]))
    return Scene(TABLE_Z, Cube(bMo, SIDE), part)


def cube_centre(scene):
    return scene.cube.bMo[:3, :3] @ np.array([SIDE / 2, SIDE / 2, -SIDE / 2]) + scene.cube.bMo[:3, 3]


def test_raycast_nearest_surface(scene):
    down = np.array([0.0, 0.0, -1.0])
    centre = cube_centre(scene)
    hit = scene.raycast(Ray(np.array([centre[0], centre[1], 0.5]), down))
    assert hit.surface == "cube"
    assert hit.distance_m == pytest.approx(0.5 - (TABLE_Z + SIDE), abs=1e-12)
    np.testing.assert_allclose(hit.point_b, [centre[0], centre[1], TABLE_Z + SIDE], atol=1e-12)

    hit = scene.raycast(Ray(np.array([0.0, 0.0, 0.5]), down))
    assert hit.surface == "table"
    np.testing.assert_allclose(hit.point_b, [0.0, 0.0, TABLE_Z], atol=1e-12)

    part_origin = scene.metal_part.bMp[:3, 3]
    hit = scene.raycast(Ray(part_origin + [0, 0, 0.3], down))
    assert hit.surface == "metal_part"
    np.testing.assert_allclose(hit.point_b, part_origin, atol=1e-12)

    # Up into the sky, and off the edge of the table: nothing.
    assert scene.raycast(Ray(np.array([0.0, 0.0, 0.5]), -down)) is None
    assert scene.raycast(Ray(np.array([1.5, 0.0, 0.5]), down)) is None


def test_raycast_oblique_picks_cube_side_over_table(scene):
    """A shallow ray toward the cube's side hits the cube before it would reach the table."""
    centre = cube_centre(scene)
    x_o = scene.cube.bMo[:3, 0]
    start = centre - 0.2 * x_o + np.array([0.0, 0.0, 0.001])
    target = centre + np.array([0.0, 0.0, -0.002])
    hit = scene.raycast(Ray(start, target - start))
    assert hit.surface == "cube"
    # The hit lies on the face x = 0 of O.
    p_o = scene.cube.bMo[:3, :3].T @ (hit.point_b - scene.cube.bMo[:3, 3])
    assert p_o[0] == pytest.approx(0.0, abs=1e-12)
    # Without the cube, the same ray reaches the table.
    away = scene.with_cube(scene.cube.moved_to(homogeneous(np.eye(3), [-0.5, -0.5, TABLE_Z + SIDE])))
    assert away.raycast(Ray(start, target - start)).surface == "table"


def test_visible_from_cube_corners(scene):
    centre = cube_centre(scene)
    above = centre + np.array([0.03, -0.02, 0.4])
    below_table = centre + np.array([0.05, 0.0, -0.3])
    for corner in scene.cube.corners_b:
        assert scene.visible_from(above, corner)
        assert not scene.visible_from(below_table, corner)
        hit = scene.raycast(Ray(below_table, corner - below_table))
        assert hit.surface == "table"


def test_visible_from_point_behind_cube(scene):
    centre = cube_centre(scene)
    x_o = scene.cube.bMo[:3, 0]
    ground = np.array([centre[0], centre[1], TABLE_Z])
    behind = ground + (SIDE / 2 + 0.01) * x_o
    in_front = ground - (SIDE / 2 + 0.01) * x_o
    low_eye = ground - 0.2 * x_o + np.array([0.0, 0.0, 0.01])  # below the cube top
    assert not scene.visible_from(low_eye, behind)
    assert scene.raycast(Ray(low_eye, behind - low_eye)).surface == "cube"
    # Controls: the same point seen from high up, and a point in front seen from the low eye.
    assert scene.visible_from(behind + np.array([0.0, 0.0, 0.5]), behind)
    assert scene.visible_from(low_eye, in_front)
    # And with the cube taken away, the point behind is visible from the low eye.
    away = scene.with_cube(scene.cube.moved_to(homogeneous(np.eye(3), [-0.5, -0.5, TABLE_Z + SIDE])))
    assert away.visible_from(low_eye, behind)


def test_scene_boxes(scene):
    names = [b.name for b in scene.boxes]
    assert names.count("table") == 1 and names.count("cube") == 1 and names.count("metal_part") == 5
    table = scene.boxes[names.index("table")]
    top = table.bMx[:3, :3] @ np.array([0, 0, table.half_extents[2]]) + table.bMx[:3, 3]
    assert top[2] == pytest.approx(TABLE_Z, abs=1e-15)
