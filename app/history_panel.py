"""History tab: past runs, one run's stage timeline, and the replay of its recording.

Shared: the table of the latest runs, newest first (outcome, duration, final feature
error, placement error). Per browser, for anyone (it changes nothing on the cell): choose
a run (the newest when one ends), see its stage timeline as a chart (app/stage_chart.py),
and replay its recording in this browser only: the frames with the live image's overlays,
the feature error chart and the flange's path in 3D up to the frame shown, in real time
(app/replay.py) with play, pause, seek and speed.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from vservo.app import live_image
from vservo.app.banner import Button, stage_words
from vservo.app.client_view import ClientView
from vservo.app.context import AppContext
from vservo.app.replay import SPEEDS, ReplayClock, ReplayTimeline
from vservo.app.session import SessionView
from vservo.app.stage_chart import stage_chart
from vservo.app.status import run_heading, run_label, runs_table
from vservo.core.perception.recording import Recording, RecordingError
from vservo.core.production.protocol import RunEntry

log = logging.getLogger("vservo.app")

NO_RUN = "(no runs yet)"
CHART_PERIOD_S = 0.25  # the replay's chart and 3D path follow at most this often
PATH_RGB = (120, 60, 200)


def replay_overlays(recording: Recording) -> list[tuple[dict, live_image.Overlay]]:
    """(cycle, overlay) for every recorded cycle with a frame: its corners and spot, the job's
    desired features and the corner trajectories up to that cycle."""
    desired = recording.description.get("desired") or {}
    desired_corners = live_image.pixel_array(desired.get("corners_px"), (4, 2))
    desired_spot = live_image.pixel_array(desired.get("laser_spot_px"), (2,))
    shown, trail = [], []
    for cycle in recording.cycles:
        corners = live_image.pixel_array(cycle.get("corners_px"), (4, 2))
        if corners is not None:
            trail.append(corners)
        if cycle.get("frame") is None:
            continue
        shown.append(
            (
                cycle,
                live_image.Overlay(
                    corners,
                    live_image.pixel_array(cycle.get("laser_spot_px"), (2,)),
                    desired_corners,
                    desired_spot,
                    np.array(trail) if trail else None,
                ),
            )
        )
    return shown


@dataclass
class _Replay:
    """One browser's replay: its recording, the frames shown with their overlays, and its clock."""

    run: RunEntry
    recording: Recording
    shown: list[tuple[dict, live_image.Overlay]]
    clock: ReplayClock
    stop: threading.Event = field(default_factory=threading.Event)
    index: int = -1  # the frame on screen


class HistoryPanel:
    def __init__(self, app: AppContext, tab: viser.GuiTabHandle) -> None:
        self.app, self.tab = app, tab
        with tab:
            self.table = app.server.gui.add_markdown("No runs yet.", order=1)
        self._replays: dict[int, _Replay] = {}  # client id -> its replay
        self._newest: int | None = None  # the newest run's id the dropdowns were set to
        self._lock = threading.Lock()

    def add_client(self, view: ClientView) -> None:
        gui = view.client.gui
        with self.tab:
            with gui.add_folder("One run", order=2):
                choice = gui.add_dropdown("Run", self._labels() or [NO_RUN])
                timeline = gui.add_markdown("")
                chart = gui.add_image(stage_chart(None), label="stage timeline", format="png")
                replay = view.button(
                    Button.REPLAY,
                    gui.add_button("Replay its recording", icon=viser.Icon.PLAYER_PLAY, disabled=True),
                    operator_only=False,
                )
                play = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY, disabled=True)
                pause = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE, disabled=True)
                seek = gui.add_slider("Replay frame", min=0, max=1, step=1, initial_value=0, disabled=True)
                speed = gui.add_dropdown("Replay speed", tuple(SPEEDS), initial_value="1x")
                status = gui.add_markdown("")
                image = gui.add_image(np.zeros((480, 640, 3), np.uint8), label="replay", format="jpeg", visible=False)
                errors = gui.add_uplot(
                    (np.array([0.0, 1.0]), np.full(2, np.nan)),
                    ({"label": "s"}, {"label": "off the taught view, px", "stroke": "#d62728", "width": 2}),
                    title="replay: how far the part is from the taught view (px)",
                    aspect=2.2,
                    scales={"x": {"time": False}, "y": {"distr": 3}},
                    visible=False,
                )
        view.handles.update(
            history_run=choice,
            history_timeline=timeline,
            history_chart=chart,
            replay_play=play,
            replay_pause=pause,
            replay_seek=seek,
            replay_status=status,
            replay_image=image,
            replay_errors=errors,
        )
        choice.on_update(lambda _: self._show_timeline(view))
        replay.on_click(lambda _: self._start_replay(view, SPEEDS[speed.value]))
        play.on_click(lambda _: self._steer(view, lambda clock: clock.play()))
        pause.on_click(lambda _: self._steer(view, lambda clock: clock.pause()))
        speed.on_update(lambda _: self._steer(view, lambda clock: clock.set_speed(SPEEDS[speed.value])))
        seek.on_update(lambda _: self._seek(view, int(seek.value)))
        self._show_timeline(view)

    def remove_client(self, client_id: int) -> None:
        with self._lock:
            replay = self._replays.pop(client_id, None)
        if replay is not None:
            replay.stop.set()

    def _labels(self) -> list[str]:
        return [run_label(run) for run in self.app.runs if run.outcome]

    def _selected(self, view: ClientView) -> RunEntry | None:
        label = view.handles["history_run"].value
        return next((run for run in self.app.runs if run_label(run) == label), None)

    def _show_timeline(self, view: ClientView) -> None:
        run = self._selected(view)
        view.handles["history_timeline"].content = run_heading(run) if run else ""
        view.handles["history_chart"].image = stage_chart(run)

    def lists_changed(self, views: list[ClientView]) -> None:
        self.table.content = runs_table(self.app.runs)
        labels = self._labels() or [NO_RUN]
        finished = [run for run in self.app.runs if run.outcome]
        newest = finished[0].id if finished else None  # the controller lists runs newest first
        with self._lock:
            new_run, self._newest = newest != self._newest, newest
        for view in views:
            try:
                changed = view.set_options("history_run", labels)
                if new_run and view.handles["history_run"].value != labels[0]:
                    view.handles["history_run"].value = labels[0]  # a run ended: show it
                    changed = True
                if changed:
                    self._show_timeline(view)
            except RuntimeError:  # viser: its elements were removed as it left, before we heard of it
                log.info("browser %d left while the runs changed", view.client_id)

    def refresh(self, view: SessionView) -> None:
        pass  # the table changes when a run ends (lists_changed)

    # -- the replay ----------------------------------------------------------------------

    def _start_replay(self, view: ClientView, speed: float) -> None:
        run = self._selected(view)
        if run is None or not run.recording:
            view.notify("Replay", "this run has no recording", error=True)
            return
        try:
            recording = Recording.open(run.recording)
            shown = replay_overlays(recording)
        except RecordingError as exc:
            view.notify("Replay", str(exc), error=True)
            return
        if not shown:
            view.notify("Replay", f"run {run.id} recorded no frames", error=True)
            return
        replay = _Replay(
            run, recording, shown, ReplayClock(ReplayTimeline.from_cycles([cycle for cycle, _ in shown], run.duration_s))
        )
        with self._lock:
            previous = self._replays.get(view.client_id)
            self._replays[view.client_id] = replay
        if previous is not None:
            previous.stop.set()
        seek = view.handles["replay_seek"]
        seek.max, seek.disabled = len(shown) - 1, False
        replay.clock.set_speed(speed)
        replay.clock.play()
        threading.Thread(target=self._replay, args=(replay, view), name="app-replay", daemon=True).start()

    def _current(self, view: ClientView) -> _Replay | None:
        with self._lock:
            return self._replays.get(view.client_id)

    def _steer(self, view: ClientView, action: Any) -> None:
        replay = self._current(view)
        if replay is not None:
            action(replay.clock)

    def _seek(self, view: ClientView, index: int) -> None:
        replay = self._current(view)
        if replay is not None and index != replay.index:  # not the slider following the replay
            replay.clock.seek(index)

    def _replay(self, replay: _Replay, view: ClientView) -> None:
        try:
            self._play(replay, view)
        except RecordingError as exc:  # a frame damaged on disk
            view.notify("Replay", str(exc), error=True)
        except RuntimeError:  # viser removed the elements: the browser left during the replay
            return

    def _play(self, replay: _Replay, view: ClientView) -> None:
        """Show the frame the clock says, whenever it changes, until the browser leaves or
        another replay replaces this one; pausing and seeking wake it at once."""
        handles, clock, timeline = view.handles, replay.clock, replay.clock.timeline
        handles["replay_image"].visible = handles["replay_errors"].visible = True
        charted_at = -np.inf
        playing = None
        while not replay.stop.is_set():
            index = clock.index()
            if index != replay.index:
                cycle, overlay = replay.shown[index]
                frame = replay.recording.frame_of(cycle)
                if frame is not None:  # every cycle shown recorded one (replay_overlays)
                    image = live_image.draw(frame.image, overlay)
                    live_image.show_jpeg(handles["replay_image"], live_image.encode_jpeg(image))
                replay.index = index
                handles["replay_seek"].value = index
                handles["replay_status"].content = (
                    f"run {replay.run.id}: {timeline.times_s[index]:.1f} s of {timeline.duration_s:.1f} s, "
                    f"frame {index + 1} of {len(replay.shown)}, {_stage_text(cycle)}"
                )
                if time.monotonic() - charted_at >= CHART_PERIOD_S or index == len(replay.shown) - 1:
                    charted_at = time.monotonic()
                    self._chart(view, timeline, index)
            if clock.playing != playing:
                playing = clock.playing
                handles["replay_play"].disabled, handles["replay_pause"].disabled = playing, not playing
            clock.changed.clear()
            wait = clock.until_next_s()
            clock.changed.wait(CHART_PERIOD_S if wait is None else min(max(wait, 0.0), CHART_PERIOD_S))

    @staticmethod
    def _chart(view: ClientView, timeline: ReplayTimeline, index: int) -> None:
        """The feature error up to the frame shown, and the flange's path to there in this browser's 3D view."""
        upto = slice(0, index + 1)
        x, errors = timeline.times_s[upto], timeline.errors_px[upto]
        if len(x) < 2:  # uPlot needs two points for its x range
            x, errors = np.array([0.0, 1.0]), np.full(2, np.nan)
        view.handles["replay_errors"].data = (x, np.where(errors > 0, errors, np.nan))
        path = timeline.path_m[upto]
        path = path[np.all(np.isfinite(path), axis=1)]
        if len(path) > 1:
            view.client.scene.add_line_segments(
                "/replay/path", np.stack([path[:-1], path[1:]], axis=1), PATH_RGB, thickness=0.003
            )


def _stage_text(cycle: dict) -> str:
    error = cycle.get("error_px")
    return (
        f"{stage_words(cycle.get('stage') or '')}, {error:.1f} px from the taught view"
        if error is not None
        else stage_words(cycle.get("stage") or "")
    )
