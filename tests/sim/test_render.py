"""The synthetic camera: frame format, noise, sub-pixel geometry of the cube's top face
against CameraModel.project, the laser spot's centroid, occlusion against ray casting,
partial views, uneven lighting and frame faults.

The geometric references are independent of the renderer: edge positions and areas come
from camera.project of points on the true 3-D edges, visibility from Scene.raycast.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.reference import homogeneous
from vservo.core.cell.scene import Cube, MetalPart, Scene
from vservo.core.geometry.camera import CameraModel, Distortion, Intrinsics, sony_xc55
from vservo.core.geometry.laser import Ray
from vservo.core.sim.raster import rasterize
from vservo.core.sim.render import SceneRenderer
from vservo.core.sim.render_settings import RenderSettings
from vservo.core.sim.sensor import FaultKind, FrameFault, smear_kernel

TABLE_Z = 0.0
SIDE = 0.020

PINHOLE = CameraModel(Intrinsics(fx=812.3, fy=809.1, u0=321.7, v0=238.4, width=640, height=480))
DISTORTED = CameraModel(PINHOLE.intrinsics, Distortion(k1=-0.18, k2=0.06, p1=0.0008, p2=-0.0005, k3=0.0))

# Side faces as dark as the table: the only thing brighter than the table is then the top
# face, and its area can be read off the image.
FLAT_SIDES = RenderSettings(side_grey_dark=60.0, side_grey_bright=60.0)


def rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def make_scene(yaw_deg=20.0, cube_xy=(0.0, 0.0), part_xy=(0.9, 0.9)) -> Scene:
    bMo = homogeneous(rot_z(math.radians(yaw_deg)), (cube_xy[0], cube_xy[1], TABLE_Z + SIDE))
    part = MetalPart(homogeneous(np.eye(3), (part_xy[0], part_xy[1], TABLE_Z + 0.010)))
    return Scene(TABLE_Z, Cube(bMo, SIDE), part)


def look_at(eye, target, roll_deg=0.0) -> np.ndarray:
    """bMc of a camera at ``eye`` whose optical axis passes through ``target``."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    # Image rows run downwards in B where they can (a level camera sees an upright scene).
    helper = np.array([0.0, 0.0, -1.0]) if abs(z[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.column_stack((x, y, z)) @ rot_z(math.radians(roll_deg))
    return homogeneous(R, eye)


def view_of_top(scene, distance, tilt_deg, azimuth_deg, roll_deg, offset=(0.003, -0.004)) -> np.ndarray:
    """A camera ``distance`` from a point near the top face's centre, tilted from vertical."""
    centre = scene.cube.corners_b.mean(axis=0) + np.array([offset[0], offset[1], 0.0])
    tilt, az = math.radians(tilt_deg), math.radians(azimuth_deg)
    eye = centre + distance * np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), math.cos(tilt)])
    return look_at(eye, centre, roll_deg)


def project_b(camera, bMc, points_b):
    cMb = np.linalg.inv(bMc)
    return camera.project(np.atleast_2d(points_b) @ cMb[:3, :3].T + cMb[:3, 3])


def shoelace(poly):
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y)))


def dense_top_face(camera, bMc, cube, per_edge=400):
    """The projected outline of the top face, densely sampled (distortion bends edges)."""
    c = cube.corners_b
    t = np.arange(per_edge)[:, None] / per_edge
    points = np.concatenate([c[i] + t * (c[(i + 1) % 4] - c[i]) for i in range(4)])
    return project_b(camera, bMc, points)


def dense_mark(camera, bMc, cube, n=720):
    a = 2 * np.pi * np.arange(n) / n
    mark_o = cube.mark_o + cube.mark_radius_m * np.column_stack((np.cos(a), np.sin(a), np.zeros(n)))
    mark_b = mark_o @ cube.bMo[:3, :3].T + cube.bMo[:3, 3]
    return project_b(camera, bMc, mark_b)


def edge_crossings(image, camera, bMc, a_b, b_b, fractions=(0.3, 0.5, 0.7), half=3, sharp=True):
    """(midpoint-crossing error, area-estimate error) in px at points along the true edge a-b.

    At each point the profile runs along the image row or column closest to the edge's
    normal, through the pixel centre nearest the edge. The true crossing of that row or
    column by the projected (curved) edge is found by solving on the 3-D edge. The
    midpoint estimate interpolates linearly where the profile crosses half-way between
    its two ends; the area estimate sums the normalized profile, which for an exactly
    area-sampled edge gives its position.
    """
    a_b, b_b = np.asarray(a_b, float), np.asarray(b_b, float)

    def at(t):
        return project_b(camera, bMc, a_b + t * (b_b - a_b))[0]

    mids, areas = [], []
    for t in fractions:
        p = at(t)
        tangent = at(t + 1e-4) - at(t - 1e-4)
        # Profile across the edge: down a column if the edge runs along u, else along a row.
        along, fixed_axis = (1, 0) if abs(tangent[0]) >= abs(tangent[1]) else (0, 1)
        fixed = int(round(p[fixed_axis]))
        s = t
        for _ in range(30):  # Newton with a numerical derivative: where the edge meets the line
            g = at(s)[fixed_axis] - fixed
            dg = (at(s + 1e-6)[fixed_axis] - at(s - 1e-6)[fixed_axis]) / 2e-6
            s -= g / dg
        truth = at(s)[along]
        centre = int(round(truth))
        idx = np.arange(centre - half, centre + half + 1)
        profile = (image[idx, fixed] if along == 1 else image[fixed, idx]).astype(float)
        lo, hi = profile[0], profile[-1]
        assert abs(hi - lo) > 20, f"no edge in the profile at t={t}: {profile}"
        n = (profile - lo) / (hi - lo)
        # One clean step (not, say, a face seen edge-on as a 2 px band): an edge at most 45
        # degrees off the profile's normal crosses at most 3 of its pixels.
        if sharp:
            assert np.count_nonzero((n > 0.01) & (n < 0.99)) <= 3, f"not a single edge at t={t}: {profile}"
        candidates = [j for j in range(len(n) - 1) if (n[j] - 0.5) * (n[j + 1] - 0.5) <= 0 and n[j] != n[j + 1]]
        estimates = [idx[j] + (0.5 - n[j]) / (n[j + 1] - n[j]) for j in candidates]
        mid = min(estimates, key=lambda e: abs(e - truth))
        mids.append(mid - truth)
        areas.append(idx[-1] + 0.5 - n.sum() - truth)
    return np.array(mids), np.array(areas)


def side_face_widths(camera, bMc, cube):
    """Image width (px, across the top edge) of each side face in view, None if turned away.

    A side face seen nearly edge-on is a thin band along a top edge; the profiles of
    ``edge_crossings`` need a plateau on either side, so the test poses avoid them.
    """
    c, widths = cube.corners_b, []
    for i in range(4):
        a, b = c[i], c[(i + 1) % 4]
        middle = 0.5 * (a + b)
        normal = middle - c.mean(axis=0)
        if (bMc[:3, 3] - middle) @ normal <= 0.0:
            widths.append(None)
            continue
        pa, pb = project_b(camera, bMc, a)[0], project_b(camera, bMc, b)[0]
        tangent = (pb - pa) / np.linalg.norm(pb - pa)
        down = project_b(camera, bMc, middle - cube.side_m * cube.bMo[:3, 2])[0] - project_b(camera, bMc, middle)[0]
        widths.append(abs(tangent[0] * down[1] - tangent[1] * down[0]))
    return widths


def top_edge_errors(image, camera, bMc, cube, sharp=True):
    assert all(w is None or w > 4.0 for w in side_face_widths(camera, bMc, cube)), "a side face is seen edge-on"
    c = cube.corners_b
    mids, areas = zip(*(edge_crossings(image, camera, bMc, c[i], c[(i + 1) % 4], sharp=sharp) for i in range(4)))
    return np.concatenate(mids), np.concatenate(areas)


# Distance (m), tilt from vertical (deg), azimuth (deg), roll about the axis (deg), camera.
POSES = [
    (0.162, 0.0, 0.0, 180.0, PINHOLE),  # the task-1 desired view: edges along the pixel grid
    (0.162, 0.0, 0.0, 180.0, DISTORTED),
    (0.20, 25.0, 65.0, 45.0, PINHOLE),  # two side faces in view
    (0.25, 15.0, 30.0, 10.0, DISTORTED),
    (0.30, 8.0, 300.0, 0.0, DISTORTED),
    (0.40, 25.0, 245.0, -30.0, DISTORTED),
]


# ---------------------------------------------------------------------------------------
# Format, determinism, noise
# ---------------------------------------------------------------------------------------


def test_frame_format_and_determinism():
    scene = make_scene()
    bMc = view_of_top(scene, 0.25, 10.0, 45.0, 0.0)
    renderer = SceneRenderer(DISTORTED, RenderSettings(noise_sigma=3.0, blur_sigma_px=0.6, lighting_gradient=0.2))
    spot = scene.cube.corners_b.mean(axis=0)
    a = renderer.render(scene, bMc, spot, np.random.default_rng(7))
    b = renderer.render(scene, bMc, spot, np.random.default_rng(7))
    c = renderer.render(scene, bMc, spot, np.random.default_rng(8))
    assert a.dtype == np.uint8 and a.shape == (480, 640)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    small = CameraModel(Intrinsics(400.0, 400.0, 160.0, 120.0, 320, 240))
    frame = SceneRenderer(small).render(scene, bMc, None, np.random.default_rng(0))
    assert frame.dtype == np.uint8 and frame.shape == (240, 320)


def test_frames_do_not_carry_over_between_renders():
    # The renderer reuses its frame buffers: a frame must not depend on what was drawn
    # before it, smeared, blurred, seen from elsewhere or held by the caller.
    scene = make_scene()
    here, there = view_of_top(scene, 0.25, 10.0, 45.0, 0.0), view_of_top(scene, 0.4, 30.0, 120.0, 15.0)
    renderer = SceneRenderer(DISTORTED, RenderSettings(noise_sigma=2.0, blur_sigma_px=0.6))
    first = renderer.render(scene, here, None, np.random.default_rng(3))
    first.fill(0)  # the caller's copy
    renderer.render(scene, there, scene.cube.corners_b.mean(axis=0), np.random.default_rng(4), fault=FrameFault.smear(5.0))
    again = renderer.render(scene, here, None, np.random.default_rng(3))
    fresh = SceneRenderer(DISTORTED, RenderSettings(noise_sigma=2.0, blur_sigma_px=0.6)).render(
        scene, here, None, np.random.default_rng(3)
    )
    assert np.array_equal(again, fresh)


def test_noise_has_the_requested_sigma():
    scene = make_scene()
    bMc = view_of_top(scene, 0.25, 0.0, 0.0, 0.0, offset=(0.06, 0.0))  # the cube off to one side
    clean = SceneRenderer(PINHOLE).render(scene, bMc, None, np.random.default_rng(0))
    noisy = SceneRenderer(PINHOLE, RenderSettings(noise_sigma=5.0)).render(scene, bMc, None, np.random.default_rng(1))
    table = clean == 60
    table[:, 250:] = False  # keep well away from the cube
    assert table.sum() > 50_000
    diff = noisy[table].astype(float) - clean[table]
    assert abs(diff.mean()) < 0.1
    # Rounding to 8 bits adds 1/12 grey^2 of variance.
    assert diff.std() == pytest.approx(math.sqrt(25.0 + 1.0 / 12.0), rel=0.02)


def test_grey_levels():
    scene = make_scene()
    bMc = view_of_top(scene, 0.20, 25.0, 120.0, 0.0)
    st = RenderSettings()
    image = SceneRenderer(PINHOLE, st).render(scene, bMc, None, np.random.default_rng(0))
    values = set(np.unique(image).tolist())
    assert {round(st.table_grey), round(st.top_grey), round(st.mark_grey)} <= values
    face = project_b(PINHOLE, bMc, scene.cube.corners_b.mean(axis=0))[0]
    assert image[int(round(face[1])), int(round(face[0]))] == round(st.top_grey)


# ---------------------------------------------------------------------------------------
# Geometry of the top face against camera.project
# ---------------------------------------------------------------------------------------


def test_rasterizer_gives_exact_area_coverage():
    # A rectangle [2.25, 5.75] x [3.5, 6.0] in edge coordinates (cell (r, c) = [c, c+1] x [r, r+1]).
    square = np.array([[2.25, 3.5], [5.75, 3.5], [5.75, 6.0], [2.25, 6.0]])
    cov = rasterize([square[::-1]], np.array([[1.0]]), 0, 0, 8, 8)[0]
    expected = np.zeros((8, 8))
    for r in range(8):
        for c in range(8):
            expected[r, c] = max(0.0, min(c + 1, 5.75) - max(c, 2.25)) * max(0.0, min(r + 1, 6.0) - max(r, 3.5))
    np.testing.assert_allclose(cov, expected, atol=1e-12)
    # A triangle cut by the window: covered area inside the window, by winding number.
    triangle = np.array([[-3.0, 1.0], [6.0, 1.0], [-3.0, 10.0]])
    cov = rasterize([triangle[::-1]], np.array([[1.0]]), 0, 0, 4, 4)[0]
    # Inside x + y <= 7 (and y >= 1) over [0, 4] x [0, 4]: 12 minus the corner triangle of side 1, halved.
    assert cov.sum() == pytest.approx(12.0 - 0.5, abs=1e-12)
    assert cov[0].sum() == 0.0 and cov[3, 3] == pytest.approx(0.5)


@pytest.mark.parametrize("distance, tilt, azimuth, roll, camera", POSES)
def test_top_face_edges_are_where_the_camera_projects_them(distance, tilt, azimuth, roll, camera):
    scene = make_scene()
    bMc = view_of_top(scene, distance, tilt, azimuth, roll)
    image = SceneRenderer(camera).render(scene, bMc, None, np.random.default_rng(0))
    mid, area = top_edge_errors(image, camera, bMc, scene.cube)
    # Linear interpolation of a sharp, exactly area-sampled step is itself off by up to
    # 0.086 px for an edge along the pixel grid; the area estimate has no such bias.
    assert np.max(np.abs(mid)) < 0.1, mid
    assert np.max(np.abs(area)) < 0.02, area


@pytest.mark.parametrize("distance, tilt, azimuth, roll, camera", [POSES[1], POSES[3], POSES[4]])
def test_edges_stay_put_under_blur_and_supersampling(distance, tilt, azimuth, roll, camera):
    scene = make_scene()
    bMc = view_of_top(scene, distance, tilt, azimuth, roll)
    blurred = SceneRenderer(camera, RenderSettings(blur_sigma_px=0.8)).render(scene, bMc, None, np.random.default_rng(0))
    mid, _ = top_edge_errors(blurred, camera, bMc, scene.cube, sharp=False)
    assert np.max(np.abs(mid)) < 0.05, mid
    plain = SceneRenderer(camera).render(scene, bMc, None, np.random.default_rng(0))
    supersampled = SceneRenderer(camera, RenderSettings(supersample=3)).render(scene, bMc, None, np.random.default_rng(0))
    # Exact coverage and 3 x 3 area-averaging agree up to the rounding of both.
    assert np.max(np.abs(plain.astype(int) - supersampled.astype(int))) <= 1


@pytest.mark.parametrize(
    "distance, tilt, azimuth, roll, camera",
    [p for p in POSES if p[1] == 0.0]
    + [
        (0.25, 0.0, 0.0, 37.0, DISTORTED),
        (0.40, 0.0, 0.0, -71.0, PINHOLE),
    ],
)
def test_top_face_area_matches_the_projected_polygon(distance, tilt, azimuth, roll, camera):
    scene = make_scene()
    bMc = view_of_top(scene, distance, tilt, azimuth, roll, offset=(0.0005, -0.0004))
    st = FLAT_SIDES
    image = SceneRenderer(camera, st).render(scene, bMc, None, np.random.default_rng(0)).astype(float)
    outline = dense_top_face(camera, bMc, scene.cube)
    u0, v0 = np.floor(outline.min(axis=0)).astype(int) - 4
    u1, v1 = np.ceil(outline.max(axis=0)).astype(int) + 5
    window = (image[v0:v1, u0:u1] - st.table_grey) / (st.top_grey - st.table_grey)
    mark_weight = (st.mark_grey - st.table_grey) / (st.top_grey - st.table_grey)
    expected = shoelace(outline) - (1.0 - mark_weight) * shoelace(dense_mark(camera, bMc, scene.cube))
    assert window.sum() == pytest.approx(expected, rel=0.005)
    # Much better than the requirement: exact coverage, only 8-bit rounding is left.
    assert window.sum() == pytest.approx(expected, rel=5e-4)


# ---------------------------------------------------------------------------------------
# Laser spot
# ---------------------------------------------------------------------------------------


def spot_on_plane(camera, bMc, uv, plane_z):
    """The point of the plane z = plane_z in B that the camera sees at pixel uv."""
    d_c = camera.ray(np.asarray(uv, float))[0]
    d_b = bMc[:3, :3] @ d_c
    s = (plane_z - bMc[2, 3]) / d_b[2]
    return bMc[:3, 3] + s * d_b


def spot_centroid(image, expected, half=6):
    cu, cv = int(round(expected[0])), int(round(expected[1]))
    window = image[cv - half : cv + half + 1, cu - half : cu + half + 1].astype(float)
    border = np.concatenate((window[0], window[-1], window[1:-1, 0], window[1:-1, -1]))
    weights = np.clip(window - np.median(border), 0.0, None)
    v, u = np.mgrid[cv - half : cv + half + 1, cu - half : cu + half + 1]
    return np.array([(weights * u).sum(), (weights * v).sum()]) / weights.sum()


@pytest.mark.parametrize("camera", [PINHOLE, DISTORTED])
@pytest.mark.parametrize("on_top", [False, True])
def test_spot_centroid_is_the_projected_spot(camera, on_top):
    scene = make_scene()
    bMc = view_of_top(scene, 0.25, 12.0, 70.0, 20.0)
    renderer = SceneRenderer(camera)
    centre = project_b(camera, bMc, scene.cube.corners_b.mean(axis=0))[0]
    base = centre if on_top else centre + np.array([-150.0, 90.0])
    plane = TABLE_Z + SIDE if on_top else TABLE_Z
    worst = 0.0
    for du in np.linspace(0.0, 0.9, 4):
        for dv in np.linspace(0.05, 0.95, 4):
            spot_b = spot_on_plane(camera, bMc, base + np.array([du, dv]), plane)
            expected = project_b(camera, bMc, spot_b)[0]
            image = renderer.render(scene, bMc, spot_b, np.random.default_rng(0))
            # A laser saturates its core: the pixel nearest the centre, at most (0.5, 0.5) px
            # off, is at 255 on any surface, so a fixed-level threshold finds it.
            assert image[int(round(expected[1])), int(round(expected[0]))] == 255
            worst = max(worst, float(np.max(np.abs(spot_centroid(image, expected) - expected))))
    assert worst < 0.05


def test_no_spot_when_hidden_or_behind():
    scene = make_scene()
    bMc = view_of_top(scene, 0.25, 0.0, 0.0, 0.0)
    renderer = SceneRenderer(PINHOLE)
    plain = renderer.render(scene, bMc, None, np.random.default_rng(0))
    behind = bMc[:3, 3] + bMc[:3, 2] * -0.1  # 10 cm behind the camera
    assert np.array_equal(renderer.render(scene, bMc, behind, np.random.default_rng(0)), plain)


# ---------------------------------------------------------------------------------------
# Occlusion and partial views, against ray casting
# ---------------------------------------------------------------------------------------

GREY_CLASSES = {
    "background": (0, 0),
    "table": (60, 60),
    "top": (205, 205),
    "mark": (35, 35),
    "side": (110, 170),
    "metal": (55, 98),
}


def expected_class(scene, hit):
    if hit is None:
        return "background"
    if hit.surface == "table":
        return "table"
    if hit.surface == "metal_part":
        return "metal"
    oMb = np.linalg.inv(scene.cube.bMo)
    p = oMb[:3, :3] @ hit.point_b + oMb[:3, 3]
    if abs(p[2]) < 1e-9:
        return "mark" if np.hypot(*(p[:2] - scene.cube.mark_o[:2])) < scene.cube.mark_radius_m else "top"
    return "side"


def check_against_raycast(image, camera, bMc, scene, step=16, around_b=None):
    """Every sampled pixel whose neighbourhood sees one surface has that surface's grey.

    Samples a grid over the image, or over the image box of the points ``around_b``.
    """
    height, width = image.shape
    u0, u1, v0, v1 = 3, width - 3, 3, height - 3
    if around_b is not None:
        uv = project_b(camera, bMc, around_b)
        u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 5, 3)
        u1, v1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 5, [width - 3, height - 3])
    v, u = np.mgrid[v0:v1:step, u0:u1:step]
    offsets = [(0.0, 0.0), (-1.2, 0.0), (1.2, 0.0), (0.0, -1.2), (0.0, 1.2)]
    checked = 0
    for uu, vv in zip(u.ravel(), v.ravel()):
        classes = set()
        for du, dv in offsets:
            d = bMc[:3, :3] @ camera.ray(np.array([uu + du, vv + dv], float))[0]
            classes.add(expected_class(scene, scene.raycast(Ray(bMc[:3, 3], d))))
        if len(classes) != 1:
            continue  # an edge runs through this pixel's neighbourhood
        (name,) = classes
        lo, hi = GREY_CLASSES[name]
        value = int(image[vv, uu])
        assert lo - 1 <= value <= hi + 1, f"pixel ({uu}, {vv}) should be {name}, is {value}"
        checked += 1
    return checked


@pytest.mark.parametrize(
    "eye, target, camera, cube_xy",
    [
        ((0.20, -0.15, 0.18), (0.02, 0.05, 0.01), DISTORTED, (0.0, 0.0)),  # cube, part and pocket at once
        ((-0.12, 0.25, 0.10), (0.05, 0.0, 0.0), PINHOLE, (0.0, 0.0)),  # low view past the metal part at the cube
        ((0.01, 0.01, 0.03), (0.30, 0.01, 0.03), PINHOLE, (0.0, 0.0)),  # level, 1 cm over the cube: half of it behind
        ((0.17, 0.0, 0.06), (0.17, 0.0, 0.0), DISTORTED, (0.0, 0.0)),  # straight down into the pocket
        # Over the table's centre looking at a cube 0.7 m away: the table's centre is nearer
        # the camera than the cube's, so no sorting by distance gets this right.
        ((0.0, 0.0, 0.25), (0.7, 0.0, 0.0), PINHOLE, (0.7, 0.0)),
    ],
)
@pytest.mark.slow
def test_visibility_matches_ray_casting(eye, target, camera, cube_xy):
    scene = make_scene(yaw_deg=20.0, cube_xy=cube_xy, part_xy=(0.17, 0.0))
    bMc = look_at(eye, target)
    image = SceneRenderer(camera).render(scene, bMc, None, np.random.default_rng(0))
    assert check_against_raycast(image, camera, bMc, scene) > 800


@pytest.mark.slow
def test_cube_in_the_pocket_is_occluded_by_the_walls():
    part_p = homogeneous(np.eye(3), (0.17, 0.0, 0.010))
    # Resting on the pocket floor, centred, turned by 0.04 rad (its footprint, 20.8 mm wide,
    # fits the 22 mm pocket).
    R = rot_z(0.04)
    cube = Cube(homogeneous(R, np.array([0.17, 0.0, 0.010 + SIDE]) - R @ [SIDE / 2, SIDE / 2, 0.0]), SIDE)
    scene = Scene(TABLE_Z, cube, MetalPart(part_p))
    for eye, target in (((0.32, -0.1, 0.12), (0.17, 0.0, 0.02)), ((0.17, 0.002, 0.2), (0.17, 0.0, 0.0))):
        bMc = look_at(eye, target)
        image = SceneRenderer(DISTORTED).render(scene, bMc, None, np.random.default_rng(0))
        outer = scene.metal_part.pocket_side_m / 2 + scene.metal_part.wall_m
        box = np.array([[x, y, z] for x in (-outer, outer) for y in (-outer, outer) for z in (-0.01, 0.03)])
        assert check_against_raycast(image, DISTORTED, bMc, scene, step=7, around_b=box + [0.17, 0.0, 0.01]) > 600


def test_partial_views_render_the_visible_part():
    scene = make_scene()
    # Level camera 3 cm over the table: the table runs from under the camera to its far edge.
    bMc = look_at((-0.3, 0.0, 0.03), (0.5, 0.0, 0.03))
    image = SceneRenderer(DISTORTED).render(scene, bMc, None, np.random.default_rng(0))
    assert np.all(image[0] == 0) and np.all(image[-1] == 60)
    # Camera 5 mm over the top face, looking along it: the top face is cut by the near plane.
    corner = scene.cube.corners_b[0]
    bMc = look_at(corner + np.array([0.0, 0.0, 0.005]), corner + np.array([1.0, 0.0, -0.2]))
    image = SceneRenderer(PINHOLE).render(scene, bMc, None, np.random.default_rng(0))
    assert np.count_nonzero(image == 205) > 1000
    # 8 mm over the mark: the top face covers the whole view, the mark most of it.
    cube = scene.cube
    mark_b = cube.bMo[:3, :3] @ cube.mark_o + cube.bMo[:3, 3]
    bMc = look_at(mark_b + 0.008 * cube.bMo[:3, 2], mark_b)
    image = SceneRenderer(PINHOLE).render(scene, bMc, None, np.random.default_rng(0))
    mark_area = shoelace(clip_to_image(dense_mark(PINHOLE, bMc, cube), 640, 480)) / image.size
    assert 0.5 < mark_area < 1.0
    assert np.count_nonzero(image == 35) / image.size == pytest.approx(mark_area, abs=0.01)
    assert np.all((image == 35) | (image == 205) | ((image > 35) & (image < 205)))
    assert image[0, 0] == 205 and image[240, 320] == 35


def clip_to_image(poly, width, height):
    """Sutherland-Hodgman of a 2-D polygon to the image rectangle [-0.5, w-0.5] x [-0.5, h-0.5]."""
    for axis, limit, keep_below in ((0, -0.5, False), (0, width - 0.5, True), (1, -0.5, False), (1, height - 0.5, True)):
        out = []
        for i in range(len(poly)):
            p, q = poly[i], poly[(i + 1) % len(poly)]
            inside_p = p[axis] <= limit if keep_below else p[axis] >= limit
            inside_q = q[axis] <= limit if keep_below else q[axis] >= limit
            if inside_p:
                out.append(p)
            if inside_p != inside_q:
                out.append(p + (limit - p[axis]) / (q[axis] - p[axis]) * (q - p))
        poly = np.array(out)
    return poly


@pytest.mark.parametrize("camera", [PINHOLE, DISTORTED])
def test_cube_partly_out_of_the_image(camera):
    scene = make_scene()
    st = FLAT_SIDES
    centre = scene.cube.corners_b.mean(axis=0)
    for eye_offset in ((0.0, -0.047, 0.16), (0.07, 0.03, 0.16)):
        eye = centre + np.array(eye_offset)
        bMc = look_at(eye, eye - np.array([0.0, 0.0, 1.0]))
        outline = dense_top_face(camera, bMc, scene.cube)
        assert not camera.in_view(outline).all() and camera.in_view(outline).any()
        image = SceneRenderer(camera, st).render(scene, bMc, None, np.random.default_rng(0)).astype(float)
        mark = dense_mark(camera, bMc, scene.cube)
        assert camera.in_view(mark).all() or not camera.in_view(mark).any()
        mark_area = shoelace(mark) if camera.in_view(mark).all() else 0.0
        mark_weight = (st.mark_grey - st.table_grey) / (st.top_grey - st.table_grey)
        measured = ((image - st.table_grey) / (st.top_grey - st.table_grey)).sum()
        expected = shoelace(clip_to_image(outline, 640, 480)) - (1.0 - mark_weight) * mark_area
        assert measured == pytest.approx(expected, rel=0.005)


# ---------------------------------------------------------------------------------------
# Lighting and frame faults
# ---------------------------------------------------------------------------------------


def test_uneven_lighting_is_smooth_and_keeps_geometry():
    scene = make_scene()
    bMc = view_of_top(scene, 0.25, 15.0, 30.0, 10.0)
    clean = SceneRenderer(DISTORTED).render(scene, bMc, None, np.random.default_rng(0)).astype(float)
    lit = SceneRenderer(DISTORTED, RenderSettings(lighting_gradient=0.4)).render(scene, bMc, None, np.random.default_rng(0))
    table = clean == 60
    v, u = np.nonzero(table)
    ratio = lit[v, u] / 60.0
    assert ratio.max() - ratio.min() > 0.3  # it does change the intensities...
    # ...smoothly: a quadratic in (u, v) explains it down to the 8-bit rounding (1/60).
    basis = np.column_stack((np.ones_like(u), u, v, u * u, u * v, v * v)).astype(float)
    coefficients, *_ = np.linalg.lstsq(basis, ratio, rcond=None)
    residual = ratio - basis @ coefficients
    assert np.sqrt(np.mean(residual**2)) < 0.006 and np.max(np.abs(residual)) < 0.012
    mid, area = top_edge_errors(lit, DISTORTED, bMc, scene.cube)
    assert np.max(np.abs(mid)) < 0.1
    # The area estimate assumes flat plateaus; the lighting slopes them a little.
    assert np.max(np.abs(area)) < 0.1


def test_dropped_and_repeated_frames():
    scene = make_scene()
    renderer = SceneRenderer(PINHOLE, RenderSettings(noise_sigma=2.0))
    rng = np.random.default_rng(0)
    assert not renderer.render(scene, view_of_top(scene, 0.2, 0, 0, 0), None, rng, FrameFault.repeat()).any()
    first = renderer.render(scene, view_of_top(scene, 0.2, 0, 0, 0), None, rng)
    dropped = renderer.render(scene, view_of_top(scene, 0.3, 0, 0, 0), None, rng, FrameFault.dropped())
    assert dropped.shape == first.shape and dropped.dtype == np.uint8 and not dropped.any()
    repeated = renderer.render(scene, view_of_top(scene, 0.3, 0, 0, 0), None, rng, FrameFault.repeat())
    assert np.array_equal(repeated, first)
    assert FrameFault.dropped().kind is FaultKind.DROPPED


def transition_width(profile):
    """Distance (px) between the 10 % and 90 % crossings of a rising or falling step."""
    n = (profile - profile[0]) / (profile[-1] - profile[0])

    def crossing(level):
        j = int(np.argmax(n >= level))  # first sample at or past the level
        return j - 1 + (level - n[j - 1]) / (n[j] - n[j - 1])

    return crossing(0.9) - crossing(0.1)


def test_smeared_frame_blurs_along_the_motion_only():
    scene = make_scene(yaw_deg=0.0)
    bMc = look_at(scene.cube.corners_b.mean(axis=0) + np.array([0, 0, 0.2]), scene.cube.corners_b.mean(axis=0), 0.0)
    # Edges of the top face along the image axes (yaw 0, camera straight down).
    outline = project_b(PINHOLE, bMc, scene.cube.corners_b)
    renderer = SceneRenderer(PINHOLE)
    clean = renderer.render(scene, bMc, None, np.random.default_rng(0)).astype(float)
    smeared = renderer.render(scene, bMc, None, np.random.default_rng(0), FrameFault.smear(8.0, 0.0)).astype(float)
    u_left = outline[:, 0].min()
    v_mid = int(round(outline[:, 1].mean())) + 12  # below the mark
    cols = np.arange(int(u_left) - 8, int(u_left) + 9)
    assert transition_width(clean[v_mid, cols]) < 2.0  # a sharp step, interpolated
    assert 5.0 < transition_width(smeared[v_mid, cols]) < 8.0
    v_top = outline[:, 1].min()
    u_mid = int(round(outline[:, 0].mean())) + 12
    rows = np.arange(int(v_top) - 6, int(v_top) + 7)
    np.testing.assert_allclose(smeared[rows, u_mid], clean[rows, u_mid], atol=1.0)
    # A smear kernel is normalised and point-symmetric: it moves no centroid.
    k = smear_kernel(5.3, 0.7)
    assert k.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(k, k[::-1, ::-1], atol=1e-7)


def test_settings_are_validated():
    with pytest.raises(ValueError):
        RenderSettings(supersample=0)
    with pytest.raises(ValueError):
        RenderSettings(noise_sigma=-1.0)
    with pytest.raises(ValueError):
        RenderSettings(lighting_gradient=1.0)
    with pytest.raises(ValueError):
        FrameFault.smear(-2.0)
    # A lens model that folds over inside the image has no image to render.
    folding = CameraModel(PINHOLE.intrinsics, Distortion(k1=-0.9))
    with pytest.raises(ValueError, match="folds"):
        SceneRenderer(folding).render(make_scene(), view_of_top(make_scene(), 0.2, 0, 0, 0), None, np.random.default_rng(0))


def test_default_camera_renders_the_task_1_desired_view():
    """The thesis camera at the task-1 desired pose: corners of Table 5-2 within a pixel."""
    scene = make_scene(yaw_deg=0.0)
    cMo = homogeneous(rot_z(math.pi) @ np.diag([1.0, -1.0, -1.0]), (0.011, -0.01, 0.162))
    bMc = scene.cube.bMo @ np.linalg.inv(cMo)
    camera = sony_xc55()
    image = SceneRenderer(camera).render(scene, bMc, None, np.random.default_rng(0))
    corners = project_b(camera, bMc, scene.cube.corners_b)
    assert np.all(np.abs(np.sort(corners[:, 0]) - [275, 275, 375, 375]) < 0.1)
    mid, area = top_edge_errors(image, camera, bMc, scene.cube)
    assert np.max(np.abs(mid)) < 0.1 and np.max(np.abs(area)) < 0.02


def test_rasterize_a_polygon_outside_the_window_gives_float_zeros():
    """No edge piece in the window: numpy's bincount would hand back integers."""
    from vservo.core.sim.raster import rasterize

    above = np.array([[1.0, 1.0], [1.0, 3.0], [4.0, 3.0], [4.0, 1.0]])
    coverage = rasterize([above], np.array([[1.0, 0.5]]), 0, 10, 6, 4)
    assert coverage.dtype == np.float64 and coverage.shape == (2, 4, 6)
    assert not coverage.any()
