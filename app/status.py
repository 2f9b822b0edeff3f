"""What the screens say about the cell, as text: status line, run progress, outcome, history.

Plain functions from the controller's state (a dict) and the stored runs to markdown and
numbers, so that every browser says the same and the wording is tested without a browser.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np

from vservo.app.banner import stage_words
from vservo.app.session import RunTrace
from vservo.core.geometry.spatial import pose_from_matrix, pose_to_mm_deg
from vservo.core.production.assembly import Outcome, Phase

PHASE_WORDS = {
    Phase.IDLE: "Idle",
    Phase.TEACHING: "Teaching",
    Phase.COMMISSIONING: "Commissioning",
    Phase.SERVOING: "Servoing",
    Phase.PICKING: "Picking",
    Phase.PLACING: "Placing",
    Phase.DONE: "Done",
    Phase.FAULT: "FAULT",
    Phase.ESTOPPED: "E-STOPPED",
}
OUTCOME_WORDS = {
    Outcome.PLACED: "placed",
    Outcome.MISSED: "MISSED",
    Outcome.FAULT: "FAULT",
    Outcome.ESTOPPED: "E-STOPPED",
    Outcome.INTERRUPTED: "INTERRUPTED",
    None: "running",
}


def _number(value: object, digits: int = 2, unit: str = "") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{float(value):.{digits}f}{unit}"


def status_markdown(state: dict, operator_present: bool, controller_gone: str | None = None) -> str:
    """The line every browser shows under the e-stop."""
    if controller_gone:
        return f"**CONTROLLER STOPPED**: {controller_gone}. Restart `vservo serve`."
    phase = PHASE_WORDS.get(state.get("phase"), str(state.get("phase")))
    parts = [f"**{phase}**"]
    if state.get("job"):
        parts.append(f"job `{state['job']}`")
    if state.get("run_id") is not None and state.get("phase") not in (Phase.IDLE, Phase.TEACHING):
        parts.append(f"run {state['run_id']}")
        if state.get("stage"):
            parts.append(stage_words(state["stage"]))
        parts.append(f"cycle {state.get('iteration', 0)}")
        parts.append(f"error {_number(state.get('error_px'), 1, ' px')}")
    control = "an operator holds control" if operator_present else "no operator"
    robot = f"{state.get('robot', '')} on {state.get('backend', '')}".strip()
    detail = state.get("detail") or ""
    # Until the controller has read the robot (its first command) the pose is unknown: never a made-up one.
    flange = flange_text(state["bMe"]) if state.get("q") else "flange pose not known yet"
    return f"{' · '.join(parts)}  \n{detail}  \n<small>{robot} · {flange} · {control}</small>"


# The laws' equations per stage (section 4.4; docs/thesis-notes.md), for the engineering fold.
STAGE_EQUATIONS = {
    "1A": "eqs. 4-26 .. 4-29",
    "1B": "eq. 4-36",
    "2": "eqs. 4-39 .. 4-49",
    "3": "eqs. 4-50, 4-51",
    "ibvs": "eq. 4-14",
    "pbvs": "eq. 2-47",
}


def engineering_markdown(state: dict) -> str:
    """The servo's own terms: stage code and its equations, cycle, ||f_id - f|| and the twist cVc."""
    stage = state.get("stage")
    if not stage:
        return "No servo stage under way."
    twist = ", ".join(_number(v, 4) for v in state.get("cVc") or [])
    return (
        f"stage `{stage}` ({STAGE_EQUATIONS.get(str(stage), 'no equation on record')}) · cycle "
        f"{state.get('iteration', 0)} · ||f_id - f|| = {_number(state.get('error_px'), 2, ' px')}  \n"
        f"cVc = [{twist}] (m/s, rad/s)"
    )


def flange_text(bMe: object) -> str:
    """The flange pose as the robot's pendant shows it: X Y Z in mm, phi theta psi in deg (eq. 2-13).

    Angles in [-90, 270): a tool pointing down has an angle of 180 deg, which in (-180, 180]
    would flip between 179.99 and -179.99 at every tremor."""
    pose = np.array(pose_to_mm_deg(pose_from_matrix(np.asarray(bMe, float))), float)
    pose[3:] = (pose[3:] + 90.0) % 360.0 - 90.0
    x, y, z, phi, theta, psi = np.round(pose, 2) + 0.0  # no "-0.00"
    return f"flange X {x:.2f} Y {y:.2f} Z {z:.2f} mm, phi {phi:.2f} theta {theta:.2f} psi {psi:.2f} deg"


def run_progress(state: dict, trace: RunTrace, threshold_px: float) -> float:
    """0..100 through the run: the servo's share follows the smallest feature error so far on a
    log scale from its first value down to the threshold; pick and place are fixed steps."""
    phase = state.get("phase")
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


def outcome_markdown(outcome: dict | None, run_id: int | None) -> str:
    """The last run's end, as the operator reads it."""
    if not outcome:
        return "No run finished yet in this session."
    word = OUTCOME_WORDS.get(outcome.get("outcome"), str(outcome.get("outcome")))
    return (
        f"**Run {run_id}: {word}**: {outcome.get('reason', '')}  \n"
        f"final feature error {_number(outcome.get('final_error_px'), 2, ' px')} · "
        f"placement error {_number(outcome.get('placement_error_mm'), 2, ' mm')} · "
        f"{_number(outcome.get('duration_s'), 1, ' s')} · {outcome.get('iterations', 0)} servo cycles"
    )


def runs_table(runs: Sequence[dict], limit: int = 15) -> str:
    """Past runs, newest first, as a markdown table."""
    if not runs:
        return "No runs yet."
    lines = ["| run | job | outcome | duration | final error | placement | started |", "|---|---|---|---|---|---|---|"]
    for run in runs[:limit]:
        started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(run["started_at"]))
        lines.append(
            f"| {run['id']} | {run['job']} | {OUTCOME_WORDS.get(run.get('outcome'), run.get('outcome'))} | "
            f"{_number(run.get('duration_s'), 1, ' s')} | {_number(run.get('final_error_px'), 2, ' px')} | "
            f"{_number(run.get('placement_error_mm'), 2, ' mm')} | {started} |"
        )
    return "\n".join(lines)


def run_label(run: dict) -> str:
    """A run as a dropdown entry."""
    return f"#{run['id']} {run['job']} {OUTCOME_WORDS.get(run.get('outcome'), run.get('outcome'))}"


def run_heading(run: dict) -> str:
    """One run in a line: its number, job, outcome and why (its stages are app/stage_chart.py's chart)."""
    return (
        f"**Run {run['id']}** ({run['job']}): {OUTCOME_WORDS.get(run.get('outcome'), run.get('outcome'))}, "
        f"{run.get('reason') or ''}"
    )
