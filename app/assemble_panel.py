"""Assemble tab and the live camera panel: pick a job, one Start, watch it run.

Per browser (operator only): the job, Present part (simulated cell: a new part arrives
near where the job was taught), Start. Shared by every browser: the stage and a progress
bar, the last outcome; in the live panel the camera image with its overlays
(app/live_image.py) and uPlot charts of the feature error and the six camera twist
components of the run under way.
"""

from __future__ import annotations

import threading
from typing import Literal

import numpy as np
import viser
from viser import uplot

from vservo.app import live_image
from vservo.app.banner import Button, Kind, banner_for
from vservo.app.client_view import ClientView
from vservo.app.context import AppContext
from vservo.app.session import LiveFrame, RunTrace, SessionView
from vservo.app.status import engineering_markdown, outcome_markdown, run_progress
from vservo.core.production.protocol import ControllerState, Phase, PresentPart, Start
from vservo.core.production.protocol.state import MOVING

TWIST_NAMES = ("vx m/s", "vy m/s", "vz m/s", "wx rad/s", "wy rad/s", "wz rad/s")
TWIST_COLOURS = ("#d62728", "#2ca02c", "#1f77b4", "#ff7f0e", "#9467bd", "#8c564b")
BLANK = np.zeros((480, 640, 3), np.uint8)
PROGRESS_COLOURS: dict[Kind, Literal["green", "orange", "red"]] = {
    Kind.PLACED: "green",
    Kind.MISSED: "orange",
    Kind.FAULT: "red",
    Kind.ESTOPPED: "red",
}


def ran_job(state: ControllerState) -> str | None:
    """The job the cell runs, or last ran (None before the first run: teaching names its template)."""
    return state.job if state.run.run_id is not None and state.phase is not Phase.TEACHING else None


def plot_data(trace: RunTrace) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """The charts' columns: cycle, feature error (px, log scale: only positive values); cycle and
    the six twist components. At least two cycles, blank before the run has them: viser's uPlot
    keeps its x range relative to the data's, which an empty or single-point series spoils."""
    x = trace.iterations.astype(float)
    errors = np.where(np.isfinite(trace.errors_px) & (trace.errors_px > 0), trace.errors_px, np.nan)
    twists = trace.twists
    if len(x) < 2:
        x, errors, twists = np.array([0.0, 1.0]), np.full(2, np.nan), np.full((2, 6), np.nan)
    return (x, errors), (x, *(twists[:, k] for k in range(6)))


class AssemblePanel:
    def __init__(self, app: AppContext, tab: viser.GuiTabHandle, live: viser.PanelHandle) -> None:
        self.app, self.tab = app, tab
        gui = app.server.gui
        with tab:
            self.stage = gui.add_markdown("", order=20)
            self.progress = gui.add_progress_bar(0.0, order=21)
            self.outcome = gui.add_markdown("", order=22)
        with live.add_tab("Live camera", viser.Icon.CAMERA):
            self.image = gui.add_image(BLANK, label="camera (overlays: seen, desired, laser and its target)", format="jpeg")
            blank_error, blank_twist = plot_data(RunTrace())
            self.error_plot = gui.add_uplot(
                blank_error,
                ({"label": "cycle"}, {"label": "off the taught view, px", "stroke": "#d62728", "width": 2}),
                title="how far the part is from the taught view (px)",
                aspect=2.2,
                scales={"x": {"time": False}, "y": {"distr": 3}},
            )
            # What an engineer reads (the law's stage, its error norm, the commanded twist), folded away.
            with gui.add_folder("Engineering", expand_by_default=False):
                self.engineering = gui.add_markdown("")
                self.refusal = gui.add_markdown("")  # the last refusal as the controller wrote it
                self.twist_plot = gui.add_uplot(
                    blank_twist,
                    (
                        {"label": "cycle"},
                        *(uplot.Series(label=name, stroke=colour, width=1.5) for name, colour in zip(TWIST_NAMES, TWIST_COLOURS)),
                    ),
                    title="camera twist cVc",
                    aspect=2.2,
                    scales={"x": {"time": False}},
                )
        self._lock = threading.Lock()
        self._job_shown: str | None = None
        self._threshold_px = 3.0
        self._job_run: str | None = None  # the job the cell runs or last ran, which every Job selector shows
        self._selectors: dict[int, ClientView] = {}

    # -- per browser ---------------------------------------------------------------------

    def add_client(self, view: ClientView) -> None:
        gui = view.client.gui
        names = self.app.job_names() or ["demo"]
        ran = ran_job(self.app.session.state)
        initial = ran if ran in names else "demo" if "demo" in names else names[0]
        with self.tab:
            job = view.control(gui.add_dropdown("Job", names, initial_value=initial, order=11))
            if self.app.session.state.can_present_part:  # only where the cell has a part feeder
                present = view.button(
                    Button.PRESENT_PART,
                    gui.add_button(
                        "Present part",
                        icon=viser.Icon.BOX,
                        order=12,
                        disabled=True,
                        hint="A new part arrives near where the chosen job's part was taught",
                    ),
                )
                present.on_click(
                    lambda _: self.app.send(
                        view, "Present part", lambda: PresentPart(job=job.value), "a new part is on the table"
                    )
                )
            start = view.button(
                Button.START, gui.add_button("Start", icon=viser.Icon.PLAYER_PLAY, color="green", order=13, disabled=True)
            )
        start.on_click(lambda _: self.app.send(view, "Start", lambda: Start(job.value)))
        view.handles["assemble_job"] = job
        with self._lock:
            self._selectors[view.client_id] = view

    def remove_client(self, client_id: int) -> None:
        with self._lock:
            self._selectors.pop(client_id, None)

    def show_refusal(self, what: str, detail: str) -> None:
        """A refusal's engineering line (the notice said it in the catalogue's words)."""
        self.refusal.content = f"Last refusal ({what}): {detail}"

    def _follow_run(self, state: ControllerState) -> None:
        """Every Job selector shows the job the cell runs or last ran, once it starts."""
        ran = ran_job(state)
        with self._lock:
            if ran is None or ran == self._job_run:
                return
            self._job_run = ran
            views = list(self._selectors.values())
        for view in views:
            selector = view.handles.get("assemble_job")
            if selector is not None and ran in selector.options and selector.value != ran:
                selector.value = ran

    def lists_changed(self, views: list[ClientView]) -> None:
        names = self.app.job_names() or ["demo"]
        for view in views:
            view.set_options("assemble_job", names)

    # -- shared displays -------------------------------------------------------------------

    def show_frame(self, frame: LiveFrame) -> None:
        """The newest camera frame with its overlays, encoded once for every browser."""
        live_image.show_jpeg(self.image, live_image.render(frame.jpeg, frame.meta))

    def refresh(self, view: SessionView) -> None:
        state = view.state
        self._follow_job(state.job or "demo")
        self._follow_run(state)
        banner = banner_for(state)
        self.stage.content = f"**{banner.title}** · {banner.detail}"
        self.engineering.content = engineering_markdown(state)
        self.progress.value = run_progress(state, view.trace, self._threshold_px)  # type: ignore[misc]  # viser's props: read-only
        # The bar takes the outcome's colour (placed green, missed amber, fault red), blue while running.
        self.progress.color = None if state.phase in MOVING else PROGRESS_COLOURS.get(banner.kind)
        self.outcome.content = outcome_markdown(state.last_outcome, state.run.run_id)

    def refresh_plots(self, view: SessionView) -> None:
        error, twist = plot_data(view.trace)
        self.error_plot.data, self.twist_plot.data = error, twist

    def _follow_job(self, name: str) -> None:
        """The 3D scene shows the metal part of the job last started or saved (fetched off this thread)."""
        with self._lock:
            if name == self._job_shown:
                return
            self._job_shown = name

        def fetch() -> None:
            detail = self.app.job_detail(name)
            if detail is not None:
                self._threshold_px = detail.threshold_px
            self.app.scene.show_job(detail)

        self.app.in_background(fetch)

    def forget_shown_job(self) -> None:
        """A job was saved under the shown name: fetch it again."""
        with self._lock:
            self._job_shown = None
