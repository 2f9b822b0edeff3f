"""The PLC handshake's state machine: the PLC's signals in, the cell's signals out.

The common handshake of vision-guided robot cells (docs/plc.md has its timing diagram):

- ready: the handshake is idle, the controller too (idle or done, nothing under way) and
  no fault is latched;
- start's rising edge while ready: the job number's bits select a job of [line.plc.jobs];
  with the part present, the run starts through the controller's own start (the page's
  guards: phase, e-stop, the robot's alarm, the safety layer); busy until it ends;
- at the end: done, and ok (the part placed) or not ok (missed, or the start refused: the
  part missing, an unknown job number, a refusal of the controller), held until the PLC
  drops start (at least one poll period);
- fault: the controller e-stopped or in fault (an E-STOP from any page, a run's fault)
  latches fault and not ok; ready stays low and no start is taken until the PLC's reset
  (a rising edge), which resets the controller as the page's Reset does.

A start edge while not ready is ignored, as is start dropping while busy: the run goes on
(the PLC stops a run with the cell's E-STOP, not by dropping start). ``step`` is called
once a poll period with the inputs read; it returns the outputs to write.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Protocol

from vservo.core.cell.config import PlcConfig
from vservo.core.errors import VservoError
from vservo.core.production.protocol.state import Outcome, Phase

log = logging.getLogger("vservo.plc")

# Where the controller can take a start: nothing under way, no e-stop, no fault.
READY_PHASES = frozenset({Phase.IDLE, Phase.DONE})
FAULT_PHASES = frozenset({Phase.ESTOPPED, Phase.FAULT})


@dataclass(frozen=True)
class PlcInputs:
    """The PLC's signals to the cell, as read in one poll. ``part_id``: what the PLC gave
    for the part (Modbus holding registers), None when it gives none."""

    start: bool = False
    job_number: int = 0
    part_present: bool = False
    reset: bool = False
    part_id: str | None = None


@dataclass(frozen=True)
class PlcOutputs:
    """The cell's signals to the PLC."""

    ready: bool = False
    busy: bool = False
    done: bool = False
    ok: bool = False
    not_ok: bool = False
    fault: bool = False


def job_number(bits: Sequence[bool]) -> int:
    """The job number the PLC's job bits carry, the first bit the least significant."""
    return sum(1 << i for i, on in enumerate(bits) if on)


class HandshakeState(Enum):
    IDLE = "idle"  # waiting for a start (ready when the controller can take one)
    BUSY = "busy"  # a run the PLC started is under way
    DONE = "done"  # the result is held until start drops
    FAULT = "fault"  # latched until the PLC's reset


class PlcCell(Protocol):
    """What the handshake asks of the controller (service.ControllerCell is the controller's)."""

    def phase(self) -> Phase: ...

    def running(self) -> bool: ...

    def start(self, job: str, part_id: str | None) -> None:
        """Start one run; a VservoError (the controller's refusal) when it cannot."""

    def outcome(self) -> Outcome | None:
        """How the run last ended."""

    def reset(self) -> None:
        """The page's Reset; a VservoError when the controller refuses it."""

    def say(self, detail: str) -> None:
        """Tell the operator what the PLC's signals did (the controller's published detail)."""


class Handshake:
    """The handshake of ``config`` on ``cell``: ``step(inputs) -> outputs`` once a poll."""

    def __init__(self, config: PlcConfig, cell: PlcCell) -> None:
        self.config, self.cell = config, cell
        self.state = HandshakeState.IDLE
        self.ok = False  # the result held in DONE
        self._last = PlcInputs()
        self.starts = 0  # runs started by the PLC
        self.refusals = 0  # starts answered not ok without a run

    @property
    def listening(self) -> bool:
        """Whether the inputs matter now: while busy, no input changes anything (a poller
        may leave the link to the run)."""
        return self.state is not HandshakeState.BUSY

    def step(self, inputs: PlcInputs) -> PlcOutputs:
        start_edge = inputs.start and not self._last.start
        reset_edge = inputs.reset and not self._last.reset
        self._last = inputs
        phase = self.cell.phase()
        if self.state is HandshakeState.BUSY:
            self._watch_run()
        elif self.state is not HandshakeState.FAULT and phase in FAULT_PHASES:
            self._fault(f"the cell is {phase.value}")
        elif self.state is HandshakeState.FAULT and reset_edge:
            self._reset(phase)
        elif self.state is HandshakeState.DONE and not inputs.start:
            self.state = HandshakeState.IDLE
        elif self.state is HandshakeState.IDLE and start_edge:
            if self._ready(phase):
                self._start(inputs)
            else:
                log.info("PLC start ignored: not ready (the controller is %s)", phase.value)
        return self.outputs(self.cell.phase())

    def outputs(self, phase: Phase) -> PlcOutputs:
        state = self.state
        return PlcOutputs(
            ready=state is HandshakeState.IDLE and self._ready(phase),
            busy=state is HandshakeState.BUSY,
            done=state is HandshakeState.DONE,
            ok=state is HandshakeState.DONE and self.ok,
            not_ok=(state is HandshakeState.DONE and not self.ok) or state is HandshakeState.FAULT,
            fault=state is HandshakeState.FAULT,
        )

    def _ready(self, phase: Phase) -> bool:
        return phase in READY_PHASES and not self.cell.running()

    def _start(self, inputs: PlcInputs) -> None:
        job = self.config.job_name(inputs.job_number)
        if not inputs.part_present:
            self._refuse("no part present (the part presence input is low)")
        elif job is None:
            self._refuse(f"job number {inputs.job_number} is not in [line.plc.jobs]")
        else:
            try:
                self.cell.start(job, inputs.part_id)
            except VservoError as exc:
                self._refuse(f"job {job!r}: {exc}")
                return
            except Exception:  # a bug: the PLC still gets its answer, the traceback goes to the log
                log.exception("PLC start of job %r: internal error", job)
                self._refuse(f"job {job!r}: internal error (its traceback is in the controller's log)")
                return
            self.starts += 1
            self.state = HandshakeState.BUSY
            log.info("PLC start: job %d (%s), part %s", inputs.job_number, job, inputs.part_id or "without an ID")

    def _refuse(self, why: str) -> None:
        self.refusals += 1
        self.state, self.ok = HandshakeState.DONE, False
        self.cell.say(f"PLC start refused: {why}")
        log.warning("PLC start refused: %s", why)

    def _watch_run(self) -> None:
        if self.cell.running():
            return
        outcome = self.cell.outcome()
        if outcome in (Outcome.PLACED, Outcome.MISSED):
            self.state, self.ok = HandshakeState.DONE, outcome is Outcome.PLACED
        else:
            self._fault(f"the run ended {outcome.value if outcome else 'without an outcome'}")

    def _fault(self, why: str) -> None:
        self.state, self.ok = HandshakeState.FAULT, False
        log.warning("PLC fault: %s; the PLC's reset clears it", why)

    def _reset(self, phase: Phase) -> None:
        if phase in FAULT_PHASES:
            try:
                self.cell.reset()
            except VservoError as exc:
                self.cell.say(f"PLC reset refused: {exc}")
                log.warning("PLC reset refused: %s", exc)
                return
        self.state = HandshakeState.IDLE
        self.cell.say("PLC reset: ready")
        log.info("PLC reset")
