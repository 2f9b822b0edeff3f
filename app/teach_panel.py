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
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import viser
import viser.transforms as vtf

from vservo.app.client_view import ClientView
from vservo.app.context import AppContext
from vservo.app.live_image import Overlay
from vservo.app.scene3d import part_pose_from_corners
from vservo.app.session import SessionView
from vservo.core.cell.kinematics import ToolMount
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.spatial import (
    Matrix,
    inverse,
    matrix_from_pose,
    pose_error,
    pose_from_matrix,
    pose_from_mm_deg,
    pose_to_mm_deg,
    rot_x,
    transform,
)
from vservo.core.production.assembly import Phase
from vservo.core.production.cell_controller import PART_SIDE_M, TeachDraft
from vservo.core.production.demo_job import DESIRED_cMo

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


class PoseEntryError(ValueError):
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
    """A pose as the move-to entry takes it: 'X Y Z phi theta psi' in mm and deg, 2 decimals."""
    return " ".join(f"{v:.2f}" for v in np.round(pose_to_mm_deg(pose_from_matrix(bMx)), 2) + 0.0)


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


Live = Callable[[dict], bool]  # whether a button can act in the controller's state

TEACHING = Phase.TEACHING.value
STANDING = {Phase.IDLE.value, Phase.TEACHING.value, Phase.DONE.value, Phase.FAULT.value}  # no run moves the arm


def teach_pose(state: dict, name: str) -> Matrix | None:
    """One of the poses the controller offers while teaching (ControllerState.teach_poses), if known."""
    pose = (state.get("teach_poses") or {}).get(name)
    return None if pose is None else np.asarray(pose, float)


def teaching(state: dict) -> bool:
    return state.get("phase") == TEACHING


def standing(state: dict) -> bool:
    return state.get("phase") in STANDING


# The steps that teach a job, in the operator's order: what the state's teach_missing (or
# teach_optional) calls it and the button that does it.
TEACH_STEPS = (
    ("the desired image", "Capture desired image"),
    ("the pick pose", "Set pick pose here"),
    ("the place pose", "Set place pose here"),
    ("the check view", "Capture check view"),
    ("the start pose", "Set start pose here"),
)


def next_button(state: dict) -> str:
    """The button of the operator's next step."""
    if not teaching(state):
        return "Begin teaching"
    untaught = [*(state.get("teach_missing") or []), *(state.get("teach_optional") or [])]
    for words, button in TEACH_STEPS:
        if any(entry.startswith(words) for entry in untaught):
            return button
    return "Save job"


def teach_checklist(state: dict) -> str:
    """What teaching still needs and the next step, or how to start it; the vacuum sensor."""
    if not teaching(state):
        return (
            "Not teaching. Keep **(new job)** (or choose a stored job as a template) and press **Begin teaching**.  \n"
            "**Next: Begin teaching**"
        )
    missing = state.get("teach_missing") or []
    optional = state.get("teach_optional") or []
    also = (" Optional: " + ", ".join(optional) + ".") if optional else ""
    todo = ("Still to teach: " + ", ".join(missing) + ".") if missing else "Everything is taught: name the job and **Save**."
    sensor = "a part on the cup" if state.get("holding_part") else "no part on the cup"
    return f"{todo}{also}  \n**Next: {next_button(state)}** · vacuum sensor: {sensor}"


def view_over_part(bMo: Matrix, eMc: Matrix) -> Matrix:
    """bMe that sees the part at bMo as the demo job's desired view sees its part: the camera
    162 mm over the top face, the four corners around the laser spot."""
    return bMo @ inverse(DESIRED_cMo) @ inverse(eMc)


def above_pocket(bMe_pocket: Matrix) -> Matrix:
    """The flange ABOVE_POCKET_M over the pose that sets the carried part in the pocket."""
    return transform(t=(0.0, 0.0, ABOVE_POCKET_M)) @ bMe_pocket


def seen_markdown(state: dict, overlay: Overlay | None, mount: ToolMount, camera: CameraModel) -> str:
    """Where the camera sees the part, a flange pose that views it for the desired image and
    the cup pose that picks it, for the move-to entry; once the pick is taught, the cup pose
    that sets the part in the cell file's pocket; which way the part moves in the image for
    each base-frame jog."""
    bMe, eMc = np.asarray(state["bMe"], float), mount.eMc
    directions = " · ".join(f"{b}: {image_direction(bMe, eMc, b)}" for b in TRANSLATIONS)
    lines = [f"Jog in the base frame, in the image: {directions}"]
    bMo = None if overlay is None else part_pose_from_corners(overlay.corners_px, bMe, eMc, camera, PART_SIDE_M)
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
    pocket = teach_pose(state, "pocket_bMe")
    if pocket is not None:
        bMv = pocket @ mount.eMv
        lines.append(f"Cup in the pocket: `{pose_words(bMv)}`")
    return "  \n".join(lines)


class TeachPanel:
    def __init__(self, app: AppContext, tab: viser.GuiTabHandle) -> None:
        self.app, self.tab = app, tab
        with tab:
            self.missing = app.server.gui.add_markdown("", order=3)
            self.seen = app.server.gui.add_markdown("", order=4)
        self._gizmos: dict[int, dict] = {}  # client id -> {"handle", "dragging"}
        self._live: dict[int, tuple[ClientView, list[tuple[Any, Live]]]] = {}  # per browser: its buttons
        self._next: dict[int, dict[str, Any]] = {}  # per browser: the step buttons by label
        self._lock = threading.Lock()

    def add_client(self, view: ClientView) -> None:
        gui, app = view.client.gui, self.app
        c = view.control
        live: list[tuple[Any, Live]] = []

        def button(label: str, when: Live, **options: Any) -> viser.GuiButtonHandle:
            handle = gui.add_button(label, **options)
            handle.disabled = True
            live.append((handle, when))
            return handle

        with self.tab:
            template = c(gui.add_dropdown("Template", [NEW_JOB, *app.job_names()], initial_value=NEW_JOB, order=1))
            begin = button("Begin teaching", lambda s: s.get("phase") in STANDING - {TEACHING}, icon=viser.Icon.SCHOOL, order=2)
            from_template: Live = lambda s: teaching(s) and template.value != NEW_JOB  # noqa: E731
            present = None
            if app.session.state.get("can_present_part"):  # only where the cell can put a part down
                with gui.add_folder("1. Present the part", order=5):
                    part_x = c(gui.add_number("Part X (mm)", -390.0, step=0.5))
                    part_y = c(gui.add_number("Part Y (mm)", 0.0, step=0.5))
                    part_turn = c(gui.add_number("Part turn (deg)", 0.0, step=0.5))
                    present = button(
                        "Present part here",
                        standing,
                        icon=viser.Icon.BOX,
                        hint="A new part on the table, its top face's centre at X, Y, turned",
                    )
            with gui.add_folder("Move the arm", order=6):
                frame = c(gui.add_dropdown("Frame", ("base", "tool"), initial_value="base"))
                step = c(gui.add_dropdown("Step", tuple(STEPS), initial_value="1 mm / 1 deg"))
                move = c(gui.add_button_group("Move", TRANSLATIONS))
                turn = c(gui.add_button_group("Turn", ROTATIONS))
                tool = c(gui.add_dropdown("Move to: tool", TOOLS, initial_value="flange"))
                target = c(gui.add_text("Pose X Y Z phi theta psi (mm, deg)", ""))
                move_there = button("Move there", standing, icon=viser.Icon.ARROW_RIGHT)
                gizmo = c(gui.add_checkbox("3D gizmo on the flange (moves on release)", False))
                with gui.add_folder("Hold to jog", expand_by_default=False):
                    speed = c(gui.add_dropdown("Speed", tuple(SPEEDS), initial_value=tuple(SPEEDS)[0]))
                    holds = {name: button(f"Hold {name}", standing) for name in (*TRANSLATIONS, *ROTATIONS)}
            with gui.add_folder("2. Desired view", order=7):
                go_view = button("Go to the template's desired view", from_template)
                capture = button("Capture desired image", teaching, icon=viser.Icon.CAMERA)
            with gui.add_folder("3. Pick", order=8):
                suction_on = button("Suction on", lambda s: teaching(s) and not s.get("holding_part"))
                suction_off = button("Suction off", lambda s: teaching(s) and bool(s.get("holding_part")))
                test_pick = button(
                    "Test pick",
                    lambda s: teaching(s) and not s.get("holding_part"),
                    hint="Suction on, lift 5 mm, report the grip, put the part back down and release",
                )
                pick = button(
                    "Set pick pose here", lambda s: teaching(s) and "the desired image" not in (s.get("teach_missing") or [])
                )
            with gui.add_folder("4. Place", order=9):
                go_pocket = button(
                    "Go above the pocket",
                    lambda s: teaching(s) and teach_pose(s, "pocket_bMe") is not None,
                    hint="The carried part 30 mm over where it sits in the metal part's pocket",
                )
                go_place = button("Go to the template's place pose", from_template)
                place = button(
                    "Set place pose here",
                    lambda s: teaching(s) and bool(s.get("holding_part")),
                    hint="The part on the cup, in the metal part",
                )
            with gui.add_folder("5. Check view", order=10):
                go_over = button(
                    "Go over the placed part",
                    lambda s: teaching(s) and teach_pose(s, "place_bMo") is not None,
                    hint="The camera over the part where the taught place sets it down, as over the part of the desired view",
                )
                go_check = button("Go to the template's check view", from_template)
                check = button(
                    "Capture check view",
                    teaching,
                    icon=viser.Icon.CAMERA,
                    hint="The part placed in the metal part, the camera over it seeing its four corners",
                )
            with gui.add_folder("6. Start pose", order=11):
                go_desired = button(
                    "Go to the desired view",
                    lambda s: teaching(s) and teach_pose(s, "view_bMe") is not None,
                    hint="Where the desired image was captured",
                )
                go_start = button("Go to the template's start pose", from_template)
                start = button("Set start pose here", teaching)
            with gui.add_folder("Settings", order=12):
                # A new job's settings, as the controller drafts it.
                threshold = c(gui.add_number("Threshold (px)", TeachDraft.threshold_px, min=0.1, max=50.0, step=0.1))
                gain = c(gui.add_number("Gain", TeachDraft.gain, min=0.05, max=5.0, step=0.05))
                approach = c(gui.add_number("Approach height (mm)", 1000.0 * TeachDraft.approach_m, min=5.0, max=200.0, step=1.0))
                tolerance = c(
                    gui.add_number("Placement tolerance (mm)", TeachDraft.placement_tolerance_mm, min=0.05, max=20.0, step=0.05)
                )
                apply = button("Apply settings", teaching)
            with gui.add_folder("Save", order=13):
                name = c(gui.add_text("Job name", ""))
                description = c(gui.add_text("Description", ""))
                save = button(
                    "Save job", lambda s: teaching(s) and not s.get("teach_missing"), icon=viser.Icon.DEVICE_FLOPPY, color="green"
                )
                cancel = button("Cancel teaching", teaching)
        view.handles["teach_template"] = template
        send = app.send
        jogging = threading.Event()  # hold-to-jog: a jog of this browser's is under way

        def template_name() -> str | None:
            return None if template.value == NEW_JOB else template.value

        def on_begin(_: Any) -> None:
            def began(reply: Any) -> None:
                view.report("Begin teaching")(reply)
                detail = app.job_detail(template_name()) if reply.ok else None
                if detail is not None:  # the template's settings, to keep or change
                    threshold.value, gain.value = float(detail["threshold_px"]), float(detail["gain"])
                    approach.value = 1000.0 * float(detail["approach_m"])
                    tolerance.value = float(detail.get("placement_tolerance_mm", 1.0))  # absent in version 1

            send(view, "Begin teaching", "begin_teach", done=began, template=template_name())

        def go_to(where: str, pose_of: Callable[[dict], Any]) -> Callable[[Any], None]:
            def fetch_and_move() -> None:
                detail = app.job_detail(template_name())
                if detail is None:
                    view.notify("Go to", f"job {template_name()!r} cannot be read", error=True)
                    return
                pose = pose_of(detail)
                if pose is None:
                    view.notify("Go to", f"job {template_name()!r} has no {where}", error=True)
                    return
                send(view, f"Go to the template's {where}", "move_to", "arrived", bMe=pose)

            return lambda _: app.in_background(fetch_and_move)

        def on_jog(event: Any) -> None:
            translation, rotation = jog_step(event.target.value, step.value)
            send(view, f"Jog {event.target.value}", "jog", translation_m=translation, rotation_rad=rotation, frame=frame.value)

        def on_hold(name: str) -> Callable[[Any], None]:
            def hold(_: Any) -> None:
                # One short jog per repeat of the held button, at the chosen speed; a repeat
                # while the last jog still moves is dropped, so letting go stops within one.
                if jogging.is_set():
                    return
                jogging.set()
                translation, rotation = hold_step(name, speed.value)

                def done(reply: Any) -> None:
                    jogging.clear()
                    view.report(f"Jog {name}")(reply)

                send(view, f"Jog {name}", "jog", done=done, translation_m=translation, rotation_rad=rotation, frame=frame.value)

            return hold

        def on_move_there(_: Any) -> None:
            try:
                bMx = parse_pose_mm_deg(target.value)
            except PoseEntryError as exc:
                view.notify("Move there: refused", str(exc), error=True)
                return
            bMe = bMx if tool.value == "flange" else bMx @ inverse(app.scene.mount.eMv)
            send(view, f"Move the {tool.value} there", "move_to", "arrived", bMe=bMe.tolist())

        def on_present(_: Any) -> None:
            send(
                view,
                "Present part here",
                "present_part",
                "a new part is on the table",
                centre_mm=[part_x.value, part_y.value],
                turn_deg=part_turn.value,
            )

        def on_save(_: Any) -> None:
            def saved(reply: Any) -> None:
                view.report("Save job", f"job {name.value!r} saved")(reply)
                if reply.ok:
                    app.forget_job(reply.result)
                    app.refresh_lists()

            send(view, "Save job", "save_job", done=saved, name=name.value.strip(), description=description.value)

        begin.on_click(on_begin)
        go_view.on_click(go_to("desired view", lambda d: d["taught_bMe"]))
        go_place.on_click(go_to("place pose", lambda d: d["bMe_place"]))
        go_pocket.on_click(
            lambda _: send(
                view,
                "Go above the pocket",
                "move_to",
                "arrived",
                bMe=above_pocket(teach_pose(app.session.state, "pocket_bMe")).tolist(),
            )
        )
        go_desired.on_click(
            lambda _: send(
                view, "Go to the desired view", "move_to", "arrived", bMe=teach_pose(app.session.state, "view_bMe").tolist()
            )
        )
        go_over.on_click(
            lambda _: send(
                view,
                "Go over the placed part",
                "move_to",
                "arrived",
                bMe=view_over_part(teach_pose(app.session.state, "place_bMo"), app.scene.mount.eMc).tolist(),
            )
        )
        go_check.on_click(go_to("check view", lambda d: (d.get("check") or {}).get("check_bMe")))
        go_start.on_click(go_to("start pose", lambda d: d["start_bMe"]))
        move.on_click(on_jog)
        turn.on_click(on_jog)
        for name_, handle in holds.items():
            handle.on_hold(on_hold(name_), callback_hz=HOLD_HZ)
        move_there.on_click(on_move_there)
        if present is not None:
            present.on_click(on_present)
        gizmo.on_update(lambda _: self._show_gizmo(view, gizmo.value))
        capture.on_click(lambda _: send(view, "Capture desired image", "capture_desired", "desired image captured"))
        suction_on.on_click(lambda _: send(view, "Suction on", "suction", on=True))
        suction_off.on_click(lambda _: send(view, "Suction off", "suction", on=False))
        test_pick.on_click(lambda _: send(view, "Test pick", "test_pick"))
        start.on_click(lambda _: send(view, "Set start pose", "set_start_pose", "start pose set"))
        pick.on_click(lambda _: send(view, "Set pick pose", "set_pick_pose", "pick pose set"))
        place.on_click(lambda _: send(view, "Set place pose", "set_place_pose", "place pose set"))
        check.on_click(lambda _: send(view, "Capture check view", "capture_check_view", "check view captured"))
        apply.on_click(
            lambda _: send(
                view,
                "Apply settings",
                "set_settings",
                "settings applied",
                threshold_px=threshold.value,
                gain=gain.value,
                approach_m=approach.value / 1000.0,
                placement_tolerance_mm=tolerance.value,
            )
        )
        save.on_click(on_save)
        cancel.on_click(lambda _: send(view, "Cancel teaching", "cancel_teach", "teaching cancelled"))
        template.on_update(lambda _: self._enable(view.client_id))

        with self._lock:
            self._live[view.client_id] = (view, live)
            self._next[view.client_id] = {handle.label: handle for handle, _ in live}

        def on_role(is_operator: bool) -> None:
            if not is_operator:  # a monitor has no gizmo
                gizmo.value = False
                self._show_gizmo(view, False)
            self._enable(view.client_id)

        view.on_role(on_role)
        self._enable(view.client_id)

    def remove_client(self, client_id: int) -> None:
        with self._lock:
            self._gizmos.pop(client_id, None)
            self._live.pop(client_id, None)
            self._next.pop(client_id, None)

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
        allows it; the next step's button in orange."""
        state = self.app.session.state
        with self._lock:
            view, live = self._live.get(client_id, (None, []))
            buttons = self._next.get(client_id, {})
        if view is None:
            return
        upcoming = next_button(state)
        for handle, when in live:
            try:
                disabled = not (view.is_operator and when(state))
                if handle.disabled != disabled:
                    handle.disabled = disabled
                color = NEXT_COLOR if handle is buttons.get(upcoming) else ("green" if handle.label == "Save job" else None)
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
        bMe = np.asarray(self.app.session.state["bMe"], float)
        handle = view.client.scene.add_transform_controls(
            "/teach/flange_gizmo", scale=0.12, depth_test=False, wxyz=vtf.SO3.from_matrix(bMe[:3, :3]).wxyz, position=bMe[:3, 3]
        )
        entry = {"handle": handle, "dragging": False}

        def on_update(event: Any) -> None:
            entry["dragging"] = event.phase != "end"
            if event.phase == "end":
                self.app.send(
                    view, "Move to the gizmo", "move_to", bMe=gizmo_pose(event.target.position, event.target.wxyz).tolist()
                )

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
