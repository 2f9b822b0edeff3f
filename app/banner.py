"""The cell's state at a glance, and which buttons can act: two plain functions of the phase.

``banner_for`` turns the controller's state into the full-width banner every page shows:
a kind (its colour), the words an operator reads from across the room, and what to do
next. ``live_buttons`` says which of the page's buttons can act now; every panel enables
its buttons from it, so no button is ever live where pressing it would only be refused.
Both are viser-free and tested without a browser (tests/app/test_app_banner.py).
"""

from __future__ import annotations

import html
from dataclasses import dataclass
from enum import Enum

from vservo.core.production.protocol import ControllerState, Outcome, Phase, RunOutcome
from vservo.core.production.protocol.catalogue import explain
from vservo.core.servo.laws.base import Stage


class Kind(Enum):
    """What the banner's colour says; the value is its background colour."""

    READY = "#1c7ed6"  # blue: nothing moves, the cell waits for an operator
    BUSY = "#0b7285"  # teal: the robot moves or the cell is being taught
    PLACED = "#2b8a3e"  # green: the part is in the metal part
    MISSED = "#e67700"  # amber: the run finished but the part is not where it must be
    FAULT = "#c92a2a"  # red: something failed; the robot is held
    ESTOPPED = "#a61e4d"  # crimson: the e-stop holds the robot


# What each servo stage does, as the operator sees the arm move (section 4.4's stages).
STAGE_WORDS = {
    Stage.ALIGN_1A: "turning to face the part",
    Stage.CENTRE_1B: "turning the laser onto the part",
    Stage.APPROACH_2: "approaching with the laser",
    Stage.FINISH_3: "final alignment",
    Stage.IBVS: "moving to the taught view",
    Stage.PBVS: "moving to the taught view",
}

OUTCOME_KINDS = {
    Outcome.PLACED: Kind.PLACED,
    Outcome.MISSED: Kind.MISSED,
    Outcome.FAULT: Kind.FAULT,
    Outcome.ESTOPPED: Kind.ESTOPPED,
}


@dataclass(frozen=True)
class Banner:
    kind: Kind
    title: str  # the state in a few words ("Running job demo: final alignment")
    next_step: str  # what the operator does now
    detail: str = ""  # the controller's own line (what failed, what was just done)

    def html(self) -> str:
        """The banner as the page shows it: full width over the top of the page, above every tab."""
        detail = f"<div style='font-size:0.95em;opacity:0.92'>{html.escape(self.detail)}</div>" if self.detail else ""
        return (
            f"<div class='vservo-banner' data-kind='{self.kind.name.lower()}' "
            f"style='background:{self.kind.value}'>"
            f"<div style='font-size:1.5em;font-weight:800'>{html.escape(self.title)}</div>"
            f"<div style='font-size:1.1em'>{html.escape(self.next_step)}</div>{detail}</div>"
        )


def stage_words(stage: Stage | str | None) -> str:
    """The servo stage in the operator's words (an unknown stage keeps its code)."""
    if stage is None:
        return ""
    try:
        return STAGE_WORDS[Stage(stage)]
    except (ValueError, KeyError):
        return str(stage)


def banner_for(state: ControllerState, controller_gone: str | None = None) -> Banner:
    """The banner for the controller's state."""
    if controller_gone:
        return Banner(Kind.FAULT, "CONTROLLER STOPPED", CONTROLLER_GONE_WORDS, controller_gone)
    job, detail = state.job or "demo", state.detail
    if state.phase is Phase.DONE:
        return _banner_done(state, job)
    if state.phase is Phase.SERVOING:
        words = stage_words(state.run.stage)
        return Banner(
            Kind.BUSY,
            f"RUNNING job {job}" + (f": {words}" if words else ""),
            "The robot moves: keep clear; E-STOP holds it.",
            "" if state.run.iteration else detail,  # the law's notes, with their formulas, are the Engineering fold's
        )
    last = state.last_outcome
    if state.phase is Phase.FAULT and last is not None and last.outcome is Outcome.FAULT and last.end is not None:
        return _banner_explained(Kind.FAULT, f"FAULT: job {job}", last)
    kind, title, next_step = PHASE_BANNERS[state.phase]
    return Banner(kind, title.format(job=job), next_step, detail)


# While the controller process is gone nothing holds the robot for vservo; `vservo serve` starts a new one.
CONTROLLER_GONE_WORDS = "The robot is not held by vservo: if it moves, press the pendant's e-stop. A new controller is starting."


def _banner_explained(kind: Kind, title: str, last: RunOutcome) -> Banner:
    """A run's end as the catalogue explains it: what happened, what to do (the engineer's reason is in the Engineering fold)."""
    assert last.end is not None
    explanation = explain(last.end)
    return Banner(kind, title, explanation.action.value, explanation.sentence)


# The banner of each phase but servoing and done: kind, title ({job}: the job's name) and what to do next.
PHASE_BANNERS = {
    Phase.IDLE: (Kind.READY, "READY", "Choose a job, present a part and press Start; or teach a new job."),
    Phase.MANUAL: (Kind.BUSY, "MANUAL", "Move the arm in the Teach tab (Move the arm); press Leave manual mode when done."),
    Phase.TEACHING: (Kind.BUSY, "TEACHING", "Follow the steps in the Teach tab, then Save the job."),
    Phase.COMMISSIONING: (Kind.BUSY, "COMMISSIONING", "The robot shows the camera the board: keep clear of the cell."),
    Phase.PICKING: (Kind.BUSY, "RUNNING job {job}: picking the part", "The robot moves: keep clear."),
    Phase.PLACING: (Kind.BUSY, "RUNNING job {job}: placing the part", "The robot moves: keep clear."),
    Phase.ESTOPPED: (Kind.ESTOPPED, "E-STOPPED", "The robot is held. When the cell is safe, press Reset."),
    Phase.FAULT: (Kind.FAULT, "FAULT", "Fix what failed (below), then press Reset."),
}


def _banner_done(state: ControllerState, job: str) -> Banner:
    """Done: the outcome decides (a missed part is no success, and says so)."""
    last = state.last_outcome
    outcome = None if last is None else last.outcome
    reason = (last.reason if last is not None else "") or state.detail
    if outcome in (Outcome.FAULT, Outcome.ESTOPPED) and last is not None and last.end is not None:
        return _banner_explained(OUTCOME_KINDS[outcome], f"{outcome.value.upper()}: job {job}", last)
    if outcome == Outcome.MISSED:
        return Banner(Kind.MISSED, f"MISSED: job {job}", "Take the part out of the metal part, then press Reset.", reason)
    if outcome in (Outcome.FAULT, Outcome.ESTOPPED):
        return Banner(OUTCOME_KINDS[outcome], f"{outcome.value.upper()}: job {job}", "Press Reset.", reason)
    return Banner(Kind.PLACED, f"PLACED: job {job}", "Press Reset, present the next part and press Start.", reason)


class Button(Enum):
    """The page's buttons whose use depends on what the cell does (the Teach tab's are its own)."""

    START = "Start"
    PRESENT_PART = "Present part"
    RESET = "Reset"
    START_COMMISSIONING = "Start commissioning"
    APPLY_COMMISSIONING = "Apply"
    RUN_CALIBRATION = "Run calibration"
    STOP_CALIBRATION = "Stop calibration"
    REPLAY = "Replay"


@dataclass(frozen=True)
class Situation:
    """What decides the buttons besides the phase: facts the app knows, not the controller."""

    can_present_part: bool = False  # the cell has a part feeder (simulated, or a test fixture)
    commissioning_to_apply: bool = False  # a good commissioning waits for Apply
    calibrating: bool = False  # the NN calibration study runs (app/calibration_run.py)
    has_runs: bool = False  # a recorded run to replay


READY_PHASES = (Phase.IDLE, Phase.DONE, Phase.FAULT)  # where a run or a commissioning may start (as the controller checks)


def live_buttons(phase: Phase, situation: Situation = Situation()) -> frozenset[Button]:
    """The buttons that can act in ``phase``, as the controller decides (cell_controller.py's
    ``_require``): a run, a part or a commissioning from ready, a finished run or a fault (a part
    also while teaching), never
    while something runs or the e-stop holds the robot; Reset only where there is something to
    reset; the calibration study's Run or Stop, whichever it can do."""
    live = set()
    if phase in READY_PHASES:
        live |= {Button.START, Button.START_COMMISSIONING}
        if situation.commissioning_to_apply:
            live.add(Button.APPLY_COMMISSIONING)
    if situation.can_present_part and phase in (*READY_PHASES, Phase.TEACHING):  # a part to teach on, too
        live.add(Button.PRESENT_PART)
    if phase in (Phase.DONE, Phase.FAULT, Phase.ESTOPPED):
        live.add(Button.RESET)
    live.add(Button.STOP_CALIBRATION if situation.calibrating else Button.RUN_CALIBRATION)
    if situation.has_runs:
        live.add(Button.REPLAY)
    return frozenset(live)
