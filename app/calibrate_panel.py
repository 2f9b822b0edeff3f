"""Calibrate tab: commissioning the connected cell, then the NN calibration study.

Commission this cell (first): per browser (operator only) the steps to run, Start and
Apply; shared by every browser, the progress of each part of the procedure, then each
step's verdict and the acceptance check in plain words, its residuals and the measured
values in the folded Engineering panel (app/commission_text.py). The controller runs it (its ``commission`` and
``apply_commissioning`` commands): the robot moves, and Apply, after a confirmation,
writes the commissioned cell file and reloads the controller's model from it.

The NN hand-eye calibration study (chapters 2-3) on the simulated cell: per browser the
preset, Run and Stop; shared, the step under way with a progress bar, then how far off
each method is in plain words, its per-method table in the Engineering panel. It runs in
background processes (app/calibration_run.py) and does not move the cell's robot.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import viser

from vservo.app import commission_text
from vservo.app.banner import Button
from vservo.app.calibration_run import (
    PRESETS,
    QUICK,
    CalibrationProgress,
    CalibrationRun,
    results_markdown,
    summary_markdown,
)
from vservo.app.client_view import ClientView
from vservo.app.context import AppContext
from vservo.app.session import SessionView
from vservo.core.production.protocol import ApplyCommissioning, Commission, Reply
from vservo.core.production.protocol.catalogue import Refusal


class CalibratePanel:
    def __init__(self, app: AppContext, tab: viser.GuiTabHandle) -> None:
        self.app, self.tab = app, tab
        gui = app.server.gui
        with tab:
            gui.add_markdown(
                "### Commission this cell\nThe robot shows the camera the calibration board; each step "
                "measures part of the cell's model (docs/commissioning.md).",
                order=1,
            )
            self.commission_progress = gui.add_markdown("", order=7)
            self.commission_results = gui.add_markdown("", order=8)
            gui.add_markdown("### Calibration study (simulated cell)", order=20)
            self.status = gui.add_markdown(
                "The study shows the camera the checkerboard on the simulated cell, "
                "trains the network and the classical calibrations, and measures how far "
                "off each one is on views it was not shown and when the arm follows "
                "points with it.",
                order=30,
            )
            self.bar = gui.add_progress_bar(0.0, order=31)
            self.summary = gui.add_markdown("", order=32)
            # Plain words first: residuals, codes and equations only for who unfolds them.
            with gui.add_folder("Engineering (calibration)", expand_by_default=False, order=40):
                self.commission_engineering = gui.add_markdown("")
                self.results = gui.add_markdown("")
        self._run: CalibrationRun | None = None
        self._lock = threading.Lock()

    def add_client(self, view: ClientView) -> None:
        gui = view.client.gui
        with self.tab:
            steps = {
                step: view.control(gui.add_checkbox(f"Step {step}", True, order=2 + k))
                for k, step in enumerate(commission_text.STEP_WORDS)
            }
            start = view.button(
                Button.START_COMMISSIONING,
                gui.add_button(
                    "Start commissioning",
                    icon=viser.Icon.PLAYER_PLAY,
                    order=6,
                    disabled=True,
                    hint="The robot moves: it shows the camera the board",
                ),
            )
            apply = view.button(
                Button.APPLY_COMMISSIONING,
                gui.add_button(
                    "Apply",
                    icon=viser.Icon.DEVICE_FLOPPY,
                    order=9,
                    disabled=True,
                    hint="Write the commissioned cell file and run on it",
                ),
            )
            preset = view.control(gui.add_dropdown("Preset", tuple(PRESETS), initial_value=QUICK, order=21))
            run = view.button(
                Button.RUN_CALIBRATION, gui.add_button("Run calibration", icon=viser.Icon.PLAYER_PLAY, order=22, disabled=True)
            )
            stop = view.button(
                Button.STOP_CALIBRATION, gui.add_button("Stop calibration", icon=viser.Icon.PLAYER_STOP, order=23, disabled=True)
            )
        start.on_click(
            lambda _: self.app.send(
                view,
                "Start commissioning",
                lambda: Commission(steps=tuple(step for step, box in steps.items() if box.value)),
                "commissioning started",
            )
        )
        apply.on_click(lambda _: self._confirm_apply(view))
        run.on_click(lambda _: self._start(view, preset.value))
        stop.on_click(lambda _: self._stop(view))

    def remove_client(self, client_id: int) -> None:
        pass  # a browser's elements go with its connection

    def lists_changed(self, views: list[ClientView]) -> None:
        pass

    def refresh(self, view: SessionView) -> None:
        """The commissioning's progress and results (the study reports its own progress, _on_change)."""
        state = view.state
        record = state.commissioning
        _set(self.commission_progress, commission_text.progress_markdown(record, state.cell_file))
        _set(self.commission_results, commission_text.results_markdown(record))
        _set(self.commission_engineering, commission_text.engineering_markdown(record))

    @property
    def calibrating(self) -> bool:
        """Whether the calibration study runs (its Stop is live, its Run is not)."""
        with self._lock:
            return self._run is not None and not self._run.progress.finished

    def _confirm_apply(self, view: ClientView) -> None:
        """Apply asks first: the modal names the file it writes."""
        if not view.allowed("Apply", self.app.roles):
            return
        record = self.app.session.state.commissioning
        if record is None:
            nothing = Reply(False, kind=Refusal.NOT_COMMISSIONED)
            view.say_refused("Apply", nothing.operator_words(), "nothing was commissioned")
            return
        with view.client.gui.add_modal("Apply the commissioning") as modal:
            view.client.gui.add_markdown(commission_text.apply_question(record))
            write = view.client.gui.add_button("Write and reload", icon=viser.Icon.DEVICE_FLOPPY, color="green")
            cancel = view.client.gui.add_button("Cancel")

        def applied(reply: Reply) -> None:
            if reply.ok:
                view.notify("Apply", f"the controller runs on {reply.result}")
            else:
                view.report("Apply")(reply)

        def on_write(_: object) -> None:
            modal.close()
            self.app.send(view, "Apply", ApplyCommissioning(), done=applied)

        write.on_click(on_write)
        cancel.on_click(lambda _: modal.close())

    def _start(self, view: ClientView, preset: str) -> None:
        if not view.allowed("Run calibration", self.app.roles):
            return
        with self._lock:
            if self._run is not None and self._run.running:
                view.notify("Run calibration", "a calibration is already running", error=True)
                return
            folder = self.app.options.data / "calibration" / time.strftime("%Y%m%d-%H%M%S")
            self._run = CalibrationRun(folder, preset, self.app.options.cell, self._on_change)
        self._run.start()
        self.results.content = self.summary.content = ""

    def _stop(self, view: ClientView) -> None:
        if not view.allowed("Stop calibration", self.app.roles):
            return
        with self._lock:
            run = self._run
        if run is not None:
            run.cancel()

    def _on_change(self, progress: CalibrationProgress) -> None:
        elapsed = time.monotonic() - progress.started_s
        self.bar.value = 100.0 * progress.fraction  # type: ignore[misc]  # viser's props: read-only
        if progress.error:
            self.bar.color = "red"
            self.status.content = f"**Calibration stopped** after {elapsed:.0f} s: {progress.error}"
        elif progress.finished:
            self.bar.color = "green"
            self.status.content = f"**Calibration finished** in {elapsed:.0f} s (files in `{self._folder()}`)."
        else:
            self.bar.color = None
            self.status.content = f"**{progress.step}** ({elapsed:.0f} s): `{progress.line}`"
        self.summary.content = summary_markdown(progress.results)
        self.results.content = results_markdown(progress.results)
        self.app.refresh_buttons()  # Run and Stop swap as the study starts and ends

    def _folder(self) -> Any:
        with self._lock:
            return self._run.folder if self._run else ""

    def close(self) -> None:
        with self._lock:
            run = self._run
        if run is not None:
            run.cancel()
            run.wait(10.0)


def _set(markdown: viser.GuiMarkdownHandle, content: str) -> None:
    """Send a shared text only when it changed (refresh runs on every state the controller sends)."""
    if markdown.content != content:
        markdown.content = content
