"""The app's picture of the cell, built from what the controller publishes over the channel.

The controller sends its state (a ControllerState, decoded by the channel's client) on
every change and every servo cycle, and camera frames (JPEG plus what the vision saw in
them, a FrameMeta). The session keeps
the newest of each, and for the run under way the history the screens plot: feature
error and camera twist per servo cycle, and the flange's path. Every browser is drawn
from the same session, so a monitor sees exactly what the operator sees.

Written by the channel's reader thread, read by the display thread: everything is
guarded by one lock, and readers take immutable snapshots. Viser-free.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from vservo.core.geometry.spatial import Matrix
from vservo.core.production.protocol import ControllerState, FrameMeta, Phase
from vservo.core.production.protocol.state import MOVING

TRACE_LENGTH = 5000  # servo cycles kept per run (a run takes a few hundred)
PATH_STEP_M = 0.0005  # a new path point once the flange moved this far


@dataclass(frozen=True)
class LiveFrame:
    """A camera frame as the controller sent it: what was seen (pixels) and the JPEG."""

    meta: FrameMeta
    jpeg: bytes
    number: int  # frames received by the session so far, this one included


@dataclass(frozen=True)
class RunTrace:
    """One run's servo history: per cycle the iteration, the controller's clock, the feature
    error (px, NaN when unknown) and the camera twist cVc (6); and the flange's path (m)."""

    run_id: int | None = None
    iterations: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    times_s: Matrix = field(default_factory=lambda: np.zeros(0))
    errors_px: Matrix = field(default_factory=lambda: np.zeros(0))
    twists: Matrix = field(default_factory=lambda: np.zeros((0, 6)))
    path_m: Matrix = field(default_factory=lambda: np.zeros((0, 3)))

    def cycle_rate_hz(self) -> float | None:
        """Servo cycles per second over the run so far (controller clock); None before two cycles."""
        if len(self.times_s) < 2 or self.times_s[-1] <= self.times_s[0]:
            return None
        return float((self.iterations[-1] - self.iterations[0]) / (self.times_s[-1] - self.times_s[0]))


@dataclass(frozen=True)
class SessionView:
    """An immutable snapshot for the display: newest state and frame, the run's trace, counters."""

    state: ControllerState
    frame: LiveFrame | None
    trace: RunTrace
    state_number: int  # states received so far
    runs_ended: int  # runs whose outcome was recorded since the app started (the history needs a refresh)
    controller_gone: str | None


class Session:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._state = ControllerState(time_s=float("-inf"))
        self._frame: LiveFrame | None = None
        self._frames = 0
        self._states = 0
        self._runs_ended = 0
        self._gone: str | None = None
        self._run_id: int | None = None
        self._ended_run: int | None = None
        self._rows: list[tuple[int, float, float, list[float]]] = []  # iteration, time, error, twist
        self._path: list[Matrix] = []

    # -- written by the channel's reader -----------------------------------------------

    def on_state(self, state: ControllerState) -> None:
        with self._changed:
            if state.time_s < self._state.time_s:
                return  # older than what is shown (the welcome's state arriving after a newer one)
            self._state = state
            self._states += 1
            phase, run_id = state.phase, state.run.run_id
            if phase in MOVING and run_id is not None and run_id != self._run_id:
                self._run_id, self._rows, self._path = run_id, [], []
            elif phase == Phase.TEACHING and self._run_id is not None:
                self._run_id, self._rows, self._path = None, [], []  # a new job: the last run's charts go
            if run_id == self._run_id and phase in MOVING:
                self._add_cycle(state)
                self._add_path_point(state)
            if state.last_outcome is not None and run_id != self._ended_run:
                # The run's outcome is on record now (the phase may have changed before: an e-stop).
                self._ended_run = run_id
                self._runs_ended += 1
            self._changed.notify_all()

    def _add_cycle(self, state: ControllerState) -> None:
        iteration = state.run.iteration
        if iteration <= 0 or (self._rows and iteration <= self._rows[-1][0]):
            return  # a phase change, not a new servo cycle
        error = np.nan if state.run.error_px is None else state.run.error_px
        self._rows = (self._rows + [(iteration, state.time_s, error, list(state.run.cVc))])[-TRACE_LENGTH:]

    def _add_path_point(self, state: ControllerState) -> None:
        point = state.bMe[:3, 3]
        if not self._path or np.linalg.norm(point - self._path[-1]) >= PATH_STEP_M:
            self._path = (self._path + [point])[-TRACE_LENGTH:]

    def on_frame(self, meta: FrameMeta, jpeg: bytes) -> None:
        with self._changed:
            self._frames += 1
            self._frame = LiveFrame(meta, jpeg, self._frames)
            self._changed.notify_all()

    def on_controller_gone(self, why: str) -> None:
        """The controller process stopped: ``why``."""
        with self._changed:
            self._gone = why
            self._states += 1  # the pages redraw the banner and the status
            self._changed.notify_all()

    def on_controller_back(self, welcome: ControllerState) -> None:
        """A new controller is connected: its welcome's state stands, whatever its clock said before."""
        with self._changed:
            self._gone, self._state = None, welcome
            self._states += 1
            self._changed.notify_all()

    # -- read by the display -----------------------------------------------------------

    @property
    def state(self) -> ControllerState:
        with self._lock:
            return self._state

    def view(self) -> SessionView:
        with self._lock:
            rows = self._rows
            trace = RunTrace(
                run_id=self._run_id,
                iterations=np.array([r[0] for r in rows], int),
                times_s=np.array([r[1] for r in rows], float),
                errors_px=np.array([r[2] for r in rows], float),
                twists=np.array([r[3] for r in rows], float).reshape(-1, 6),
                path_m=np.array(self._path, float).reshape(-1, 3),
            )
            return SessionView(self._state, self._frame, trace, self._states, self._runs_ended, self._gone)

    def wait_for_news(self, seen_states: int, seen_frames: int, timeout_s: float) -> bool:
        """Block until a state or frame newer than those counts arrives (or the controller goes or is back); False on timeout."""
        with self._changed:
            return self._changed.wait_for(lambda: self._states > seen_states or self._frames > seen_frames, timeout_s)
