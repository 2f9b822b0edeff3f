"""The study's commands: ``vservo demo``, ``simulate``, ``montecarlo``, ``reproduce``, ``replay``,
and the vision, stream and JRC link benches (``vservo bench vision``, ``stream``, ``jrc``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.cell.config import load_cell
from vservo.core.geometry.spatial import Matrix
from vservo.core.servo.methods import LaserLaw
from vservo.core.sim import Arm
from vservo.core.terminal.command_line import BenchCommand, bounded, fraction, positive, print_result, seed


def _cmd_demo(args: argparse.Namespace) -> int:
    from vservo.core.study.demo import run_demo

    report = run_demo(load_cell(args.cell), seed=args.seed)
    print(json.dumps(report) if args.json else report_text(report))
    return 0


def report_text(report: dict[str, Any]) -> str:
    lines = []
    for step in report["steps"]:
        lines.append(f"- {step['what']}")
        for key, value in step.items():
            if key != "what":
                lines.append(f"    {key}: {value}")
    return "\n".join([report["title"], *lines])


def _pose_argument(text: str) -> Matrix:
    """X,Y,Z,phi,theta,psi in m and rad (Table 5-1's convention)."""
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        values = np.array([])
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"expected 6 comma-separated numbers X,Y,Z,phi,theta,psi (m, rad), got {text!r}")
    return values


def _cmd_simulate(args: argparse.Namespace) -> int:
    from vservo.core.study.simulate import simulate

    result = simulate(
        cell_path=args.cell,
        task_number=args.task,
        method=args.method,
        robust=_reading(args),
        seed=args.seed,
        initial=args.initial,
        desired=args.desired,
        gain=args.gain,
        max_iterations=args.max_iterations,
        dt_s=args.dt,
        features=args.features,
        record_to=args.record,
        arm=Arm(args.arm),
        truth=args.truth,
        laser_law=LaserLaw(args.law),
    )
    summary = result.summary()
    if args.json:
        print(json.dumps(summary))
    else:
        verdict = "converged" if summary["converged"] else f"failed: {summary['failure']} ({summary['reason']})"
        print(f"{summary['task']}, {summary['method']}: {verdict} after {summary['iterations']} iterations")
        print(
            f"  final error {summary['final_error_px']} px, end-effector path {summary['path_length_m']:.3f} m "
            f"(straight line {summary['straight_line_m']:.3f} m)"
        )
        pose = summary["final_pose_error"]
        print(f"  final pose error {pose['translation_m'] * 1000:.3f} mm, {np.degrees(pose['rotation_rad']):.3f} deg")
        print("  stages: " + ", ".join(f"{s['stage']} x{s['iterations']}" for s in summary["stages"]))
    return 0


def _cmd_montecarlo(args: argparse.Namespace) -> int:
    from vservo.core.study.montecarlo import run_montecarlo
    from vservo.core.study.run import RunSettings
    from vservo.core.study.simulate import study_cell
    from vservo.core.terminal.progress import Progress

    config = study_cell(args.cell, _reading(args), args.truth)
    progress = Progress(args.n, f"montecarlo {args.method}")
    summary = run_montecarlo(
        config,
        RunSettings(method=args.method, arm=Arm(args.arm), laser_law=LaserLaw(args.law)),
        args.n,
        args.seed,
        args.processes,
        on_sample=lambda outcome: progress.advance("ok" if outcome.converged else str(outcome.failure)),
    )
    progress.close()
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"{args.method}: {summary['success_rate']:.1%} of {args.n} converged; failures {summary['failures']}")
        print(f"  path length (m) median {summary['path_length_m']['median']}, p95 {summary['path_length_m']['p95']}")
        print(f"  iterations median {summary['iterations']['median']}, p95 {summary['iterations']['p95']}")
        print(f"  {summary['distribution']}")
    return 0


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from vservo.core.study.report import reproduce

    summaries = reproduce(Path(args.out), args.cell, args.montecarlo, args.seed, arm=Arm(args.arm))
    print(f"wrote {args.out}/results.json, {args.out}/report.md and {len(summaries['figures'])} figures")
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from vservo.core.perception.recording import RecordingError
    from vservo.core.study.replay import replay

    try:
        result = replay(args.folder, args.cell)
    except RecordingError as exc:
        raise ValueError(str(exc)) from None
    print_result(result, args.json)
    return 0


def _cmd_bench_vision(args: argparse.Namespace) -> int:
    from vservo.core.study.vision_bench import bench_vision

    print_result(bench_vision(load_cell(args.cell), seed=args.seed), args.json)
    return 0


def _cmd_bench_stream(args: argparse.Namespace) -> int:
    from vservo.core.study.stream_bench import bench_stream

    print_result(bench_stream(load_cell(args.cell), views=args.views, quality=args.quality, seed=args.seed), args.json)
    return 0


def _cmd_bench_jrc(args: argparse.Namespace) -> int:
    config = load_cell(args.cell)
    if args.soak:
        from vservo.core.study.link_soak import run_soak
        from vservo.core.terminal.progress import Progress

        progress = Progress(args.soak, "soak")
        result = run_soak(
            config, args.soak, args.fault_rate, args.seed, args.time_scale, args.timer_a, args.timer_b, on_move=progress.advance
        )
        progress.close()
    else:
        from vservo.core.study.link_bench import bench_jrc

        result = bench_jrc(config, samples=args.samples, seed=args.seed)
    print_result(result, args.json)
    return 0


def _add_arm_option(command: argparse.ArgumentParser) -> None:
    command.add_argument(
        "--arm",
        choices=tuple(arm.value for arm in Arm),
        default=Arm.UPJ.value,
        help="what carries the camera: upj, the cell's arm (default), or none, a free camera that "
        "moves as the control law commands (no joints, limits or workspace)",
    )


def _reading(args: argparse.Namespace) -> Any:
    """The Table 5-3 reading of ``--robust``, None without it."""
    from vservo.core.study.tasks import Table53Reading

    return None if args.robust is None else Table53Reading(args.robust)


def _add_truth_options(command: argparse.ArgumentParser) -> None:
    """--law, --robust and --truth: which laser law, and how the true cell differs from the model."""
    from vservo.core.study.tasks import Table53Reading

    command.add_argument(
        "--law",
        choices=tuple(law.value for law in LaserLaw),
        default=LaserLaw.THESIS.value,
        help="the laser method's law: thesis (section 4.4, the study's reproduction; default) or robust "
        "(robust to calibration error, docs/thesis-notes.md)",
    )

    command.add_argument(
        "--robust",
        nargs="?",
        const=Table53Reading.REPRODUCTION.value,
        choices=tuple(reading.value for reading in Table53Reading),
        help="the calibration errors of Table 5-3 (model and true cell both), read as the reproduction reads "
        "them (reproduction, the default: the law keeps the actual values) or the other way (other: the law "
        "applies the erroneous ones)",
    )
    command.add_argument(
        "--truth",
        metavar="FILE",
        help="a cell file whose [simulation.truth.*] tables say how the true cell differs from the --cell "
        "file's model (static/truths/ holds some); the control law sees only the model",
    )


def add_study_commands(commands: argparse._SubParsersAction) -> None:
    """Register ``vservo demo``, ``simulate``, ``montecarlo``, ``reproduce`` and ``replay``."""
    demo = commands.add_parser("demo", help="a tour of the simulated cell: arm, camera, laser, JRC-style steps")
    demo.add_argument("--seed", type=seed, default=None, help="seed of the simulated cell (default: the cell's)")
    demo.add_argument("--json", action="store_true", help="one JSON object")
    demo.set_defaults(run=_cmd_demo)

    simulate = commands.add_parser(
        "simulate",
        help="one visual servo run of the thesis's simulation study (Tables 5-1 .. 5-4)",
        description="Teach the desired image, start at the initial pose and servo. Poses are the object "
        "in the camera frame, X,Y,Z,phi,theta,psi in m and rad (Table 5-1); write negative values as "
        "--initial=-0.12,...",
    )
    simulate.add_argument("--task", type=int, choices=(1, 2, 3, 4), help="task of Table 5-1 (default 2)")
    simulate.add_argument("--method", choices=("laser", "ibvs", "pbvs", "2.5d"), default="laser")
    _add_truth_options(simulate)
    simulate.add_argument("--seed", type=seed, default=None, help="seed of the simulated cell")
    simulate.add_argument("--initial", type=_pose_argument, help="initial cMo, replaces the task's")
    simulate.add_argument("--desired", type=_pose_argument, help="desired cMo, replaces the task's")
    simulate.add_argument("--gain", type=positive(float), default=1.0, help="gain of every control law (default 1)")
    simulate.add_argument("--max-iterations", type=positive(int), default=3000)
    simulate.add_argument("--dt", type=positive(float), default=0.1, help="control period in s (default 0.1)")
    simulate.add_argument(
        "--features",
        choices=("projected", "rendered"),
        default="projected",
        help="projected points, or detections in the simulated camera's images",
    )
    simulate.add_argument("--record", metavar="FOLDER", help="record the run (frames, features, commands, stages)")
    _add_arm_option(simulate)
    simulate.add_argument("--json", action="store_true", help="one JSON object")
    simulate.set_defaults(run=_cmd_simulate)

    montecarlo = commands.add_parser("montecarlo", help="success rate of a method from random initial poses, on all cores")
    montecarlo.add_argument("--method", choices=("laser", "ibvs", "pbvs", "2.5d"), default="laser")
    montecarlo.add_argument("--n", type=positive(int), default=100, help="number of initial poses (default 100)")
    montecarlo.add_argument("--seed", type=seed, default=0, help="seed of the initial poses (default 0)")
    montecarlo.add_argument("--processes", type=positive(int), default=None, help="worker processes (default: all cores)")
    _add_truth_options(montecarlo)
    _add_arm_option(montecarlo)
    montecarlo.add_argument("--json", action="store_true", help="one JSON object")
    montecarlo.set_defaults(run=_cmd_montecarlo)

    reproduce = commands.add_parser("reproduce", help="every task and method of chapter 5: results.json, report.md and figures")
    reproduce.add_argument("--out", required=True, metavar="DIR", help="folder for the results (created)")
    reproduce.add_argument(
        "--montecarlo",
        type=bounded(int, 0, 100_000),
        default=500,
        metavar="N",
        help="random initial poses per method for the Monte Carlo table (default 500, 0 skips it)",
    )
    reproduce.add_argument("--seed", type=seed, default=0, help="seed of the Monte Carlo poses (default 0)")
    _add_arm_option(reproduce)
    reproduce.set_defaults(run=_cmd_reproduce)

    replay_command = commands.add_parser(
        "replay", help="play a recorded run back through the vision and the control law and compare"
    )
    replay_command.add_argument("folder", help="a recording (vservo simulate --record FOLDER)")
    replay_command.add_argument("--json", action="store_true", help="one JSON object")
    replay_command.set_defaults(run=_cmd_replay)


def add_vision_bench(bench: BenchCommand) -> None:
    """Register ``vservo bench vision``."""
    bench.add("vision", "render, detection and loop times, detection accuracy", _cmd_bench_vision)


def add_stream_bench(bench: BenchCommand) -> None:
    """Register ``vservo bench stream``."""
    stream = bench.add("stream", "corner and spot differences and latency of frames through an MJPEG stream", _cmd_bench_stream)
    stream.add_argument("--views", type=positive(int), default=24, help="stream: views of the cell (default 24)")
    stream.add_argument("--quality", type=_jpeg_quality, default=100, help="stream: JPEG quality 0..100 (default 100)")


def add_locate_bench(bench: BenchCommand) -> None:
    """Register ``vservo bench locate``."""
    locate = bench.add(
        "locate",
        "a locating job on parts put anywhere in its survey view (a commissioned cell with a fixture)",
        _cmd_bench_locate,
    )
    locate.add_argument("--job", default="demo", help="locate: the taught job to run as a locating job (default demo)")
    locate.add_argument("--placements", type=positive(int), default=40, help="locate: random placements of the part (default 40)")
    locate.add_argument(
        "--data", metavar="DIR", help="locate: data folder for the jobs and runs (default: a new temporary folder)"
    )


def _cmd_bench_locate(args: argparse.Namespace) -> int:
    import tempfile

    from vservo.core.study.locate_bench import bench_locate

    data = Path(args.data) if args.data else Path(tempfile.mkdtemp(prefix="vservo-bench-locate-"))
    result = bench_locate(load_cell(args.cell), args.job, args.placements, args.seed or 0, data)
    print_result(result, args.json)
    return 0 if result["placed_share"] >= 0.95 else 1


def _jpeg_quality(text: str) -> int:
    try:
        quality = int(text)
    except ValueError:
        quality = -1
    if not 0 <= quality <= 100:
        raise argparse.ArgumentTypeError(f"a JPEG quality is an integer in 0..100, got {text!r}")
    return quality


def add_jrc_bench(bench: BenchCommand) -> None:
    """Register ``vservo bench jrc`` (with its soak)."""
    jrc = bench.add(
        "jrc",
        "RPOSC and MOVL round trips over a pty against the wire time, or with --soak the link under injected faults",
        _cmd_bench_jrc,
    )
    jrc.add_argument("--samples", type=positive(int), default=50, help="jrc: round trips per command (default 50)")
    jrc.add_argument("--soak", type=positive(int), metavar="MOVES", help="jrc: soak the link with MOVES incremental moves")
    jrc.add_argument("--fault-rate", type=fraction, default=0.05, help="soak: faults per exchange (default 0.05)")
    jrc.add_argument("--time-scale", type=positive(float), default=50.0, help="soak: emulator speed-up (default 50)")
    jrc.add_argument("--timer-a", type=positive(float), default=0.1, help="soak: timer A in s (default 0.1)")
    jrc.add_argument("--timer-b", type=positive(float), default=1.0, help="soak: timer B in s (default 1)")
