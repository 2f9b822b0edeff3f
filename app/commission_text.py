"""What the Calibrate tab says about commissioning, as text: the progress of each part of
the procedure, then in plain words each step's verdict and the acceptance check; for the
Engineering fold, each step's residuals and the measured values (docs/commissioning.md).

Plain functions of the state's ``commissioning`` record (CommissioningProgress, in
core/production/protocol/state.py) to markdown, so every browser says the same and the
wording is tested without a browser.
"""

from __future__ import annotations

from vservo.core.production.protocol import CommissioningProgress, CommissionStep
from vservo.core.production.protocol.state import StepReport

# The procedure's parts as Progress names them, in the order they run.
PROCEDURE = {
    "find": "finding the board",
    "tilted": "tilted views (camera, hand-eye)",
    "laser": "laser spot views",
    "grid": "the network's grid of views",
    "nn": "training the network",
    "acceptance": "acceptance check",
}
# Commissioning's steps and how the results table names them.
STEP_WORDS = {
    CommissionStep.CAMERA: "camera",
    CommissionStep.HAND_EYE: "hand-eye",
    CommissionStep.LASER: "laser",
    CommissionStep.NN: "network (nn)",
}


SKIPPED = "out of the arm's reach, skipped"  # a viewpoint commissioning passes over: no failure


def progress_markdown(record: CommissioningProgress | None, cell_file: str) -> str:
    """Which cell file the controller runs on, and how commissioning goes: a line per part of
    the procedure (views, or epochs, done of total and the last note)."""
    runs_on = f"The controller runs on `{cell_file}`.  "
    if record is None:
        return (
            f"{runs_on}  \nNot commissioned in this session. Choose the steps and press **Start commissioning**: "
            "the robot shows the camera the calibration board (the simulated cell lays it on the table itself)."
        )
    summary = record.summary
    if record.applied:
        head = f"**Applied**: the controller's model is now `{record.applied}`."
    elif record.error:
        head = f"**Commissioning stopped**: {record.error}"
    elif summary is not None:
        retakes = [step for step, report in summary.steps.items() if report.verdict != "good"]
        head = (
            f"**Commissioned**: every step is good. **Apply** writes `{record.out}`."
            if not retakes
            else f"**Commissioned**, but {', '.join(retakes)} say{'s' if len(retakes) == 1 else ''} retake: commission again."
        )
    else:
        head = f"**Commissioning** {', '.join(record.steps)}; the new cell file will be `{record.out}`."
    lines = [head, ""] if record.applied else [runs_on, head, ""]
    for name, line in record.progress.items():
        what = PROCEDURE.get(name, name)
        # Once it ended, the step's verdict speaks: the last view's note (a viewpoint out of
        # reach, skipped) would read as a failure of a step that is good.
        last = "" if summary is not None else f" (last: {SKIPPED if line.note == 'unreachable' else line.note})"
        count = (
            f"epoch {line.done} of at most {line.total}, {line.note}"
            if name == "nn"
            else f"{line.done} of {line.total} views{last}"
        )
        lines.append(f"- {what}: {count}")
    return "\n".join(lines).strip()


def _verdict(report: StepReport) -> str:
    if report.verdict == "good":
        return "good"
    why = report.why
    return "**retake**" + (why[len("retake") :] if why.startswith("retake") else f": {why}")


def _residuals(step: CommissionStep, r: StepReport) -> str:
    if step == CommissionStep.CAMERA:
        return (
            f"RMS {r.rms_px:.3f} px over {r.views} views (worst view {r.worst_view_rms_px:.3f} px); "
            f"fx known to ±{r.std_fx_px:.2f} px"
        )
    if step == CommissionStep.HAND_EYE:
        return f"RMS {r.rms_px:.3f} px; board seen still to {r.spread_mm:.3f} mm, {r.spread_deg:.3f} deg"
    if step == CommissionStep.LASER:
        return f"line RMS {r.line_rms_mm:.3f} mm over {r.depth_span_mm:.0f} mm of depth, {r.spots} spots"
    return (
        f"validation error {r.validation_mean_mm:.3f} mm mean, {r.validation_max_mm:.3f} mm max "
        f"({r.corners} corners from {r.views} views)"
    )


def _pose(values: tuple[float, ...]) -> str:
    x, y, z, phi, theta, psi = values
    return f"X {x:.3f} Y {y:.3f} Z {z:.3f} mm, phi {phi:.3f} theta {theta:.3f} psi {psi:.3f} deg"


def results_markdown(record: CommissioningProgress | None) -> str:
    """When commissioning has finished, in plain words: each step's verdict (what to change
    when it says retake) and the acceptance check, the figure to sign off; empty before."""
    summary = None if record is None else record.summary
    if summary is None:
        return ""
    lines = [f"- {STEP_WORDS[step]}: {_verdict(report)}" for step, report in summary.steps.items()]
    acceptance = summary.acceptance
    lines.append("")
    if acceptance:
        lines.append(
            f"**Acceptance check, the figure to sign off**: mean error **{acceptance.mean_mm:.3f} mm**, "
            f"max **{acceptance.max_mm:.3f} mm** over {acceptance.corners} board corners (where the "
            "commissioned model puts a corner the camera sees, against where the board has it)."
        )
    else:
        lines.append("No acceptance check: it needs the camera or the hand-eye step.")
    return "\n".join(lines)


def engineering_markdown(record: CommissioningProgress | None) -> str:
    """When commissioning has finished, for the Engineering fold: each step's residuals and
    the measured values; empty before."""
    summary = None if record is None else record.summary
    if record is None or summary is None:
        return ""
    lines = ["| step | residuals |", "|---|---|"]
    for step, report in summary.steps.items():
        lines.append(f"| {STEP_WORDS[step]} | {_residuals(step, report)} |")

    def kept(step: CommissionStep) -> str:
        return "" if step in record.steps else " (not measured: the cell file's)"

    camera, laser = summary.camera, summary.laser
    u0, v0 = camera.principal_point_px
    lines += [
        "",
        "Measured values:",
        "",
        f"- camera: fx {camera.fx_px:.2f} px, fy {camera.fy_px:.2f} px, principal point "
        f"({u0:.2f}, {v0:.2f}) px{kept(CommissionStep.CAMERA)}",
        f"- hand-eye eMc: {_pose(summary.eMc_mm_deg)}{kept(CommissionStep.HAND_EYE)}",
        f"- laser cMl: {_pose(summary.cMl_mm_deg)}{kept(CommissionStep.LASER)}",
        f"- laser baseline d {laser.baseline_mm:.2f} mm, angle alpha {laser.alpha_deg:.2f} deg{kept(CommissionStep.LASER)}",
        "",
        f"<small>{summary.views.used} of {summary.views.taken} views used · "
        f"{summary.cell_time_s:.0f} s of cell time · views and network in "
        f"`{record.out.removesuffix('.toml')}-commissioning`</small>",
    ]
    return "\n".join(lines)


def apply_question(record: CommissioningProgress) -> str:
    """The confirmation Apply asks for."""
    return f"Write `{record.out}` and reload the controller's model from it?"
