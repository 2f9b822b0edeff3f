"""``vservo reproduce``: every task and method of chapter 5, the figures and the report.

The figures follow Figs. 5-1 .. 5-8 (image trajectories, camera velocities, pose errors,
feature errors, end-effector paths); the report puts the Table 5-4 analogue beside the
thesis's numbers and says, from the numbers of the run, where the results differ. The
snapshot records where it came from (core/study/provenance.py).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.cell.config import CellConfig, parse_cell, read_cell_bytes, read_cell_data
from vservo.core.servo.methods import METHODS
from vservo.core.sim import Arm
from vservo.core.study import calibration_errors, canvas, plots, provenance
from vservo.core.study.montecarlo import SampleOutcome, run_montecarlo
from vservo.core.study.run import RunResult, RunSettings, run_task
from vservo.core.study.tasks import (
    ROBUSTNESS_TASK,
    TASKS,
    THESIS_DESIRED_FEATURES_PX,
    THESIS_PATH_LENGTH_M,
    distance_to_thesis_set,
    robustness_cell,
)
from vservo.core.terminal.progress import Progress

MONTECARLO_METHODS = ("laser", "ibvs", "2.5d")
CORNER_COLORS = ((180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214))  # BGR, one per corner
LASER_COLOR = (0, 0, 200)


# -- figures -----------------------------------------------------------------------------


def image_trajectory(result: RunResult, title: str) -> canvas.Image:
    """Corner and laser-spot trajectories on the image plane (Figs. 5-1a .. 5-5a, 5-7)."""
    trace = result.trace
    series = [
        plots.Series(f"corner {i + 1}", trace.corners_px[:, i, 0], trace.corners_px[:, i, 1], CORNER_COLORS[i]) for i in range(4)
    ]
    series.append(plots.Series("laser spot", trace.laser_px[:, 0], trace.laser_px[:, 1], LASER_COLOR))
    return plots.image_trajectory_plot(
        series,
        title=title,
        initial_marker_points=trace.corners_px[0],
        desired_points=result.desired.corners_px,
        extra_points=[("desired laser spot", result.desired.laser_spot_px[None, :], LASER_COLOR)],
    )


def camera_velocity(result: RunResult) -> canvas.Image:
    t, cVc = result.trace.time_s, result.trace.cVc
    linear = plots.line_plot(
        [plots.Series(name, t, cVc[:, i]) for i, name in enumerate(("vx", "vy", "vz"))],
        "camera translational velocity",
        "time (s)",
        "m/s",
        size=(480, 300),
    )
    angular = plots.line_plot(
        [plots.Series(name, t, cVc[:, 3 + i]) for i, name in enumerate(("wx", "wy", "wz"))],
        "camera rotational velocity",
        "time (s)",
        "rad/s",
        size=(480, 300),
    )
    return canvas.grid([linear, angular], columns=1)


def pose_errors(result: RunResult) -> canvas.Image:
    t, errors = result.trace.time_s, result.trace.pose_error_true
    translation = plots.line_plot(
        [plots.Series("translation", t, errors[:, 0])], "end-effector position error", "time (s)", "m", size=(480, 300)
    )
    rotation = plots.line_plot(
        [plots.Series("rotation", t, errors[:, 1])], "end-effector orientation error", "time (s)", "rad", size=(480, 300)
    )
    return canvas.grid([translation, rotation], columns=1)


def feature_errors(result: RunResult) -> canvas.Image:
    trace = result.trace
    errors = trace.corners_px - result.desired.corners_px
    series = []
    for i in range(4):
        for axis, name in enumerate("uv"):
            series.append(plots.Series(f"{name}{i + 1}", trace.time_s, errors[:, i, axis]))
    return plots.line_plot(series, "image feature errors", "time (s)", "pixel", size=(640, 400))


def path_3d(results: dict[str, RunResult], title: str) -> canvas.Image:
    return plots.path_3d_plot([plots.Series3(label, result.trace.bMe_position_true) for label, result in results.items()], title)


def run_figure(result: RunResult, title: str, full: bool) -> canvas.Image:
    """Figs. 5-1 (image, pose and feature errors) and 5-2/5-3/5-5 (with velocities and path)."""
    panels = [image_trajectory(result, "(a) image trajectory")]
    if full:
        panels.append(camera_velocity(result))
    panels += [pose_errors(result), feature_errors(result)]
    if full:
        panels.append(path_3d({result.method: result}, "end-effector path"))
    return canvas.grid(panels, columns=3 if full else 2, caption=title)


def write_figures(results: dict[tuple[int, str], RunResult], robust: RunResult, out: Path) -> list[Path]:
    figures = {
        "fig_5_1_task1_laser.png": run_figure(results[1, "laser"], "Fig. 5-1 analogue: task 1, IBVS with laser", False),
        "fig_5_2_task2_laser.png": run_figure(results[2, "laser"], "Fig. 5-2 analogue: task 2, IBVS with laser", True),
        "fig_5_3_task3_laser.png": run_figure(results[3, "laser"], "Fig. 5-3 analogue: task 3, IBVS with laser", True),
        "fig_5_4_task4_laser.png": canvas.grid(
            [image_trajectory(results[4, "laser"], "image trajectory")], 1, "Fig. 5-4 analogue: task 4, IBVS with laser"
        ),
        "fig_5_5_robustness_task2.png": run_figure(robust, "Fig. 5-5 analogue: robustness test on task 2", True),
        "fig_5_6_task2_paths.png": path_3d(
            {method: results[2, method] for method in METHODS}, "Fig. 5-6 analogue: end-effector paths, task 2"
        ),
        "fig_5_7_task2_pbvs_image.png": image_trajectory(results[2, "pbvs"], "Fig. 5-7 analogue: task 2, PBVS"),
        "fig_5_8_task3_paths.png": path_3d(
            {method: results[3, method] for method in ("laser", "2.5d")}, "Fig. 5-8 analogue: end-effector paths, task 3"
        ),
    }
    return [canvas.write_png(out / name, image) for name, image in figures.items()]


# -- report --------------------------------------------------------------------------------
#
# Every sentence that says what a result means is built from that result: a snapshot
# that changes changes its report with it.

PATH_TOLERANCE = 0.10  # a path further than this from Table 5-4's gets its own line


def _path_cell(summary: dict[str, Any]) -> str:
    if summary["converged"]:
        return f"{summary['path_length_m']:.3f}"
    return f"failure ({summary['failure']})"


def _thesis_cell(task: int, method: str) -> str:
    if method not in THESIS_PATH_LENGTH_M[task]:
        return "n/a"
    value = THESIS_PATH_LENGTH_M[task][method]
    return "failure" if value is None else f"{value:.3f}"


def _join(words: list[str]) -> str:
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " and " + words[-1]


def _stages(summary: dict[str, Any]) -> str:
    return ", ".join(f"{stage['stage']} x{stage['iterations']}" for stage in summary["stages"])


def _failed(method: str, summary: dict[str, Any]) -> str:
    plural = "s" if summary["iterations"] != 1 else ""
    return f"{method} fails after {summary['iterations']} iteration{plural} ({summary['failure']}: {summary['reason']})"


def task_outcome(task: int, runs: dict[str, dict[str, Any]]) -> str:
    """Which methods converge on a task and in how many iterations, which fail, how and when."""
    summaries = {method: runs[f"{task}/{method}"] for method in METHODS}
    converged = [method for method, s in summaries.items() if s["converged"]]
    parts = []
    if converged:
        verb = "converges" if len(converged) == 1 else "converge"
        iterations = _join([str(summaries[method]["iterations"]) for method in converged])
        parts.append(f"{_join(converged)} {verb} ({iterations} iterations)")
    parts += [_failed(method, s) for method, s in summaries.items() if not s["converged"]]
    return f"Task {task} ({TASKS[task].description}): " + "; ".join(parts) + "."


def path_off_thesis(task: int, method: str, summary: dict[str, Any]) -> str | None:
    """The line for a converged path more than PATH_TOLERANCE from Table 5-4's, else None.

    Task 1's laser path is 0 in the thesis (a turn in place), where no ratio exists: there a
    path that is not 0 at the table's millimetre resolution gets the line.
    """
    thesis = THESIS_PATH_LENGTH_M[task].get(method)
    if thesis is None or not summary["converged"]:
        return None
    path = summary["path_length_m"]
    head = f"Task {task}, {method}: path {path:.3f} m against the thesis's {thesis:.3f} m"
    if thesis == 0.0:
        return f"{head} (a turn in place)." if round(path, 3) != 0.0 else None
    deviation = (path - thesis) / thesis
    if abs(deviation) <= PATH_TOLERANCE:
        return None
    return f"{head}, {abs(deviation):.1%} {'longer' if deviation > 0 else 'shorter'}."


def differences(runs: dict[str, dict[str, Any]], robust: dict[str, Any]) -> list[str]:
    """Where the runs and the thesis part: outcomes, paths beyond PATH_TOLERANCE, the robustness test."""
    notes = []
    if not robust["converged"]:
        notes.append(
            f"Robustness test: the thesis's task 2 converges under the errors of Table 5-3; here the laser "
            f"method stops after {robust['iterations']} iterations ({robust['failure']}: {robust['reason']}), "
            f"after stages {_stages(robust)}."
        )
    for task in TASKS:
        for method in ("laser", "2.5d", "ibvs"):
            s, thesis = runs[f"{task}/{method}"], THESIS_PATH_LENGTH_M[task][method]
            if (thesis is None) == s["converged"]:
                what = "converges" if s["converged"] else f"fails ({s['failure']}: {s['reason']})"
                notes.append(
                    f"Task {task}, {method}: the thesis reports {'a failure' if thesis is None else 'success'}, here it {what}."
                )
            off = path_off_thesis(task, method, s)
            if off:
                notes.append(off)
    pbvs = runs["2/pbvs"]
    if pbvs["converged"]:
        notes.append(
            f"Task 2, PBVS: the thesis reports that the corners leave the image (Fig. 5-7); here they stay in "
            f"it and PBVS converges in {pbvs['iterations']} iterations, along a path of "
            f"{pbvs['path_length_m']:.3f} m for a straight line of {pbvs['straight_line_m']:.3f} m."
        )
    return notes or [f"None: every outcome is the thesis's and every path within {PATH_TOLERANCE:.0%} of the thesis's."]


def robustness_outcome(robust: dict[str, Any], nominal: dict[str, Any]) -> str:
    """How the robustness run ended, beside task 2's run without the errors."""
    if not robust["converged"]:
        return (
            f"Under the errors of Table 5-3 the laser method stops after {robust['iterations']} iterations "
            f"({_stages(robust)}): {robust['failure']}, {robust['reason']}. The thesis's run converges."
        )
    change = (robust["path_length_m"] - nominal["path_length_m"]) / nominal["path_length_m"]
    return (
        f"Under the errors of Table 5-3 the laser method converges, as in the thesis, after {robust['iterations']} "
        f"iterations ({_stages(robust)}) where task 2 without them takes {nominal['iterations']}; its path is "
        f"{robust['path_length_m']:.3f} m against {nominal['path_length_m']:.3f} m ({change:+.1%})."
    )


def montecarlo_outcome(montecarlo: dict[str, dict[str, Any]]) -> str:
    """The methods by success rate, each with its most common failure."""
    ranked = sorted(montecarlo.items(), key=lambda item: item[1]["success_rate"], reverse=True)
    parts = []
    for method, m in ranked:
        part = f"{method} {m['success_rate']:.1%}"
        if m["failures"]:
            failure, count = max(m["failures"].items(), key=lambda item: item[1])
            part += f" (most common failure {failure}: {count} of {m['n']})"
        parts.append(part)
    return "Success rates, highest first: " + "; ".join(parts) + "."


def _header(summaries: dict[str, Any]) -> list[str]:
    made = summaries["provenance"]
    return [
        "# vservo: the simulation study of chapter 5",
        "",
        f"Made by `{made['command']}` from commit `{made['commit']}` on {made['date']}, with the cell "
        f"{made['cell']} (sha256 `{made['cell_sha256']}`). results.json holds the same numbers and this record.",
        "",
        f"Velocity control with dt = {summaries['dt_s']} s, every gain 1, final threshold 1 px, f0 = f0^l = 10 px. "
        "Path lengths are of the true end effector.",
    ]


def report_markdown(summaries: dict[str, Any]) -> str:
    runs = summaries["runs"]
    lines = _header(summaries) + [
        "",
        "## Table 5-4 analogue: length of the end-effector path (m)",
        "",
        "| task | " + " | ".join(f"{m} (vservo) | {m} (thesis)" for m in METHODS) + " |",
        "|---|" + "---|---|" * len(METHODS),
    ]
    for task in TASKS:
        cells = []
        for method in METHODS:
            cells += [_path_cell(runs[f"{task}/{method}"]), _thesis_cell(task, method)]
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    lines += ["", "PBVS has no column in Table 5-4; the thesis reports that it loses the features in task 2 (Fig. 5-7).", ""]
    lines += [f"- {task_outcome(task, runs)}" for task in TASKS]
    lines += [""]

    lines += [
        "## Every run",
        "",
        "| task | method | converged | failure | iterations | final error (px) | "
        "path (m) | straight line (m) | final pose error (mm, deg) | stages |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, s in runs.items():
        task, method = key.split("/")
        pose = s["final_pose_error"]
        stages = ", ".join(f"{st['stage']}x{st['iterations']}" for st in s["stages"])
        lines.append(
            f"| {task} | {method} | {s['converged']} | {s['failure'] or ''} | {s['iterations']} | {s['final_error_px']} | "
            f"{s['path_length_m']:.3f} | {s['straight_line_m']:.3f} | {pose['translation_m'] * 1000:.2f}, "
            f"{np.degrees(pose['rotation_rad']):.2f} | {stages} |"
        )

    robust = summaries["robustness"]
    lines += [
        "",
        "## Robustness test (Table 5-3, task 2, laser method)",
        "",
        f"Converged: {robust['converged']} ({robust['reason']}); path {robust['path_length_m']:.3f} m, "
        f"final error {robust['final_error_px']} px, final pose error "
        f"{robust['final_pose_error']['translation_m'] * 1000:.2f} mm / "
        f"{np.degrees(robust['final_pose_error']['rotation_rad']):.2f} deg.",
        "",
        robustness_outcome(robust, runs["2/laser"]),
        "",
        "## Desired features taught in simulation beside Table 5-2 (corrected sets)",
        "",
        "The corners are numbered from the corner where the object frame sits, so the order may be a cyclic "
        "shift of the thesis's; the sets are compared as sets.",
        "",
    ]
    for task in TASKS:
        taught = np.array(summaries["desired_features_px"][str(task)])
        thesis = THESIS_DESIRED_FEATURES_PX[2 if task in (1, 3) else 1]
        lines.append(
            f"- task {task}: taught {np.round(taught, 1).tolist()}, thesis {thesis.astype(int).tolist()}, "
            f"largest distance between the sets {distance_to_thesis_set(taught, thesis):.1f} px"
        )

    montecarlo = summaries.get("montecarlo")
    if montecarlo:
        first = next(iter(montecarlo.values()))
        draws = first["draws_per_sample"]
        reach = (
            f"On average {draws} poses that passed the view checks were drawn for each one the arm could reach: "
            "the arm's reach filters the distribution."
            if draws > 1
            else "The arm could reach every pose that passed the view checks."
            if first.get("arm", Arm.UPJ) == Arm.UPJ
            else "No arm carries the camera (a free camera): every pose that passed the view checks is kept."
        )
        lines += [
            "",
            f"## Monte Carlo: {first['n']} random initial poses, seed {first['seed']}",
            "",
            f"{first['distribution']}. {reach} Every method meets the same poses.",
            "",
            "| method | success rate | path median (m) | path p95 (m) | iterations median | iterations p95 | failures |",
            "|---|---|---|---|---|---|---|",
        ]
        for method, m in montecarlo.items():
            lines.append(
                f"| {method} | {m['success_rate']:.1%} | {m['path_length_m']['median']} | {m['path_length_m']['p95']} | "
                f"{m['iterations']['median']} | {m['iterations']['p95']} | {m['failures']} |"
            )
        lines += ["", montecarlo_outcome(montecarlo)]

    if "calibration_errors" in summaries:  # a snapshot from before the robust law has none
        lines += calibration_errors.report_lines(summaries["calibration_errors"])

    notes = differences(runs, robust)
    lines += ["", "## Where the results differ from the thesis", ""] + [f"- {note}" for note in notes]
    lines += ["", "## Figures", ""] + [f"- `{name}`" for name in summaries["figures"]]
    return "\n".join(lines) + "\n"


# -- the study -----------------------------------------------------------------------------


@dataclass(frozen=True)
class StudyRuns:
    """Every task with every method, and the robustness test: what a snapshot re-runs."""

    results: dict[tuple[int, str], RunResult]
    robust: RunResult

    def summaries(self) -> dict[str, Any]:
        """The runs' part of results.json."""
        return {
            "runs": {f"{task}/{method}": result.summary() for (task, method), result in self.results.items()},
            "robustness": self.robust.summary(),
            "desired_features_px": {str(task): self.results[task, "laser"].desired.corners_px.tolist() for task in TASKS},
        }


def study_cells(data: dict[str, Any], source: str) -> tuple[CellConfig, CellConfig]:
    """The cell of the four tasks and the robustness test's (Table 5-3's errors), from cell-file data."""
    return parse_cell(data, source), parse_cell(robustness_cell(data), f"{source} with the errors of Table 5-3")


def run_study(config: CellConfig, robust_config: CellConfig, dt_s: float, arm: Arm = Arm.UPJ) -> StudyRuns:
    """The four tasks with every method and the robustness test, each run once (seeded,
    deterministic), the camera on the arm or, with ``arm`` none, free."""
    progress = Progress(len(TASKS) * len(METHODS) + 1, "reproduce")
    results: dict[tuple[int, str], RunResult] = {}
    for task_number, task in TASKS.items():
        for method in METHODS:
            results[task_number, method] = run_task(config, task, RunSettings(method=method, dt_s=dt_s, arm=arm))
            progress.advance(f"task {task_number} {method}")
    robust = run_task(robust_config, ROBUSTNESS_TASK, RunSettings(method="laser", dt_s=dt_s, arm=arm))
    progress.advance("robustness")
    progress.close()
    return StudyRuns(results, robust)


def reproduce(
    out: Path, cell_path: str | Path | None = None, montecarlo_n: int = 500, seed: int = 0, dt_s: float = 0.1, arm: Arm = Arm.UPJ
) -> dict[str, Any]:
    """Run the whole study, write results.json, report.md and the figures into ``out``.

    The provenance is taken first, before anything in ``out`` changes: regenerating the
    committed snapshot must not mark its own commit dirty.
    """
    cell_bytes, source = read_cell_bytes(cell_path)
    made = provenance.record(source, cell_bytes, provenance.reproduce_command(out, cell_path, montecarlo_n, seed, arm))
    config, robust_config = study_cells(*read_cell_data(cell_path))
    study = run_study(config, robust_config, dt_s, arm)

    summaries: dict[str, Any] = {"provenance": made.as_dict(), "dt_s": dt_s, **study.summaries()}
    if montecarlo_n > 0:
        summaries["montecarlo"] = {}
        for method in MONTECARLO_METHODS:
            bar = Progress(montecarlo_n, f"montecarlo {method}")
            summaries["montecarlo"][method] = run_montecarlo(
                config,
                RunSettings(method=method, dt_s=dt_s, arm=arm),
                montecarlo_n,
                seed,
                on_sample=partial(_advance, bar),
            )
            bar.close()

    summaries["calibration_errors"] = calibration_errors.run_calibration_errors(cell_path, montecarlo_n, seed, dt_s, arm)

    out.mkdir(parents=True, exist_ok=True)
    summaries["figures"] = [path.name for path in write_figures(study.results, study.robust, out)]
    (out / "results.json").write_text(json.dumps(summaries, indent=2) + "\n")
    (out / "report.md").write_text(report_markdown(summaries))
    return summaries


def _advance(bar: Progress, outcome: SampleOutcome) -> None:
    """One Monte Carlo sample done: the bar notes "ok" or why it failed."""
    bar.advance("ok" if outcome.converged else str(outcome.failure))
