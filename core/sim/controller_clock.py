"""The emulated controller's own count of the time a real one would take: the cell clock.

An emulator runs its arm ``time_scale`` times faster than a real JRC, on a host whose
own delays vary with the machine's load; the wall clock multiplied by the speed-up
would count those delays that many times, and a run of the same seed would read a
different cell time each time. The emulator knows better: how long each motion lasts
by its motion model (core/sim/jrc_emulator.py) and how many bytes each exchange puts
on the line. ``ControllerClock`` adds them up as a real controller on that line would
spend them, so the same exchanges read the same time whatever the wall clock did:

- an exchange outside a motion costs its bytes at the line's rate (9600 baud on the
  JRC's RS-232: 100 .. 135 ms; microseconds over Ethernet);
- a motion starts once its command (MOVL, IMOV) has crossed to the controller, and its
  answer crosses while the arm moves;
- the exchanges that wait for the motion's end (JWAIT, or RSTATS polls over Ethernet)
  overlap it: those that find it still running cost nothing, and the one that reports its
  end ends one reply after it (or after its own request, if that arrived later);
- a motion cut short (hold, servo off, alarm) ends where the plant stopped it.

What the host does between its commands (vision, the control law, the safety layer's
checks) is not the controller's and does not count: the host measures its own wall time.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

MOTION_COMMANDS = frozenset({"MOVL", "IMOV"})


class Ended(StrEnum):
    """What an answer says of the motion under way."""

    RUNNING = "running"  # still moving (a JWAIT whose time ran out, RSTATS's running bit)
    ENDED = "ended"  # the motion has ended (JWAIT's data answer, RSTATS without the bit)
    SILENT = "silent"  # nothing (any other command)


@dataclass(frozen=True)
class CountedExchange:
    """One exchange as the clock counted it: the command's name, its request's and its
    reply's time on the line, the motion it set going (s, or 0), what its answer said of
    the motion under way, and the clock after it."""

    name: str
    request_s: float
    reply_s: float
    motion_s: float
    ended: Ended
    ends_s: float


@dataclass
class ControllerClock:
    """The cell clock of an emulated controller (module docstring), in s from its start.

    ``exchanges`` keeps every exchange counted, in order: what a bench splits by phase
    and compares with the floor of the moves it made.
    """

    now_s: float = 0.0
    exchanges: list[CountedExchange] = field(default_factory=list)
    _motion_start_s: float | None = None  # the motion under way, as the clock has it
    _motion_s: float = 0.0

    def count(self, name: str, request_s: float, reply_s: float, motion_s: float, ended: Ended) -> None:
        """One exchange: ``request_s`` and ``reply_s`` its two halves' time on the line,
        ``motion_s`` the duration of the motion it set going (0 for none), ``ended`` what
        its answer says of the motion under way."""
        pending = self._motion_start_s is not None
        if pending and ended is Ended.RUNNING:
            pass  # a wait that found the arm still moving crossed the line while it moved
        elif pending and (ended is Ended.ENDED or motion_s > 0.0):
            # The end reported, or a new motion taken (so the last one had ended): not before it.
            motion_end_s = self._motion_s + (self._motion_start_s or 0.0)
            self.now_s = max(self.now_s + request_s, motion_end_s) + reply_s
            self._motion_start_s = None
        else:
            self.now_s += request_s + reply_s
        if motion_s > 0.0:  # it moves once the command has crossed; the answer crosses meanwhile
            self._motion_start_s, self._motion_s = self.now_s - reply_s, motion_s
        self.exchanges.append(CountedExchange(name, request_s, reply_s, motion_s, ended, self.now_s))

    def cut(self, ran_s: float) -> None:
        """The motion under way was stopped after ``ran_s`` of its run (hold, servo off, alarm)."""
        if self._motion_start_s is not None:
            self._motion_s = min(self._motion_s, ran_s)
