"""The 3D view of the cell, shared by every browser: the arm, its camera and laser, the part.

- the UPJ from its URDF through Pinocchio's ViserVisualizer, posed from the joints the
  controller publishes (``state.q``);
- the tools on the flange from the NOMINAL tool mount of the cell file the controller runs
  on (what it believes, not the simulator's truth; after an applied commissioning, the
  commissioned file's): the vacuum cup (eMv), the camera's body and view frustum (eMc),
  the laser pointer and its beam (eMc cMl), each joined to the flange by a bracket line;
- the part where the vision puts it: the pose estimated from the four detected corners
  with the nominal camera (planar PnP), carried rigidly by the cup while it holds the part;
- the metal part where the selected job places the part (from its place pose); while a job
  is taught, where the cell file's [metal_part] says it stands, and the outline of the part
  where the taught pick and place set it down (the place check);
- the flange's path in the run under way.

Nothing here reads the simulated cell: the view is the controller's picture of the cell.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np
import viser
import viser.transforms as vtf
from pinocchio.visualize import ViserVisualizer

from vservo.app.live_image import Overlay
from vservo.core.cell.config import CellConfig, ConfigError, load_cell
from vservo.core.cell.kinematics import ToolMount
from vservo.core.cell.scene import Cube, MetalPart
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.pose_estimation import PoseEstimationError, pose_from_planar_points
from vservo.core.geometry.spatial import Matrix, inverse, rot_x, transform
from vservo.core.production.protocol import ControllerState, JobDetail, Phase
from vservo.core.production.protocol.commands import PART_SIDE_M
from vservo.robot_models.loader import load_arm

log = logging.getLogger("vservo.app")

RAY_LENGTH_M = 0.3  # the beam drawn when no part is known to end it on
PART_RGB = (230, 160, 40)
METAL_RGB = (150, 155, 165)
CAMERA_RGB = (40, 90, 220)
LASER_RGB = (240, 30, 30)
PATH_RGB = (20, 160, 90)
CUP_RGB = (30, 30, 30)
BRACKET_RGB = (90, 90, 90)
OUTLINE_RGB = (20, 200, 60)  # the part where the taught place sets it down
# The tools' bodies as drawn: the cup's bellows above its lip, the camera's housing behind
# its lens, the laser pointer's tube behind its aperture (m).
CUP_RADIUS_M, CUP_HEIGHT_M = 0.009, 0.020
CAMERA_BODY_M = (0.035, 0.035, 0.045)
LASER_RADIUS_M, LASER_LENGTH_M = 0.006, 0.040


def tool_bodies(bMe: Matrix, mount: ToolMount) -> dict[str, Matrix]:
    """Where each tool's body is drawn: its centre, z along the tool's axis (the cup's and
    the laser's towards the part, the camera's along its view); the body lies behind the
    tool's frame origin (the cup's lip, the lens, the aperture)."""
    behind = {"cup": CUP_HEIGHT_M / 2, "camera": CAMERA_BODY_M[2] / 2, "laser": LASER_LENGTH_M / 2}
    frames = {"cup": mount.eMv, "camera": mount.eMc, "laser": mount.eMl}
    return {name: bMe @ frames[name] @ transform(t=(0.0, 0.0, -behind[name])) for name in frames}


def part_pose_from_corners(
    corners_px: Matrix | None, bMe: Matrix, eMc: Matrix, camera: CameraModel, side_m: float
) -> Matrix | None:
    """bMo of the part from its four corners seen in one frame (None if not all are seen)."""
    if corners_px is None or not np.all(np.isfinite(corners_px)):
        return None
    try:
        cMo = pose_from_planar_points(corners_px, Cube(np.eye(4), side_m).corners_o, camera)
    except PoseEstimationError:
        return None
    return bMe @ eMc @ cMo


def placed_part_frame(bMe_place: Matrix, eMv: Matrix, side_m: float) -> Matrix:
    """bMp, the metal part's pocket frame (centre of its floor) for a job's place pose.

    At the place pose the cup is on the middle of the part's top face, pointing down
    (Fig. C-2's teaching): the part's bottom, a side lower, is the pocket's floor.
    """
    bMv = bMe_place @ eMv
    return bMv @ transform(rot_x(np.pi), (0.0, 0.0, side_m))


def part_outline(bMo: Matrix, side_m: float) -> Matrix:
    """The twelve edges of the part at bMo (O a top-face corner, z up) as (12, 2, 3) segments."""
    corners = np.array([[x, y, z, 1.0] for z in (0.0, -side_m) for x, y in ((0, 0), (side_m, 0), (side_m, side_m), (0, side_m))])
    points = (bMo @ corners.T).T[:, :3]
    edges = [(i, (i + 1) % 4) for i in range(4)] + [(4 + i, 4 + (i + 1) % 4) for i in range(4)] + [(i, i + 4) for i in range(4)]
    return np.array([[points[a], points[b]] for a, b in edges])


def laser_ray(bMe: Matrix, eMl: Matrix, part_top_z_m: float | None) -> tuple[Matrix, Matrix]:
    """Start and end of the beam (B): from the laser along +z of L, to the part's top plane if known."""
    bMl = bMe @ eMl
    origin, direction = bMl[:3, 3], bMl[:3, 2]
    length = RAY_LENGTH_M
    if part_top_z_m is not None and direction[2] < -1e-6:
        length = float(np.clip((part_top_z_m - origin[2]) / direction[2], 0.0, 2.0))
    return origin, origin + length * direction


class PartTracker:
    """Where the app shows the part: seen (PnP), or carried by the cup, or in the pocket once
    placed, or last known."""

    def __init__(self, mount: ToolMount, camera: CameraModel) -> None:
        self.mount, self.camera = mount, camera
        self.bMo: Matrix | None = None
        self._vMo: Matrix | None = None  # the part in the cup frame while it is held

    def update(self, state: ControllerState, overlay: Overlay | None, side_m: float, bMp: Matrix | None = None) -> Matrix | None:
        """bMp: the shown job's pocket frame, where a placed part sits."""
        bMe = state.bMe
        bMv = bMe @ self.mount.eMv
        if state.holding_part:
            if self._vMo is None:
                # Grasped: the part hangs from the cup as it was last seen, or centred under it.
                self._vMo = (
                    inverse(bMv) @ self.bMo
                    if self.bMo is not None
                    else inverse(transform(rot_x(np.pi), (side_m / 2, side_m / 2, 0.0)))
                )
            self.bMo = bMv @ self._vMo
            return self.bMo
        if self._vMo is not None and bMp is not None and state.phase in (Phase.PLACING, Phase.DONE):
            # Released in the pocket: the part's bottom face on the pocket's floor, as it hung from the cup.
            self.bMo = bMv @ self._vMo
            self.bMo[:3, 3] += bMp[:3, 3] - (self.bMo @ transform(t=(side_m / 2, side_m / 2, -side_m)))[:3, 3]
        self._vMo = None
        if overlay is not None and state.phase != Phase.DONE:
            seen = part_pose_from_corners(overlay.corners_px, bMe, self.mount.eMc, self.camera, side_m)
            if seen is not None:
                self.bMo = seen
        return self.bMo


def _wxyz(M: Matrix) -> np.ndarray:
    return vtf.SO3.from_matrix(M[:3, :3]).wxyz


@dataclass
class _Job:
    name: str
    side_m: float
    bMe_place: Matrix


class CellScene:
    """The shared scene (server.scene): built once, updated by the display thread."""

    def __init__(self, server: viser.ViserServer, config: CellConfig) -> None:
        self.server = server
        arm = load_arm(config.arm)
        self.robot = ViserVisualizer(arm.model, arm.collision_model, arm.visual_model)
        self.robot.initViewer(viewer=server)
        self.robot.loadViewerModel(rootNodeName="/cell/robot")
        self.robot.display(config.home_q)
        scene = server.scene
        self.frustum = scene.add_camera_frustum(
            "/cell/camera", fov=1.0, aspect=1.0, scale=0.05, thickness=0.002, color=CAMERA_RGB, visible=False
        )  # shown once the robot's pose is known
        self.part = scene.add_box("/cell/part", PART_RGB, (0.02, 0.02, 0.02), visible=False)
        self.tools = {
            "cup": scene.add_cylinder("/cell/tools/cup", CUP_RADIUS_M, CUP_HEIGHT_M, CUP_RGB, visible=False),
            "camera": scene.add_box("/cell/tools/camera", CAMERA_RGB, CAMERA_BODY_M, visible=False),
            "laser": scene.add_cylinder("/cell/tools/laser", LASER_RADIUS_M, LASER_LENGTH_M, LASER_RGB, visible=False),
        }  # shown, like the frustum, once the robot's pose is known
        self.metal: list = []
        # show_job (a browser's job choice) and update (the display thread) both touch the metal
        # part's boxes: one at a time, or update meets a box show_job has just removed.
        self._metal_lock = threading.Lock()
        # The cell file's metal part, drawn while a job is taught (a job's own follows its place pose).
        self.modelled_metal = (
            []
            if config.metal_part is None
            else [
                scene.add_box(
                    f"/cell/modelled_metal_part/{index}",
                    METAL_RGB,
                    2 * box.half_extents,
                    wxyz=_wxyz(box.bMx),
                    position=box.bMx[:3, 3],
                    visible=False,
                )
                for index, box in enumerate(config.metal_part.boxes)
            ]
        )
        self.place_outline = scene.add_line_segments(
            "/cell/teach/place_outline", np.zeros((12, 2, 3)), OUTLINE_RGB, thickness=0.003, visible=False
        )
        self._teaching_shown: tuple[bool, bytes | None] | None = None  # None: not shown yet
        self._use_model(config)
        self.job: _Job | None = None
        self._path_points = 0
        self.path: viser.LineSegmentsHandle | None = None
        # No shadows: an operator PC without a GPU (and headless Chromium) renders in software.
        server.scene.configure_default_lights(cast_shadow=False)
        # From the front right at the cell's middle, far enough back that the whole arm and the
        # table fit the narrowest view the page leaves it (some 200 px wide in a 1024x640 window).
        server.initial_camera.position = (0.3, -1.1, 0.79)
        server.initial_camera.look_at = (-0.22, 0.0, 0.28)

    def _use_model(self, config: CellConfig) -> None:
        """Draw the tools and the camera's view as ``config`` has them."""
        self.source, self.mount, self.camera = config.source, config.nominal.mount, config.nominal.camera
        intrinsics = self.camera.intrinsics
        self.frustum.fov = 2 * np.arctan2(intrinsics.height / 2, intrinsics.fy)
        self.frustum.aspect = intrinsics.width / intrinsics.height
        self.tracker = PartTracker(self.mount, self.camera)

    def _follow_the_controllers_model(self, cell_file: str | None) -> None:
        """The controller names the cell file it runs on; after an Apply it is the commissioned
        one, and the tools are drawn where that file puts them (the arm and the metal part
        stay: commissioning measures the camera, hand-eye and laser only)."""
        if not cell_file or cell_file == self.source:
            return
        try:
            config = load_cell(cell_file)
        except (ConfigError, OSError) as exc:
            log.error(
                "the controller runs on %s, which the app cannot read (%s): the 3D view keeps the tools of %s",
                cell_file,
                exc,
                self.source,
            )
            self.source = cell_file  # said once, not at every update
            return
        self._use_model(config)

    def show_job(self, job: JobDetail | None) -> None:
        """The metal part where ``job`` places the part; None hides it."""
        with self._metal_lock:
            self._show_job(job)

    def _show_job(self, job: JobDetail | None) -> None:
        for handle in self.metal:
            handle.remove()
        self.metal = []
        self._teaching_shown = None  # the new boxes' visibility is set on the next update
        if job is None:
            self.job = None
            return
        self.job = _Job(job.name, job.part_side_m, job.bMe_place)
        bMp = placed_part_frame(self.job.bMe_place, self.mount.eMv, self.job.side_m)
        for index, box in enumerate(MetalPart(bMp).boxes):
            self.metal.append(
                self.server.scene.add_box(
                    f"/cell/metal_part/{index}", METAL_RGB, 2 * box.half_extents, wxyz=_wxyz(box.bMx), position=box.bMx[:3, 3]
                )
            )

    def _show_teaching(self, state: ControllerState) -> None:
        """While teaching: the cell file's metal part instead of a job's, and the taught place's part outline."""
        teaching = state.phase == Phase.TEACHING
        placed = state.teaching.place_bMo if teaching and state.teaching is not None else None
        shown = (teaching, None if placed is None else placed.tobytes())
        if shown == self._teaching_shown:
            return  # every update would otherwise resend them to every browser
        self._teaching_shown = shown
        for handle in self.metal:
            handle.visible = not (teaching and self.modelled_metal)
        for handle in self.modelled_metal:
            handle.visible = teaching
        if placed is not None:
            outline = part_outline(placed, self.job.side_m if self.job else PART_SIDE_M)
            self.place_outline.points = outline.astype(np.float32)
        self.place_outline.visible = placed is not None

    def update(self, state: ControllerState, overlay: Overlay | None, path_m: Matrix) -> None:
        if not state.q.size:
            return  # no readout of the robot yet: no camera or beam at a made-up pose
        self._follow_the_controllers_model(state.cell_file)
        self.robot.display(state.q)
        bMe = state.bMe
        bMc = bMe @ self.mount.eMc
        self.frustum.wxyz, self.frustum.position, self.frustum.visible = _wxyz(bMc), bMc[:3, 3], True
        bodies = tool_bodies(bMe, self.mount)
        for name, bMx in bodies.items():
            self.tools[name].wxyz, self.tools[name].position, self.tools[name].visible = _wxyz(bMx), bMx[:3, 3], True
        brackets = np.array([[bMe[:3, 3], bMx[:3, 3]] for bMx in bodies.values()])
        self.server.scene.add_line_segments("/cell/tools/brackets", brackets, BRACKET_RGB, thickness=0.004)
        with self._metal_lock:
            self._show_teaching(state)
        side = self.job.side_m if self.job else PART_SIDE_M
        bMp = placed_part_frame(self.job.bMe_place, self.mount.eMv, side) if self.job else None
        bMo = self.tracker.update(state, overlay, side, bMp)
        if bMo is not None:
            centre = bMo @ transform(t=(side / 2, side / 2, -side / 2))
            self.part.dimensions = (side, side, side)
            self.part.wxyz, self.part.position, self.part.visible = _wxyz(centre), centre[:3, 3], True
        start, end = laser_ray(bMe, self.mount.eMl, None if bMo is None else float(bMo[2, 3]))
        self.server.scene.add_line_segments("/cell/laser", np.array([[start, end]]), LASER_RGB, thickness=0.002)
        if len(path_m) != self._path_points:
            self._path_points = len(path_m)
            if len(path_m) > 1:
                segments = np.stack([path_m[:-1], path_m[1:]], axis=1)
                self.path = self.server.scene.add_line_segments("/cell/path", segments, PATH_RGB, thickness=0.002)
            elif self.path is not None:
                self.path.visible = False  # a new run: its path starts afresh
