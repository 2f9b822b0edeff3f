"""Teach tab (Fig. C-2): jog the arm, capture the desired image, set the poses, save the job.

Per browser (operator only): begin teaching from scratch or from a stored job (its poses
and settings are kept until taught again); go to the template's taught view or start
pose; jog in Cartesian steps of a chosen size, in the base or the tool frame, or drag a
3D gizmo on the flange (the arm moves when the gizmo is let go); capture the desired
image; set the start, pick and place poses where the arm is; capture the check view (the
placed part seen from over the metal part; optional); threshold, gain, approach height and
placement tolerance; name and save. Shared: what is still missing before the job can be saved.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import viser
import viser.transforms as vtf

from vservo.app.client_view import ClientView
from vservo.app.context import AppContext
from vservo.app.session import SessionView
from vservo.app.status import teach_markdown
from vservo.core.geometry.spatial import Matrix, pose_error, transform

NEW_JOB = "(new job)"
# Jog step: translation (m) and rotation (deg) per press.
STEPS = {"0.5 mm / 0.5 deg": (0.0005, 0.5), "1 mm / 1 deg": (0.001, 1.0), "5 mm / 2 deg": (0.005, 2.0),
         "10 mm / 5 deg": (0.010, 5.0), "20 mm / 10 deg": (0.020, 10.0)}
TRANSLATIONS = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
ROTATIONS = ("+Rx", "-Rx", "+Ry", "-Ry", "+Rz", "-Rz")
GIZMO_FOLLOW = 1e-4  # m and rad: the gizmo is moved to the flange only when they differ by more


def jog_step(button: str, step: str) -> tuple[list[float], list[float]]:
    """(translation m, rotation rad) of one press of a jog button at a step size."""
    metres, degrees = STEPS[step]
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


class TeachPanel:
    def __init__(self, app: AppContext, tab: viser.GuiTabHandle) -> None:
        self.app, self.tab = app, tab
        with tab:
            self.missing = app.server.gui.add_markdown("", order=100)
        self._gizmos: dict[int, dict] = {}  # client id -> {"handle", "dragging"}
        self._lock = threading.Lock()

    def add_client(self, view: ClientView) -> None:
        gui, app = view.client.gui, self.app
        c = view.control
        with self.tab:
            template = c(gui.add_dropdown("Template", [NEW_JOB, *app.job_names()], initial_value=NEW_JOB, order=1))
            begin = c(gui.add_button("Begin teaching", icon=viser.Icon.SCHOOL, order=2))
            go_to = c(gui.add_button_group("Go to the template's", ("desired view", "start pose"), order=3))
            with gui.add_folder("Jog", order=4):
                step = c(gui.add_dropdown("Step", tuple(STEPS), initial_value="1 mm / 1 deg"))
                frame = c(gui.add_dropdown("Frame", ("base", "tool"), initial_value="base"))
                move = c(gui.add_button_group("Move", TRANSLATIONS))
                turn = c(gui.add_button_group("Turn", ROTATIONS))
                gizmo = c(gui.add_checkbox("3D gizmo on the flange (moves on release)", False))
            with gui.add_folder("Teach here", order=5):
                capture = c(gui.add_button("Capture desired image", icon=viser.Icon.CAMERA))
                start = c(gui.add_button("Set start pose here"))
                pick = c(gui.add_button("Set pick pose here (cup on the part)"))
                place = c(gui.add_button("Set place pose here (part in the metal part)"))
                check = c(gui.add_button("Capture check view (part placed)", icon=viser.Icon.CAMERA))
                gui.add_markdown("Check view: the part in the metal part, the camera over it seeing its four corners; "
                                 "runs measure the placement from here (optional: without it, placement unknown).")
            with gui.add_folder("Settings", order=6):
                threshold = c(gui.add_number("Threshold (px)", 3.0, min=0.1, max=50.0, step=0.1))
                gain = c(gui.add_number("Gain", 1.0, min=0.05, max=5.0, step=0.05))
                approach = c(gui.add_number("Approach height (mm)", 40.0, min=5.0, max=200.0, step=1.0))
                tolerance = c(gui.add_number("Placement tolerance (mm)", 1.0, min=0.05, max=20.0, step=0.05))
                apply = c(gui.add_button("Apply settings"))
            with gui.add_folder("Save", order=7):
                name = c(gui.add_text("Job name", ""))
                description = c(gui.add_text("Description", ""))
                save = c(gui.add_button("Save job", icon=viser.Icon.DEVICE_FLOPPY, color="green"))
                cancel = c(gui.add_button("Cancel teaching"))
        view.handles["teach_template"] = template
        send = app.send

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

        def on_go_to(event: Any) -> None:
            where = event.target.value
            if template_name() is None:
                view.notify("Go to", "choose a template job first", error=True)
                return
            key = "taught_bMe" if where == "desired view" else "start_bMe"

            def fetch_and_move() -> None:
                detail = app.job_detail(template_name())
                if detail is None:
                    view.notify("Go to", f"job {template_name()!r} cannot be read", error=True)
                    return
                send(view, f"Go to the {where}", "move_to", bMe=detail[key])
            app.in_background(fetch_and_move)

        def on_jog(event: Any) -> None:
            translation, rotation = jog_step(event.target.value, step.value)
            send(view, f"Jog {event.target.value}", "jog", translation_m=translation, rotation_rad=rotation,
                 frame=frame.value)

        def on_save(_: Any) -> None:
            def saved(reply: Any) -> None:
                view.report("Save job", f"job {name.value!r} saved")(reply)
                if reply.ok:
                    app.forget_job(reply.result)
                    app.refresh_lists()
            send(view, "Save job", "save_job", done=saved, name=name.value.strip(), description=description.value)

        begin.on_click(on_begin)
        go_to.on_click(on_go_to)
        move.on_click(on_jog)
        turn.on_click(on_jog)
        gizmo.on_update(lambda _: self._show_gizmo(view, gizmo.value))
        capture.on_click(lambda _: send(view, "Capture desired image", "capture_desired", "desired image captured"))
        start.on_click(lambda _: send(view, "Set start pose", "set_start_pose", "start pose set"))
        pick.on_click(lambda _: send(view, "Set pick pose", "set_pick_pose", "pick pose set"))
        place.on_click(lambda _: send(view, "Set place pose", "set_place_pose", "place pose set"))
        check.on_click(lambda _: send(view, "Capture check view", "capture_check_view", "check view captured"))
        apply.on_click(lambda _: send(view, "Apply settings", "set_settings", "settings applied",
                                      threshold_px=threshold.value, gain=gain.value, approach_m=approach.value / 1000.0,
                                      placement_tolerance_mm=tolerance.value))
        save.on_click(on_save)
        cancel.on_click(lambda _: send(view, "Cancel teaching", "cancel_teach", "teaching cancelled"))

        def on_role(is_operator: bool) -> None:
            if not is_operator:  # a monitor has no gizmo
                gizmo.value = False
                self._show_gizmo(view, False)
        view.on_role(on_role)

    def remove_client(self, client_id: int) -> None:
        with self._lock:
            self._gizmos.pop(client_id, None)

    def lists_changed(self, views: list[ClientView]) -> None:
        names = [NEW_JOB, *self.app.job_names()]
        for view in views:
            view.set_options("teach_template", names)

    def refresh(self, view: SessionView) -> None:
        self.missing.content = teach_markdown(view.state)

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
        handle = view.client.scene.add_transform_controls("/teach/flange_gizmo", scale=0.12, depth_test=False,
                                                          wxyz=vtf.SO3.from_matrix(bMe[:3, :3]).wxyz,
                                                          position=bMe[:3, 3])
        entry = {"handle": handle, "dragging": False}

        def on_update(event: Any) -> None:
            entry["dragging"] = event.phase != "end"
            if event.phase == "end":
                self.app.send(view, "Move to the gizmo", "move_to",
                              bMe=gizmo_pose(event.target.position, event.target.wxyz).tolist())

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
