"""Replaying a recorded run: when each recorded frame is due, and the operator's play, pause,
seek and speed.

The recording's timestamps (``time_s`` per cycle) set the pace. On a real cell they are the
controller's clock, and a replay at 1x lasts as long as the servo did. The simulated cell
records its own simulated clock, which runs slower than the run took (a simulated cycle
covers more time than its wall-clock period): there the timestamps are scaled so the replay
lasts the run's recorded duration, never longer. Viser-free: tested without a browser.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from vservo.core.geometry.spatial import Matrix

SPEEDS = {"0.25x": 0.25, "0.5x": 0.5, "1x": 1.0, "2x": 2.0, "4x": 4.0}


@dataclass(frozen=True)
class ReplayTimeline:
    """The shown frames' times from the replay's start at 1x (s), and the flange path (m) and
    feature error (px) recorded with each."""

    times_s: Matrix
    errors_px: Matrix
    path_m: Matrix  # (N, 3)

    @classmethod
    def from_cycles(cls, cycles: Sequence[dict], run_duration_s: float | None) -> ReplayTimeline:
        """``cycles``: the recorded cycles shown (each with ``time_s``, ``error_px``, ``bMe``)."""
        times = np.array([float(c.get("time_s") or 0.0) for c in cycles], float)
        times = times - times[0] if len(times) else times
        span = float(times[-1]) if len(times) else 0.0
        if run_duration_s and span > run_duration_s > 0.0:
            times = times * (run_duration_s / span)  # a simulated clock: the run's own duration
        errors = np.array([np.nan if c.get("error_px") is None else float(c["error_px"]) for c in cycles], float)
        path = np.array(
            [np.asarray(c["bMe"], float)[:3, 3] if c.get("bMe") is not None else np.full(3, np.nan) for c in cycles], float
        ).reshape(-1, 3)
        return cls(times, errors, path)

    @property
    def duration_s(self) -> float:
        return float(self.times_s[-1]) if len(self.times_s) else 0.0

    def index_at(self, t_s: float) -> int:
        """The frame shown at replay time ``t_s``: the last one due by then."""
        return max(0, int(np.searchsorted(self.times_s, t_s, side="right")) - 1)


class ReplayClock:
    """Where a replay is, in replay seconds: play, pause, seek (to a frame) and speed.

    Thread-safe: the browser's callbacks steer it while the replay thread reads it.
    ``changed`` is set on every steer, so the replay thread wakes at once.
    """

    def __init__(self, timeline: ReplayTimeline, now: Callable[[], float] = time.monotonic) -> None:
        self.timeline, self._now = timeline, now
        self._lock = threading.Lock()
        self._position_s = 0.0  # at _since (wall clock), while playing
        self._since = now()
        self._speed = 1.0
        self._playing = False
        self.changed = threading.Event()

    def _position(self) -> float:
        moved = (self._now() - self._since) * self._speed if self._playing else 0.0
        return min(self._position_s + moved, self.timeline.duration_s)

    def _steer(self, position_s: float, playing: bool, speed: float) -> None:
        self._position_s, self._since, self._playing, self._speed = position_s, self._now(), playing, speed
        self.changed.set()

    def play(self) -> None:
        with self._lock:
            position = self._position()
            if position >= self.timeline.duration_s:
                position = 0.0  # play after the end starts over
            self._steer(position, True, self._speed)

    def pause(self) -> None:
        with self._lock:
            self._steer(self._position(), False, self._speed)

    def seek(self, index: int) -> None:
        with self._lock:
            index = int(np.clip(index, 0, len(self.timeline.times_s) - 1))
            self._steer(float(self.timeline.times_s[index]), self._playing, self._speed)

    def set_speed(self, speed: float) -> None:
        if not speed > 0.0:
            raise ValueError(f"replay speed must be positive, got {speed!r}")
        with self._lock:
            self._steer(self._position(), self._playing, speed)

    @property
    def playing(self) -> bool:
        with self._lock:
            return self._playing and self._position() < self.timeline.duration_s

    def index(self) -> int:
        with self._lock:
            return self.timeline.index_at(self._position())

    def until_next_s(self) -> float | None:
        """Wall seconds until the next frame is due (None when paused or at the end)."""
        with self._lock:
            if not self._playing:
                return None
            position = self._position()
            following = self.timeline.index_at(position) + 1
            if following >= len(self.timeline.times_s):
                return None
            return (float(self.timeline.times_s[following]) - position) / self._speed
