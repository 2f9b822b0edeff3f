"""Teach tab (Fig. C-2): the steps in the order an operator meets them, the next one named.

Per browser (operator only): begin teaching from scratch or from a stored job (its poses
and settings are kept until taught again); present a part where the cell can; move the
arm: jog in Cartesian steps of a chosen size or hold a button to jog at a chosen speed,
in the base or the tool frame, type a pose for the flange or the cup to move to, or drag
a 3D gizmo on the flange (the arm moves when the gizmo is let go); capture the desired
image (the page shows where the part is seen and a flange pose that views it as the demo
job's desired view does); the cup on the part (and the cup pose on it), suction, a test
pick, set the pick; carry the part into the metal part (the cell file's, drawn in 3D: go
above its pocket, the cup pose that sets the part in it), set the place and read the
place check; the check view; the start pose; threshold, gain, approach height and placement
tolerance; name and save. A button is enabled only while it can act: the operator's,
and the teaching ones while teaching. Shared: the vacuum sensor and what is still missing.
Viser gives the Python side no keyboard events: there are no jog keys (docs/operator-guide.md).

The buttons are a table (``TeachButton``): the label, when it is live (a predicate on the
controller's typed state), the command it sends (made from the browser's inputs) and what
it says on success; the step it teaches, for the checklist's next step.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import viser
import viser.transforms as vtf

from vservo.app.client_view import ClientView
from vservo.app.context import AppContext
from vservo.app.live_image import Overlay
from vservo.app.scene3d import part_pose_from_corners
from vservo.app.session import SessionView
from vservo.app.status import pendant_pose
from vservo.core.cell.kinematics import ToolMount
from vservo.core.errors import VservoError
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.spatial import (
    Matrix,
    inverse,
    matrix_from_pose,
    pose_error,
    pose_from_mm_deg,
    rot_x,
    rot_z,
    rotation_angle,
    transform,
)
from vservo.core.production.demo_job import DESIRED_cMo
from vservo.core.production.protocol import (
    BeginTeach,
    CancelTeach,
    CaptureCheckView,
    CaptureDesired,
    CentreCup,
    Command,
    ControllerState,
    EnterManual,
    GoHome,
    GoSurvey,
    JobDetail,
    Jog,
    LeaveManual,
    MoveJoint,
    MoveTo,
    Phase,
    PresentPart,
    Reply,
    SaveJob,
    SetPickPose,
    SetPlacePose,
    SetSettings,
    SetStartPose,
    Suction,
    Teaching,
    TeachStep,
    TestPick,
    ViewPart,
)
from vservo.core.production.protocol.commands import (
    APPROACH_M,
    GAIN,
    NEW_JOB_SETTINGS,
    PART_CENTRE_MM,
    PART_SIDE_M,
    PART_TURN_DEG,
    PLACEMENT_TOLERANCE_MM,
    THRESHOLD_PX,
    Range,
)
from vservo.core.production.protocol.state import HAND_MOVES, STANDING

NEW_JOB = "(new job)"
# Jog step: translation (m) and rotation (deg) per press.
STEPS = {
    "0.5 mm / 0.5 deg": (0.0005, 0.5),
    "1 mm / 1 deg": (0.001, 1.0),
    "5 mm / 2 deg": (0.005, 2.0),
    "10 mm / 5 deg": (0.010, 5.0),
    "20 mm / 10 deg": (0.020, 10.0),
}
TRANSLATIONS = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
ROTATIONS = ("+Rx", "-Rx", "+Ry", "-Ry", "+Rz", "-Rz")
GIZMO_FOLLOW = 1e-4  # m and rad: the gizmo is moved to the flange only when they differ by more
# Hold-to-jog: speed (m/s, deg/s) while a button is held; the page repeats the hold this often.
SPEEDS = {
    "slow: 2 mm/s, 2 deg/s": (0.002, 2.0),
    "medium: 10 mm/s, 5 deg/s": (0.010, 5.0),
    "fast: 25 mm/s, 10 deg/s": (0.025, 10.0),
}
HOLD_HZ = 5.0
# The cup pose offered for a pick: on the middle of the top face, pressed this far into its
# level compensator, as an operator jogs until it presses.
PICK_PRESS_M = 0.003
TOOLS = ("flange", "cup")
# "Go above the pocket" stops the carried part this high over where it sits in the pocket:
# clear of the walls (12 mm deep), near enough to go the rest in one straight move.
ABOVE_POCKET_M = 0.030
NEXT_COLOR = "orange"  # the next step's button: the theme's buttons are blue already
# What the page says under Part seen on a cell whose model is not measured (Teaching.model_measured).
NOMINAL_WARNING = (
    "**This cell was never commissioned**: Part seen, Flange to view it and Cup on it come from the nominal model and "
    "can be tens of mm off (60 mm and 22 mm with Table 5-5's errors). Use **View the part** and **Centre the cup on "
    "the part** instead: they rest on the image and the vacuum sensor alone."
)


class PoseEntryError(VservoError, ValueError):
    """A typed pose that is not six numbers."""


def parse_pose_mm_deg(text: str) -> Matrix:
    """A pose typed as 'X Y Z phi theta psi' (mm, deg; commas allowed), as the status line shows it."""
    words = text.replace(",", " ").split()
    try:
        values = [float(word) for word in words]
    except ValueError:
        raise PoseEntryError(f"{text!r}: type six numbers, X Y Z in mm then phi theta psi in deg") from None
    if len(values) != 6 or not np.all(np.isfinite(values)):
        raise PoseEntryError(f"{text!r}: type six numbers, X Y Z in mm then phi theta psi in deg")
    return matrix_from_pose(pose_from_mm_deg(values))


def pose_words(bMx: Matrix) -> str:
    """A pose as the move-to entry takes it: 'X Y Z phi theta psi' in mm and deg, 2 decimals,
    the angles as the status line shows them (pendant_pose)."""
    return " ".join(f"{v:.2f}" for v in pendant_pose(bMx))


def cup_on_part(bMo: Matrix, side_m: float = PART_SIDE_M) -> Matrix:
    """bMv for a pick of the part at bMo: the cup on the middle of its top face, pointing
    down, pressed PICK_PRESS_M, its x along the part's edge (as the demo job is taught)."""
    return bMo @ transform(rot_x(np.pi), (side_m / 2, side_m / 2, -PICK_PRESS_M))


def image_direction(bMe: Matrix, eMc: Matrix, button: str) -> str:
    """Which way the part moves in the image when the flange moves along a base axis:
    the opposite of the camera's motion, projected on the image's u (right) and v (down)."""
    axis = np.zeros(3)
    axis["XYZ".index(button[-1])] = 1.0 if button[0] == "+" else -1.0
    in_camera = -(bMe @ eMc)[:3, :3].T @ axis  # the part's apparent motion in C
    u, v, z = in_camera
    if abs(z) > max(abs(u), abs(v)):
        return "part larger" if z < 0 else "part smaller"
    if abs(u) >= abs(v):
        return "part right" if u > 0 else "part left"
    return "part down" if v > 0 else "part up"


def jog_step(button: str, step: str) -> tuple[list[float], list[float]]:
    """(translation m, rotation rad) of one press of a jog button at a step size."""
    return _jog(button, *STEPS[step])


def hold_step(button: str, speed: str) -> tuple[list[float], list[float]]:
    """(translation m, rotation rad) of one repeat of a held jog button: a HOLD_HZ-th of a second at ``speed``."""
    metres_s, degrees_s = SPEEDS[speed]
    return _jog(button, metres_s / HOLD_HZ, degrees_s / HOLD_HZ)


def _jog(button: str, metres: float, degrees: float) -> tuple[list[float], list[float]]:
    sign = 1.0 if button[0] == "+" else -1.0
    axis = "XYZ".index(button[-1].upper())
    translation, rotation = [0.0] * 3, [0.0] * 3
    if button in ROTATIONS:
        rotation[axis] = sign * np.deg2rad(degrees)
    else:
        translation[axis] = sign * metres
    return translation, rotation


def gizmo_pose(position: Any, wxyz: Any) -> Matrix:
    """bMe from a gizmo's position and quaternion."""
    return transform(vtf.SO3(np.asarray(wxyz, float)).as_matrix(), np.asarray(position, float))


Live = Callable[[ControllerState], bool]  # whether a button can act in the controller's state


def standing(state: ControllerState) -> bool:
    """No run moves the arm: a jog, a move or a part presented can act."""
    return state.phase in STANDING


def draft(state: ControllerState) -> Teaching | None:
    """The job being taught, as the state says it (None when not teaching)."""
    return state.teaching if state.phase is Phase.TEACHING else None


def teaching(state: ControllerState) -> bool:
    return draft(state) is not None


def taught(step: TeachStep) -> Live:
    """Live while teaching once ``step`` is taught."""
    return lambda state: (job := draft(state)) is not None and step in job.taught


def holding(wanted: bool) -> Live:
    """Live while teaching with the vacuum sensor reporting a part on the cup (or none)."""
    return lambda state: teaching(state) and state.holding_part == wanted


def offered(pose: str) -> Live:
    """Live while teaching once the controller offers the pose ``pose`` (a Teaching field)."""
    return lambda state: teaching(state) and teach_pose(state, pose) is not None


def teach_pose(state: ControllerState, name: str) -> Matrix | None:
    """One of the poses the controller offers while teaching (view_bMe, pocket_bMe, place_bMo), if known."""
    job = draft(state)
    return None if job is None else getattr(job, name)


def view_over_part(bMo: Matrix, eMc: Matrix, bMe_near: Matrix | None = None) -> Matrix:
    """bMe that sees the part at bMo as the demo job's desired view sees its part: the camera
    162 mm over the top face, the four corners around the laser spot. Of the four such views
    a quarter turn apart about the part (its square face looks the same from each), the one
    nearest ``bMe_near`` in turn when given: a move to it, and on from it to the views after
    it, then turns the wrist the least, never near a half turn (which way round it goes could
    then differ between the arm and its model)."""
    views = []
    for quarter in range(4):
        turned = bMo @ transform(t=(PART_SIDE_M / 2, PART_SIDE_M / 2, 0.0)) @ transform(rot_z(quarter * np.pi / 2))
        views.append(turned @ transform(t=(-PART_SIDE_M / 2, -PART_SIDE_M / 2, 0.0)) @ inverse(DESIRED_cMo) @ inverse(eMc))
    if bMe_near is None:
        return views[0]
    return min(views, key=lambda bMe: rotation_angle(bMe[:3, :3].T @ np.asarray(bMe_near)[:3, :3]))


def above_pocket(bMe_pocket: Matrix) -> Matrix:
    """The flange ABOVE_POCKET_M over the pose that sets the carried part in the pocket."""
    return transform(t=(0.0, 0.0, ABOVE_POCKET_M)) @ bMe_pocket


class TemplateError(VservoError, LookupError):
    """The chosen template job cannot be read, or lacks the pose asked for."""


class TeachForm:
    """One browser's Teach tab: its inputs, as the table's commands read them."""

    def __init__(self, app: AppContext) -> None:
        self.app = app
        self.handles: dict[str, Any] = {}  # the inputs by name, added as the tab is built

    def value(self, name: str) -> Any:
        return self.handles[name].value

    @property
    def state(self) -> ControllerState:
        return self.app.session.state

    @property
    def template(self) -> str | None:
        """The template job chosen, None for a new job."""
        return None if self.value("template") == NEW_JOB else self.value("template")

    def pose(self, name: str) -> Matrix:
        """A pose the controller offers while teaching (the button is live only once it does)."""
        pose = teach_pose(self.state, name)
        if pose is None:
            raise TemplateError(f"the controller offers no {name} now")
        return pose

    def template_pose(self, where: str, pose_of: Callable[[JobDetail], Matrix | None]) -> Matrix:
        """A pose of the template job (read from the controller: call it off viser's threads)."""
        detail = self.app.job_detail(self.template)
        if detail is None:
            raise TemplateError(f"job {self.template!r} cannot be read")
        pose = pose_of(detail)
        if pose is None:
            raise TemplateError(f"job {self.template!r} has no {where}")
        return pose

    def typed_pose(self) -> Matrix:
        """The flange pose of the move-to entry: typed for the flange or the cup."""
        bMx = parse_pose_mm_deg(self.value("target"))
        return bMx if self.value("tool") == "flange" else bMx @ inverse(self.app.scene.mount.eMv)


@dataclass(frozen=True)
class TeachButton:
    """One of the Teach tab's buttons: its label, when it is live, the command it sends (made
    from the browser's inputs), what it says on success; the step it teaches, if any."""

    label: str
    live: Live
    command: Callable[[TeachForm], Command]
    success: str | None = None
    hint: str | None = None
    icon: Any = None
    teaches: TeachStep | None = None
    from_template: bool = False  # reads the template job first (off viser's threads), live only with one chosen
    color: Any = None


def _go_to_template(where: str, pose_of: Callable[[JobDetail], Matrix | None]) -> TeachButton:
    return TeachButton(
        f"Go to the template's {where}",
        teaching,
        lambda form: MoveTo(form.template_pose(where, pose_of)),
        "arrived",
        from_template=True,
    )


BEGIN = TeachButton(
    "Begin teaching",
    lambda state: standing(state) and not teaching(state),
    lambda form: BeginTeach(form.template),
    icon=viser.Icon.SCHOOL,
)
PRESENT = TeachButton(
    "Present part here",
    standing,
    lambda form: PresentPart((form.value("part_x"), form.value("part_y")), form.value("part_turn")),
    "a new part is on the table",
    hint="A new part on the table, its top face's centre at X, Y, turned",
    icon=viser.Icon.BOX,
)


def hand_moves(state: ControllerState) -> bool:
    """Jogs and typed moves act: while teaching, or in manual mode."""
    return state.phase in HAND_MOVES


MOVE_THERE = TeachButton("Move there", hand_moves, lambda form: MoveTo(form.typed_pose()), "arrived", icon=viser.Icon.ARROW_RIGHT)
MOVE_JOINT = TeachButton(
    "Move there (joint path)",
    hand_moves,
    lambda form: MoveJoint(form.typed_pose()),
    "arrived",
    hint="The same target on a joint-space path: where the straight line would take a joint past its limit",
)
HOME = TeachButton(
    "Home", standing, lambda form: GoHome(), hint="The cell file's home pose, on a joint-space path", icon=viser.Icon.HOME
)
SURVEY = TeachButton(
    "Survey",
    standing,
    lambda form: GoSurvey(),
    hint="The camera over the table where parts are presented, on a joint-space path",
    icon=viser.Icon.EYE,
)
MANUAL = TeachButton(
    "Manual mode",
    lambda state: state.phase in (Phase.IDLE, Phase.DONE),
    lambda form: EnterManual(),
    hint="Jog and Move there outside teaching, until Leave manual mode",
)
LEAVE_MANUAL = TeachButton("Leave manual mode", lambda state: state.phase is Phase.MANUAL, lambda form: LeaveManual())
VIEW_PART = TeachButton(
    "View the part",
    teaching,
    lambda form: ViewPart(),
    "the part in view",
    hint="By the image alone, right on any cell: the laser spot onto the part's centre, the part as large as "
    "in the demo job's desired view",
)
CENTRE_CUP = TeachButton(
    "Centre the cup on the part",
    lambda state: teaching(state) and not state.holding_part,
    lambda form: CentreCup(),
    "cup centred on the part",
    hint="From the desired view, by the camera and the vacuum sensor alone, right on any cell: the cup "
    "over the part's centre, lowered until it grips, left pressed with the suction off",
)
CAPTURE_DESIRED = TeachButton(
    "Capture desired image",
    teaching,
    lambda form: CaptureDesired(),
    "desired image captured",
    icon=viser.Icon.CAMERA,
    teaches=TeachStep.DESIRED_IMAGE,
)
SUCTION_ON = TeachButton("Suction on", holding(False), lambda form: Suction(True))
SUCTION_OFF = TeachButton("Suction off", holding(True), lambda form: Suction(False))
TEST_PICK = TeachButton(
    "Test pick",
    holding(False),
    lambda form: TestPick(),
    hint="Suction on, lift 5 mm, report the grip, put the part back down and release",
)
SET_PICK = TeachButton(
    "Set pick pose here",
    taught(TeachStep.DESIRED_IMAGE),
    lambda form: SetPickPose(),
    "pick pose set",
    teaches=TeachStep.PICK_POSE,
)
SET_PLACE = TeachButton(
    "Set place pose here",
    holding(True),
    lambda form: SetPlacePose(),
    "place pose set",
    hint="The part on the cup, in the metal part",
    teaches=TeachStep.PLACE_POSE,
)
CAPTURE_CHECK = TeachButton(
    "Capture check view",
    teaching,
    lambda form: CaptureCheckView(),
    "check view captured",
    hint="The part placed in the metal part, the camera over it seeing its four corners",
    icon=viser.Icon.CAMERA,
    teaches=TeachStep.CHECK_VIEW,
)
SET_START = TeachButton(
    "Set start pose here", teaching, lambda form: SetStartPose(), "start pose set", teaches=TeachStep.START_POSE
)
# The steps' folders, in the operator's order: the title, its place on the page, its buttons.
STEP_FOLDERS: tuple[tuple[str, int, tuple[TeachButton, ...]], ...] = (
    ("2. Desired view", 7, (_go_to_template("desired view", lambda job: job.taught_bMe), VIEW_PART, CAPTURE_DESIRED)),
    ("3. Pick", 8, (CENTRE_CUP, SUCTION_ON, SUCTION_OFF, TEST_PICK, SET_PICK)),
    (
        "4. Place",
        9,
        (
            TeachButton(
                "Go above the pocket",
                offered("pocket_bMe"),
                lambda form: MoveTo(above_pocket(form.pose("pocket_bMe"))),
                "arrived",
                hint="The carried part 30 mm over where it sits in the metal part's pocket",
            ),
            _go_to_template("place pose", lambda job: job.bMe_place),
            SET_PLACE,
        ),
    ),
    (
        "5. Check view",
        10,
        (
            TeachButton(
                "Go over the placed part",
                offered("place_bMo"),
                lambda form: MoveTo(view_over_part(form.pose("place_bMo"), form.app.scene.mount.eMc, form.state.bMe)),
                "arrived",
                hint="The camera over the part where the taught place sets it down, as over the part of the desired view",
            ),
            _go_to_template("check view", lambda job: job.check_bMe),
            CAPTURE_CHECK,
        ),
    ),
    (
        "6. Start pose",
        11,
        (
            TeachButton(
                "Go to the desired view",
                offered("view_bMe"),
                lambda form: MoveTo(form.pose("view_bMe")),
                "arrived",
                hint="Where the desired image was captured",
            ),
            _go_to_template("start pose", lambda job: job.start_bMe),
            SET_START,
        ),
    ),
)
APPLY = TeachButton(
    "Apply settings",
    teaching,
    lambda form: SetSettings(
        form.value("threshold"), form.value("gain"), form.value("approach") / 1000.0, form.value("tolerance")
    ),
    "settings applied",
)
SAVE = TeachButton(
    "Save job",
    lambda state: (job := draft(state)) is not None and not job.missing,
    lambda form: SaveJob(form.value("name").strip(), form.value("description")),
    icon=viser.Icon.DEVICE_FLOPPY,
    color="green",
)
CANCEL = TeachButton("Cancel teaching", teaching, lambda form: CancelTeach(), "teaching cancelled")


def next_button(state: ControllerState) -> str:
    """The button of the operator's next step, from what the draft has and what the cell
    says now: a test pick until one held, then the pick; with the part on the cup, the place,
    then Suction off before anything else; the check view, the start pose, Save."""
    job = draft(state)
    if job is None:
        return BEGIN.label
    taught, holding_part = job.taught, state.holding_part
    if TeachStep.DESIRED_IMAGE not in taught:
        return CAPTURE_DESIRED.label
    if TeachStep.PICK_POSE not in taught:
        return SET_PICK.label if job.test_pick_held else TEST_PICK.label
    if TeachStep.PLACE_POSE not in taught:
        return SET_PLACE.label if holding_part else SUCTION_ON.label
    if holding_part:
        return SUCTION_OFF.label
    if TeachStep.CHECK_VIEW not in taught:
        return CAPTURE_CHECK.label
    if TeachStep.START_POSE not in taught:
        return SET_START.label
    return SAVE.label


def teach_checklist(state: ControllerState) -> str:
    """What teaching still needs and the next step, or how to start it; the vacuum sensor."""
    job = draft(state)
    if job is None:
        return (
            "Not teaching. Keep **(new job)** (or choose a stored job as a template) and press **Begin teaching**.  \n"
            "**Next: Begin teaching**"
        )
    missing = [step.words for step in job.missing]
    optional = [step.words for step in job.optional_missing]
    also = (" Optional: " + ", ".join(optional) + ".") if optional else ""
    todo = ("Still to teach: " + ", ".join(missing) + ".") if missing else "Everything is taught: name the job and **Save**."
    sensor = "a part on the cup" if state.holding_part else "no part on the cup"
    return f"{todo}{also}  \n**Next: {next_button(state)}** · vacuum sensor: {sensor}"


def seen_markdown(state: ControllerState, overlay: Overlay | None, mount: ToolMount, camera: CameraModel) -> str:
    """Where the camera sees the part, a flange pose that views it for the desired image and
    the cup pose that picks it, for the move-to entry; once the pick is taught, the cup pose
    that sets the part in the cell file's pocket; which way the part moves in the image for
    each base-frame jog."""
    bMe, eMc = state.bMe, mount.eMc
    directions = " · ".join(f"{b}: {image_direction(bMe, eMc, b)}" for b in TRANSLATIONS)
    lines = [f"Jog in the base frame, in the image: {directions}"]
    corners = None if overlay is None else overlay.corners_px
    bMo = None if corners is None else part_pose_from_corners(corners, bMe, eMc, camera, PART_SIDE_M)
    if bMo is None:
        lines.append("Part seen: not all four corners are in view.")
    else:
        centre = bMo @ np.array([PART_SIDE_M / 2, PART_SIDE_M / 2, 0.0, 1.0])
        turn = np.rad2deg(np.arctan2(bMo[1, 0], bMo[0, 0]))
        lines.append(
            f"Part seen: top-face centre X {1000 * centre[0]:.2f} Y {1000 * centre[1]:.2f} "
            f"Z {1000 * centre[2]:.2f} mm, turned {turn:.2f} deg.  \n"
            f"Flange to view it: `{pose_words(view_over_part(bMo, eMc))}`  \n"
            f"Cup on it: `{pose_words(cup_on_part(bMo))}`"
        )
    job = draft(state)
    if job is not None and not job.model_measured and bMo is not None:
        lines.append(NOMINAL_WARNING)
    pocket = teach_pose(state, "pocket_bMe")
    if pocket is not None:
        bMv = pocket @ mount.eMv
        assumed = "" if job is None or job.model_measured else " (the part taken as centred on the cup)"
        lines.append(f"Cup in the pocket: `{pose_words(bMv)}`{assumed}")
    return "  \n".join(lines)


def _number(gui: Any, label: str, value: float, bounds: Range, step: float, scale: float = 1.0) -> Any:
    """A number input offering exactly what its command takes (``scale``: the page's unit per the command's)."""
    return gui.add_number(label, value * scale, min=bounds.low * scale, max=bounds.high * scale, step=step)


class TeachPanel:
    def __init__(self, app: AppContext, tab: viser.GuiTabHandle) -> None:
        self.app, self.tab = app, tab
        with tab:
            self.missing = app.server.gui.add_markdown("", order=3)
            self.seen = app.server.gui.add_markdown("", order=4)
        self._gizmos: dict[int, dict] = {}  # client id -> {"handle", "dragging"}
        # Per browser: its form, and its buttons with when each is live (and whether it needs a template).
        self._live: dict[int, tuple[ClientView, TeachForm, list[tuple[Any, Live, bool]]]] = {}
        self._lock = threading.Lock()

    def add_client(self, view: ClientView) -> None:
        form = TeachForm(self.app)
        buttons: list[tuple[Any, Live, bool]] = []
        with self.tab:
            self._add_top(view, form, buttons)
            if self.app.session.state.can_present_part:  # only where the cell can put a part down
                self._add_present(view, form, buttons)
            self._add_move(view, form, buttons)
            for title, order, rows in STEP_FOLDERS:
                with view.client.gui.add_folder(title, order=order):
                    for row in rows:
                        self._add_button(view, form, buttons, row)
            self._add_settings(view, form, buttons)
            self._add_save(view, form, buttons)
        view.handles["teach_template"] = form.handles["template"]
        form.handles["template"].on_update(lambda _: self._enable(view.client_id))
        with self._lock:
            self._live[view.client_id] = (view, form, buttons)

        def on_role(is_operator: bool) -> None:
            if not is_operator:  # a monitor has no gizmo
                form.handles["gizmo"].value = False
                self._show_gizmo(view, False)
            self._enable(view.client_id)

        view.on_role(on_role)
        self._enable(view.client_id)

    # -- building one browser's tab -------------------------------------------------------------

    def _add_button(
        self,
        view: ClientView,
        form: TeachForm,
        buttons: list[tuple[Any, Live, bool]],
        row: TeachButton,
        done: Callable[[Reply], None] | None = None,
        order: float | None = None,
    ) -> Any:
        """The row's button, disabled until the state makes it live; a click sends its command."""
        handle = view.client.gui.add_button(row.label, icon=row.icon, hint=row.hint, color=row.color, disabled=True, order=order)
        buttons.append((handle, row.live, row.from_template))

        def send() -> None:
            self.app.send(view, row.label, lambda: row.command(form), row.success, done)

        handle.on_click(lambda _: self.app.in_background(send) if row.from_template else send())
        return handle

    def _add_top(self, view: ClientView, form: TeachForm, buttons: list[tuple[Any, Live, bool]]) -> None:
        gui = view.client.gui
        names = [NEW_JOB, *self.app.job_names()]
        form.handles["template"] = view.control(gui.add_dropdown("Template", names, initial_value=NEW_JOB, order=1))

        def began(reply: Reply) -> None:
            view.report(BEGIN.label)(reply)
            detail = self.app.job_detail(form.template) if reply.ok else None
            if detail is not None:  # the template's settings, to keep or change
                form.handles["threshold"].value, form.handles["gain"].value = detail.threshold_px, detail.gain
                form.handles["approach"].value = 1000.0 * detail.approach_m
                form.handles["tolerance"].value = detail.placement_tolerance_mm

        self._add_button(view, form, buttons, BEGIN, began, order=2)

    def _add_present(self, view: ClientView, form: TeachForm, buttons: list[tuple[Any, Live, bool]]) -> None:
        gui, c = view.client.gui, view.control
        with gui.add_folder("1. Present the part", order=5):
            form.handles["part_x"] = c(_number(gui, "Part X (mm)", -390.0, PART_CENTRE_MM, 0.5))
            form.handles["part_y"] = c(_number(gui, "Part Y (mm)", 0.0, PART_CENTRE_MM, 0.5))
            form.handles["part_turn"] = c(_number(gui, "Part turn (deg)", 0.0, PART_TURN_DEG, 0.5))
            self._add_button(view, form, buttons, PRESENT)

    def _add_move(self, view: ClientView, form: TeachForm, buttons: list[tuple[Any, Live, bool]]) -> None:
        """Jog by steps, a typed pose to move to, the gizmo, hold to jog."""
        gui, c = view.client.gui, view.control
        with gui.add_folder("Move the arm", order=6):
            for row in (HOME, SURVEY, MANUAL, LEAVE_MANUAL):
                self._add_button(view, form, buttons, row)
            frame = c(gui.add_dropdown("Frame", ("base", "tool"), initial_value="base"))
            step = c(gui.add_dropdown("Step", tuple(STEPS), initial_value="1 mm / 1 deg"))
            move = c(gui.add_button_group("Move", TRANSLATIONS))
            turn = c(gui.add_button_group("Turn", ROTATIONS))
            form.handles["tool"] = c(gui.add_dropdown("Move to: tool", TOOLS, initial_value="flange"))
            form.handles["target"] = c(gui.add_text("Pose X Y Z phi theta psi (mm, deg)", ""))
            self._add_button(view, form, buttons, MOVE_THERE)
            self._add_button(view, form, buttons, MOVE_JOINT)
            gizmo = form.handles["gizmo"] = c(gui.add_checkbox("3D gizmo on the flange (moves on release)", False))
            with gui.add_folder("Hold to jog", expand_by_default=False):
                speed = c(gui.add_dropdown("Speed", tuple(SPEEDS), initial_value=tuple(SPEEDS)[0]))
                holds = {name: gui.add_button(f"Hold {name}", disabled=True) for name in (*TRANSLATIONS, *ROTATIONS)}
        buttons.extend((handle, hand_moves, False) for handle in holds.values())

        def on_jog(event: Any) -> None:
            translation, rotation = jog_step(event.target.value, step.value)
            self.app.send(view, f"Jog {event.target.value}", lambda: Jog(translation, rotation, frame.value))

        move.on_click(on_jog)
        turn.on_click(on_jog)
        jogging = threading.Event()  # hold-to-jog: a jog of this browser's is under way
        for name, handle in holds.items():
            handle.on_hold(self._on_hold(view, name, lambda: (speed.value, frame.value), jogging), callback_hz=HOLD_HZ)
        gizmo.on_update(lambda _: self._show_gizmo(view, gizmo.value))

    def _on_hold(
        self, view: ClientView, name: str, choices: Callable[[], tuple[str, str]], jogging: threading.Event
    ) -> Callable[[Any], None]:
        """One short jog per repeat of the held button, at the chosen speed; a repeat while the
        last jog still moves is dropped, so letting go stops within one."""

        def hold(_: Any) -> None:
            if jogging.is_set():
                return
            jogging.set()
            speed, frame = choices()
            translation, rotation = hold_step(name, speed)

            def done(reply: Reply) -> None:
                jogging.clear()
                view.report(f"Jog {name}")(reply)

            self.app.send(view, f"Jog {name}", lambda: Jog(translation, rotation, frame), done=done)

        return hold

    def _add_settings(self, view: ClientView, form: TeachForm, buttons: list[tuple[Any, Live, bool]]) -> None:
        """A new job's settings, as the controller drafts it, in the ranges its command takes."""
        gui, c, new = view.client.gui, view.control, NEW_JOB_SETTINGS
        with gui.add_folder("Settings", order=12):
            form.handles["threshold"] = c(_number(gui, "Threshold (px)", new.threshold_px, THRESHOLD_PX, 0.1))
            form.handles["gain"] = c(_number(gui, "Gain", new.gain, GAIN, 0.05))
            form.handles["approach"] = c(_number(gui, "Approach height (mm)", new.approach_m, APPROACH_M, 1.0, 1000.0))
            tolerance = new.placement_tolerance_mm
            form.handles["tolerance"] = c(_number(gui, "Placement tolerance (mm)", tolerance, PLACEMENT_TOLERANCE_MM, 0.05))
            self._add_button(view, form, buttons, APPLY)

    def _add_save(self, view: ClientView, form: TeachForm, buttons: list[tuple[Any, Live, bool]]) -> None:
        gui, c = view.client.gui, view.control
        with gui.add_folder("Save", order=13):
            form.handles["name"] = c(gui.add_text("Job name", ""))
            form.handles["description"] = c(gui.add_text("Description", ""))

            def saved(reply: Reply) -> None:
                view.report(SAVE.label, f"job {form.value('name')!r} saved")(reply)
                if reply.ok:
                    self.app.forget_job(reply.result)
                    self.app.refresh_lists()

            self._add_button(view, form, buttons, SAVE, saved)
            self._add_button(view, form, buttons, CANCEL)

    # -- shared ---------------------------------------------------------------------------

    def remove_client(self, client_id: int) -> None:
        with self._lock:
            self._gizmos.pop(client_id, None)
            self._live.pop(client_id, None)

    def lists_changed(self, views: list[ClientView]) -> None:
        names = [NEW_JOB, *self.app.job_names()]
        for view in views:
            view.set_options("teach_template", names)

    def refresh(self, view: SessionView) -> None:
        self.missing.content = teach_checklist(view.state)
        self.refresh_seen(view)
        with self._lock:
            clients = list(self._live)
        for client_id in clients:
            self._enable(client_id)

    def refresh_seen(self, view: SessionView) -> None:
        """Where the part is seen, from the newest frame (the display thread calls this on each
        frame shown: a part presented while the arm stands still changes the frame, not the state)."""
        overlay = Overlay.from_meta(view.frame.meta) if view.frame is not None else None
        scene = self.app.scene  # the nominal tools and camera the controller believes in
        seen = seen_markdown(view.state, overlay, scene.mount, scene.camera)
        if self.seen.content != seen:
            self.seen.content = seen

    def _enable(self, client_id: int) -> None:
        """Each button enabled only while it can act: the operator's browser, and the state
        allows it (a template's, with one chosen); the next step's button in orange."""
        state = self.app.session.state
        with self._lock:
            entry = self._live.get(client_id)
        if entry is None:
            return
        view, form, buttons = entry
        upcoming = next_button(state)
        chosen = form.template is not None
        for handle, live, from_template in buttons:
            try:
                disabled = not (view.is_operator and live(state) and (chosen or not from_template))
                if handle.disabled != disabled:
                    handle.disabled = disabled
                color = NEXT_COLOR if handle.label == upcoming else ("green" if handle.label == SAVE.label else None)
                if handle.color != color:
                    handle.color = color
            except RuntimeError:  # viser removed it: its browser left
                return

    # -- the gizmo ----------------------------------------------------------------------------

    def _show_gizmo(self, view: ClientView, show: bool) -> None:
        """The operator's own gizmo (client scene: no other browser sees or drags it)."""
        with self._lock:
            current = self._gizmos.pop(view.client_id, None)
        if current is not None:
            current["handle"].remove()
        if not show or not view.is_operator:
            return
        bMe = self.app.session.state.bMe
        handle = view.client.scene.add_transform_controls(
            "/teach/flange_gizmo", scale=0.12, depth_test=False, wxyz=vtf.SO3.from_matrix(bMe[:3, :3]).wxyz, position=bMe[:3, 3]
        )
        entry = {"handle": handle, "dragging": False}

        def on_update(event: Any) -> None:
            entry["dragging"] = event.phase != "end"
            if event.phase == "end":
                bMe_target = gizmo_pose(event.target.position, event.target.wxyz)
                self.app.send(view, "Move to the gizmo", lambda: MoveTo(bMe_target))

        handle.on_update(on_update)
        with self._lock:
            self._gizmos[view.client_id] = entry

    def follow_flange(self, bMe: Matrix) -> None:
        """Keep each gizmo on the flange while it is not being dragged (the display thread calls this)."""
        with self._lock:
            entries = list(self._gizmos.values())
        for entry in entries:
            handle = entry["handle"]
            if entry["dragging"] or max(pose_error(gizmo_pose(handle.position, handle.wxyz), bMe)) < GIZMO_FOLLOW:
                continue
            try:
                handle.wxyz, handle.position = vtf.SO3.from_matrix(bMe[:3, :3]).wxyz, bMe[:3, 3]
            except RuntimeError:  # viser removed it: its browser left
                continue
