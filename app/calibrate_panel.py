"""Calibrate tab: the NN hand-eye calibration workflow (chapters 2-3) on the simulated cell.

Per browser (operator only): the preset, Run and Stop. Shared: the step under way with a
progress bar, then the per-method result table. The work runs in background processes
(app/calibration_run.py); it does not move the cell's robot.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import viser

from vservo.app.calibration_run import PRESETS, QUICK, CalibrationProgress, CalibrationRun, results_markdown
from vservo.app.client_view import ClientView
from vservo.app.context import AppContext
from vservo.app.session import SessionView


class CalibratePanel:
    def __init__(self, app: AppContext, tab: viser.GuiTabHandle) -> None:
        self.app, self.tab = app, tab
        gui = app.server.gui
        with tab:
            self.status = gui.add_markdown("The workflow collects checkerboard views on the simulated cell, trains "
                                           "the network and the classical calibrations, evaluates them on held-out "
                                           "views and tracks points with each (PBVS, eq. 2-47).", order=10)
            self.bar = gui.add_progress_bar(0.0, order=11)
            self.results = gui.add_markdown("", order=12)
        self._run: CalibrationRun | None = None
        self._lock = threading.Lock()

    def add_client(self, view: ClientView) -> None:
        gui = view.client.gui
        with self.tab:
            preset = view.control(gui.add_dropdown("Preset", tuple(PRESETS), initial_value=QUICK, order=1))
            run = view.control(gui.add_button("Run calibration", icon=viser.Icon.PLAYER_PLAY, order=2))
            stop = view.control(gui.add_button("Stop calibration", icon=viser.Icon.PLAYER_STOP, order=3))
        run.on_click(lambda _: self._start(view, preset.value))
        stop.on_click(lambda _: self._stop(view))

    def remove_client(self, client_id: int) -> None:
        pass

    def lists_changed(self, views: list[ClientView]) -> None:
        pass

    def refresh(self, view: SessionView) -> None:
        pass  # the workflow reports its own progress (_on_change)

    def _start(self, view: ClientView, preset: str) -> None:
        if not view.allowed("Run calibration", self.app.roles):
            return
        with self._lock:
            if self._run is not None and self._run.running:
                view.notify("Run calibration", "a calibration is already running", error=True)
                return
            folder = self.app.options.data / "calibration" / time.strftime("%Y%m%d-%H%M%S")
            self._run = CalibrationRun(folder, preset, self.app.options.cell, self._on_change).start()
        self.results.content = ""

    def _stop(self, view: ClientView) -> None:
        if not view.allowed("Stop calibration", self.app.roles):
            return
        with self._lock:
            run = self._run
        if run is not None:
            run.cancel()

    def _on_change(self, progress: CalibrationProgress) -> None:
        elapsed = time.monotonic() - progress.started_s
        self.bar.value = 100.0 * progress.fraction
        if progress.error:
            self.bar.color = "red"
            self.status.content = f"**Calibration stopped** after {elapsed:.0f} s: {progress.error}"
        elif progress.finished:
            self.bar.color = "green"
            self.status.content = f"**Calibration finished** in {elapsed:.0f} s (files in `{self._folder()}`)."
        else:
            self.bar.color = None
            self.status.content = f"**{progress.step}** ({elapsed:.0f} s): `{progress.line}`"
        self.results.content = results_markdown(progress.results)

    def _folder(self) -> Any:
        with self._lock:
            return self._run.folder if self._run else ""

    def close(self) -> None:
        with self._lock:
            run = self._run
        if run is not None:
            run.cancel()
            run.wait(10.0)
