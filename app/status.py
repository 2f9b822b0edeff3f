"""What the screens say about the cell, as text: status line, run progress, outcome, history.

Plain functions from the controller's state (a ControllerState) and the stored runs
(RunEntry) to markdown and numbers, so that every browser says the same and the wording is tested without a browser.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np

from vservo.app.banner import CONTROLLER_GONE_WORDS, stage_words
from vservo.app.session import RunTrace
from vservo.core.geometry.spatial import pose_from_matrix, pose_to_mm_deg
from vservo.core.production.protocol import ControllerState, Outcome, Phase, RunEntry, RunOutcome
from vservo.core.production.protocol.catalogue import explain

PHASE_WORDS = {
    Phase.IDLE: "Idle",
    Phase.MANUAL: "Manual",
    Phase.TEACHING: "Teaching",
    Phase.COMMISSIONING: "Commissioning",
    Phase.SERVOING: "Servoing",
    Phase.PICKING: "Picking",
    Phase.PLACING: "Placing",
    Phase.DONE: "Done",
    Phase.FAULT: "FAULT",
    Phase.ESTOPPED: "E-STOPPED",
}
OUTCOME_WORDS: dict[Outcome | None, str] = {
    Outcome.PLACED: "placed",
    Outcome.MISSED: "MISSED",
    Outcome.FAULT: "FAULT",
    Outcome.ESTOPPED: "E-STOPPED",
    Outcome.INTERRUPTED: "INTERRUPTED",
    None: "running",
}


def _number(value: float | None, digits: int = 2, unit: str = "") -> str:
    if value is None or not math.isfinite(value):
        return "-"
    return f"{float(value):.{digits}f}{unit}"


def status_markdown(state: ControllerState, operator_present: bool, controller_gone: str | None = None) -> str:
    """The line every browser shows under the e-stop."""
    if controller_gone:
        return f"**CONTROLLER STOPPED**: {controller_gone}. {CONTROLLER_GONE_WORDS}"
    parts = [f"**{PHASE_WORDS[state.phase]}**"]
    if state.job:
        parts.append(f"job `{state.job}`")
    run = state.run
    if run.run_id is not None and state.phase not in (Phase.IDLE, Phase.TEACHING):
        parts.append(f"run {run.run_id}")
        if run.stage:
            parts.append(stage_words(run.stage))
        parts.append(f"cycle {run.iteration}")
        parts.append(f"error {_number(run.error_px, 1, ' px')}")
    control = "an operator holds control" if operator_present else "no operator"
    robot = f"{state.robot} on {state.backend}".strip()
    # Until the controller has read the robot (its first command) the pose is unknown: never a made-up one.
    flange = flange_text(state.bMe) if state.q.size else "flange pose not known yet"
    return f"{' · '.join(parts)}  \n{_plain_detail(state)}  \n<small>{robot} · {flange} · {control}</small>"


def _plain_detail(state: ControllerState) -> str:
    """The controller's line, but a faulted run's in the catalogue's words (its own is the Engineering fold's)."""
    last = state.last_outcome
    if state.phase is Phase.FAULT and last is not None and last.outcome is Outcome.FAULT and last.end is not None:
        return explain(last.end).sentence
    return state.detail


# The laws' equations per stage (section 4.4; docs/thesis-notes.md), for the engineering fold.
STAGE_EQUATIONS = {
    "1A": "eqs. 4-26 .. 4-29",
    "1B": "eq. 4-36",
    "2": "eqs. 4-39 .. 4-49",
    "3": "eqs. 4-50, 4-51",
    "ibvs": "eq. 4-14",
    "pbvs": "eq. 2-47",
}


def engineering_markdown(state: ControllerState) -> str:
    """The servo's own terms: stage code and its equations, cycle, ||f_id - f|| and the twist cVc;
    the controller's own line and the last run's reason as it wrote them (the banner explains them)."""
    run = state.run
    lines = [f"Controller: {state.detail or '-'}"]
    if state.last_outcome is not None:
        end = f" ({state.last_outcome.end.value})" if state.last_outcome.end is not None else ""
        lines.append(f"Last run's end{end}: {state.last_outcome.reason}")
    if not run.stage:
        return "  \n".join(["No servo stage under way.", *lines])
    twist = ", ".join(_number(v, 4) for v in run.cVc)
    return "  \n".join(
        [
            f"stage `{run.stage}` ({STAGE_EQUATIONS.get(str(run.stage), 'no equation on record')}) · cycle "
            f"{run.iteration} · ||f_id - f|| = {_number(run.error_px, 2, ' px')}",
            f"cVc = [{twist}] (m/s, rad/s)",
            *lines,
        ]
    )


def pendant_pose(bMx: object) -> np.ndarray:
    """A pose as the robot's pendant shows it: X Y Z in mm, phi theta psi in deg (eq. 2-13),
    rounded to 2 decimals. Angles in [-90, 270): a tool pointing down has an angle of 180 deg,
    which in (-180, 180] would flip between 179.99 and -179.99 at every tremor."""
    pose = np.array(pose_to_mm_deg(pose_from_matrix(np.asarray(bMx, float))), float)
    pose[3:] = (pose[3:] + 90.0) % 360.0 - 90.0
    return np.round(pose, 2) + 0.0  # no "-0.00"


def flange_text(bMe: object) -> str:
    """The flange pose as the robot's pendant shows it (``pendant_pose``)."""
    x, y, z, phi, theta, psi = pendant_pose(bMe)
    return f"flange X {x:.2f} Y {y:.2f} Z {z:.2f} mm, phi {phi:.2f} theta {theta:.2f} psi {psi:.2f} deg"


def run_progress(state: ControllerState, trace: RunTrace, threshold_px: float) -> float:
    """0..100 through the run: the servo's share follows the smallest feature error so far on a
    log scale from its first value down to the threshold; pick and place are fixed steps."""
    phase = state.phase
    if phase == Phase.DONE:
        return 100.0
    if phase == Phase.PLACING:
        return 88.0
    if phase == Phase.PICKING:
        return 75.0
    if phase not in (Phase.SERVOING, Phase.FAULT, Phase.ESTOPPED):
        return 0.0
    errors = trace.errors_px[np.isfinite(trace.errors_px)]
    if len(errors) == 0:
        return 5.0
    # The best error so far: the bar never goes back when a stage switch raises the error a little.
    first, now = max(errors[0], threshold_px * 1.01), max(errors.min(), threshold_px)
    share = np.clip(np.log(first / now) / np.log(first / threshold_px), 0.0, 1.0)
    return float(10.0 + 60.0 * share)


def outcome_markdown(outcome: RunOutcome | None, run_id: int | None) -> str:
    """The last run's end, as the operator reads it."""
    if outcome is None:
        return "No run finished yet in this session."
    return (
        f"**Run {run_id}: {OUTCOME_WORDS[outcome.outcome]}**: {outcome.reason}  \n"
        f"final feature error {_number(outcome.final_error_px, 2, ' px')} · "
        f"placement error {_number(outcome.placement_error_mm, 2, ' mm')} · "
        f"{_number(outcome.duration_s, 1, ' s')} · {outcome.iterations} servo cycles"
    )


def runs_table(runs: Sequence[RunEntry], limit: int = 15) -> str:
    """Past runs, newest first, as a markdown table."""
    if not runs:
        return "No runs yet."
    lines = [
        "| run | job | outcome | duration | final error | placement | started | recording |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for run in runs[:limit]:
        started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(run.started_at))
        lines.append(
            f"| {run.id} | {run.job} | {OUTCOME_WORDS[run.outcome]} | "
            f"{_number(run.duration_s, 1, ' s')} | {_number(run.final_error_px, 2, ' px')} | "
            f"{_number(run.placement_error_mm, 2, ' mm')} | {started} | {recording_words(run)} |"
        )
    return "\n".join(lines)


def recording_words(run: RunEntry) -> str:
    """Whether the run's recording can be replayed: kept, removed by the retention, or never made."""
    if run.recording_removed_at is not None:
        return "recording removed"
    return "kept" if run.recording else "-"


def run_label(run: RunEntry) -> str:
    """A run as a dropdown entry."""
    return f"#{run.id} {run.job} {OUTCOME_WORDS[run.outcome]}"


def run_heading(run: RunEntry) -> str:
    """One run in a line: its number, job, outcome and why (its stages are app/stage_chart.py's chart)."""
    removed = " (recording removed)" if run.recording_removed_at is not None else ""
    return f"**Run {run.id}** ({run.job}): {OUTCOME_WORDS[run.outcome]}, {run.reason or ''}{removed}"
