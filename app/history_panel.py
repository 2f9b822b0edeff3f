"""History tab: past runs, one run's stage timeline, and the replay of its recording.

Shared: the table of the latest runs (outcome, duration, final feature error, placement
error). Per browser, for anyone (it changes nothing on the cell): choose a run, read its
stage timeline, and replay its recording (frames and features as they were recorded)
with the live image's overlays, in this browser only, at the recorded pace.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import viser

from vservo.app import live_image
from vservo.app.client_view import ClientView
from vservo.app.context import AppContext
from vservo.app.session import SessionView
from vservo.app.status import run_label, runs_table, stage_timeline
from vservo.core.perception.recording import Recording, RecordingError

REPLAY_MAX_PERIOD_S = 0.2  # a slow recorded cycle is shown for at most this long
NO_RUN = "(no runs yet)"


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
        if cycle.get(("frame")) is None:
            continue
        shown.append((cycle, live_image.Overlay(corners, live_image.pixel_array(cycle.get("laser_spot_px"), (2,)),
                                                desired_corners, desired_spot, np.array(trail) if trail else None)))
    return shown


class HistoryPanel:
    def __init__(self, app: AppContext, tab: viser.GuiTabHandle) -> None:
        self.app, self.tab = app, tab
        with tab:
            self.table = app.server.gui.add_markdown("No runs yet.", order=1)
        self._replays: dict[int, threading.Event] = {}  # client id -> stop of its replay
        self._lock = threading.Lock()

    def add_client(self, view: ClientView) -> None:
        gui = view.client.gui
        with self.tab:
            with gui.add_folder("One run", order=2):
                choice = gui.add_dropdown("Run", self._labels() or [NO_RUN])
                timeline = gui.add_markdown("")
                replay = gui.add_button("Replay its recording", icon=viser.Icon.PLAYER_PLAY)
                status = gui.add_markdown("")
                image = gui.add_image(np.zeros((480, 640, 3), np.uint8), label="replay", format="jpeg", visible=False)
        view.handles.update(history_run=choice, history_timeline=timeline)
        choice.on_update(lambda _: self._show_timeline(view))
        replay.on_click(lambda _: self._start_replay(view, status, image))
        self._show_timeline(view)

    def remove_client(self, client_id: int) -> None:
        with self._lock:
            stop = self._replays.pop(client_id, None)
        if stop is not None:
            stop.set()

    def _labels(self) -> list[str]:
        return [run_label(run) for run in self.app.runs if run.get("outcome")]

    def _selected(self, view: ClientView) -> dict | None:
        label = view.handles["history_run"].value
        return next((run for run in self.app.runs if run_label(run) == label), None)

    def _show_timeline(self, view: ClientView) -> None:
        run = self._selected(view)
        view.handles["history_timeline"].content = stage_timeline(run) if run else ""

    def lists_changed(self, views: list[ClientView]) -> None:
        self.table.content = runs_table(self.app.runs)
        labels = self._labels() or [NO_RUN]
        for view in views:
            if view.set_options("history_run", labels):
                self._show_timeline(view)

    def refresh(self, view: SessionView) -> None:
        pass  # the table changes when a run ends (lists_changed)

    def _start_replay(self, view: ClientView, status: Any, image: Any) -> None:
        run = self._selected(view)
        if run is None or not run.get("recording"):
            view.notify("Replay", "this run has no recording", error=True)
            return
        stop = threading.Event()
        with self._lock:
            previous = self._replays.get(view.client_id)
            self._replays[view.client_id] = stop
        if previous is not None:
            previous.set()
        threading.Thread(target=self._replay, args=(run, stop, status, image, view), name="app-replay",
                         daemon=True).start()

    def _replay(self, run: dict, stop: threading.Event, status: Any, image: Any, view: ClientView) -> None:
        try:
            recording = Recording.open(run["recording"])
            shown = replay_overlays(recording)
        except RecordingError as exc:
            view.notify("Replay", str(exc), error=True)
            return
        try:
            self._play(run, recording, shown, stop, status, image)
        except RecordingError as exc:  # a frame damaged on disk
            view.notify("Replay", str(exc), error=True)
        except RuntimeError:  # viser removed the elements: the browser left during the replay
            return

    @staticmethod
    def _play(run: dict, recording: Recording, shown: list, stop: threading.Event, status: Any, image: Any) -> None:
        image.visible = True
        previous_time = None
        for number, (cycle, overlay) in enumerate(shown, start=1):
            if stop.is_set():
                return
            frame = recording.frame_of(cycle)
            live_image.show_jpeg(image, live_image.encode_jpeg(live_image.draw(frame.image, overlay)))
            status.content = (f"run {run['id']}: cycle {cycle.get('iteration')} of {len(recording.cycles)}, stage "
                              f"{cycle.get('stage')}, error {cycle.get('error_px') or 0:.1f} px ({number}/{len(shown)})")
            now = float(cycle.get("time_s") or 0.0)
            pause = 0.05 if previous_time is None else float(np.clip(now - previous_time, 0.02, REPLAY_MAX_PERIOD_S))
            previous_time = now
            stop.wait(pause)
        status.content += "  \nreplay finished"
