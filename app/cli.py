"""The ``vservo`` command line."""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vservo.core.calibration.cli import add_calibrate_command
from vservo.core.cell.config import ROBOT_BACKENDS, CellConfig, ConfigError, load_cell
from vservo.core.cell.kinematics import ArmKinematics, KinematicsError
from vservo.core.geometry.spatial import pose_from_matrix, pose_to_mm_deg
from vservo.core.production.storage import StoreError, default_data_dir
from vservo.core.robot.backend import RobotError
from vservo.robot_models.loader import load_arm


def _round(values: Any, digits: int = 4) -> Any:
    return (np.round(np.asarray(values, dtype=float), digits) + 0.0).tolist()  # + 0.0: no "-0.0"


def cell_info(config: CellConfig) -> dict[str, Any]:
    """The loaded robot, camera and laser, as one JSON-ready dict (``vservo info``)."""
    arm = ArmKinematics(load_arm(config.arm), config.nominal.mount)
    intrinsics = config.nominal.camera.intrinsics
    laser = config.nominal.laser
    origin, direction = laser.origin_c, laser.direction_c
    # The angle alpha of Fig. 4-2: between the beam and the baseline from laser to camera.
    alpha = float(np.degrees(np.arccos(np.clip(direction @ (-origin / np.linalg.norm(origin)), -1.0, 1.0))))
    return {
        "cell": config.source,
        "robot": {
            "name": arm.name,
            "dof": arm.dof,
            "joint_limits_deg": _round(np.degrees(np.stack([arm.lower, arm.upper], axis=1)), 3),
            "frames": list(arm.frame_names),
            "home_joints_deg": _round(np.degrees(config.home_q), 3),
            "home_flange_pose_mm_deg": _round(pose_to_mm_deg(pose_from_matrix(arm.fk(config.home_q))), 3),
        },
        "camera": {
            "fx_px": round(intrinsics.fx, 4),
            "fy_px": round(intrinsics.fy, 4),
            "principal_point_px": [intrinsics.u0, intrinsics.v0],
            "image_size_px": [intrinsics.width, intrinsics.height],
            "distortion_k1_k2_p1_p2_k3": _round(config.nominal.camera.distortion.as_opencv(), 8),
            "eMc_mm_deg": _round(pose_to_mm_deg(pose_from_matrix(config.nominal.eMc)), 3),
        },
        "laser": {
            "cMl_mm_deg": _round(pose_to_mm_deg(pose_from_matrix(laser.cMl)), 3),
            "baseline_mm": round(float(np.linalg.norm(origin)) * 1000.0, 3),
            "alpha_deg": round(alpha, 3),
            "direction_c": _round(direction, 6),
        },
        "link": {
            "backend": config.robot_backend,
            **vars(config.jrc),
        },
        "safety": {
            "workspace_min_mm": _round(config.safety.workspace_min_m * 1000.0, 3),
            "workspace_max_mm": _round(config.safety.workspace_max_m * 1000.0, 3),
            "max_step_mm": round(config.safety.max_step_m * 1000.0, 3),
            "max_step_deg": round(float(np.degrees(config.safety.max_step_rad)), 3),
            "max_speed_mm_s": round(config.safety.max_speed_m_s * 1000.0, 3),
            "joint_margin_deg": round(float(np.degrees(config.safety.joint_margin_rad)), 3),
            "watchdog_s": config.safety.watchdog_s,
        },
        "motion": {
            "mode": config.motion.mode,
            "divide_factor": config.motion.divide_factor,
            "sampling_period_s": config.motion.sampling_period_s,
            "speed_mm_s": config.motion.speed_m_s * 1000.0,
        },
    }


def _print(result: dict[str, Any], as_json: bool) -> None:
    """One JSON object, or one line per key (a nested table indented under its name)."""
    if as_json:
        print(json.dumps(result))
        return
    for key, value in result.items():
        if isinstance(value, dict):
            print(f"{key}:")
            for inner, inner_value in value.items():
                print(f"  {inner}: {inner_value}")
        else:
            print(f"{key}: {value}")


def _cmd_info(args: argparse.Namespace) -> int:
    _print(cell_info(load_cell(args.cell)), args.json)
    return 0


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


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, as every vservo error is."""

    def error(self, message: str) -> None:
        self.exit(2, f"{self.prog}: error: {message}\n")


def _pose_argument(text: str) -> np.ndarray:
    """X,Y,Z,phi,theta,psi in m and rad (Table 5-1's convention)."""
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        values = np.array([])
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"expected 6 comma-separated numbers X,Y,Z,phi,theta,psi (m, rad), got {text!r}")
    return values


def _positive(kind: type) -> Any:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}, got {text!r}") from None
        if not value > 0:
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}, got {text!r}")
        return value

    return parse


def _fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number from 0 to 1, got {text!r}")
    return value


def _cmd_simulate(args: argparse.Namespace) -> int:
    from vservo.core.study.simulate import simulate

    result = simulate(
        cell_path=args.cell,
        task_number=args.task,
        method=args.method,
        robust=args.robust,
        seed=args.seed,
        initial=args.initial,
        desired=args.desired,
        gain=args.gain,
        max_iterations=args.max_iterations,
        dt_s=args.dt,
        features=args.features,
        record_to=args.record,
    )
    summary = result.summary()
    if args.json:
        print(json.dumps(summary))
    else:
        verdict = "converged" if summary["converged"] else f"failed: {summary['failure']} ({summary['reason']})"
        print(f"{summary['task']}, {summary['method']}: {verdict} after {summary['iterations']} iterations")
        print(f"  final error {summary['final_error_px']} px, end-effector path {summary['path_length_m']:.3f} m "
              f"(straight line {summary['straight_line_m']:.3f} m)")
        pose = summary["final_pose_error"]
        print(f"  final pose error {pose['translation_m'] * 1000:.3f} mm, {np.degrees(pose['rotation_rad']):.3f} deg")
        print("  stages: " + ", ".join(f"{s['stage']} x{s['iterations']}" for s in summary["stages"]))
    return 0


def _cmd_montecarlo(args: argparse.Namespace) -> int:
    from vservo.core.progress import Progress
    from vservo.core.study.montecarlo import run_montecarlo
    from vservo.core.study.run import RunSettings

    config = load_cell(args.cell)
    progress = Progress(args.n, f"montecarlo {args.method}")
    summary = run_montecarlo(
        config, RunSettings(method=args.method), args.n, args.seed, args.processes,
        on_sample=lambda outcome: progress.advance("ok" if outcome.converged else outcome.failure),
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

    summaries = reproduce(Path(args.out), args.cell, args.montecarlo, args.seed)
    print(f"wrote {args.out}/results.json, {args.out}/report.md and {len(summaries['figures'])} figures")
    return 0


def _cmd_detect(args: argparse.Namespace) -> int:
    from vservo.core.cell.scene import Cube
    from vservo.core.perception.camera_source import CameraSourceError, read_mono8
    from vservo.core.perception.vision.pipeline import ImageFeatureExtractor, front_winding

    try:
        image = read_mono8(args.image)
    except CameraSourceError as exc:
        raise ValueError(str(exc)) from None
    config = load_cell(args.cell)
    extractor = ImageFeatureExtractor(
        config.nominal.camera, config.nominal.laser, front_winding(Cube(np.eye(4)).corners_o),
        spot_threshold=args.spot_threshold, region_threshold=args.region_threshold,
    )
    features, report = extractor.extract(image)
    result = {"image": args.image, "size": [image.shape[1], image.shape[0]], **report.as_dict(),
              "laser_depth_mm": None if np.isnan(features.laser_depth_m) else round(features.laser_depth_m * 1000.0, 3)}
    _print(result, args.json)
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from vservo.core.perception.recording import RecordingError
    from vservo.core.study.replay import replay

    try:
        result = replay(args.folder, args.cell)
    except RecordingError as exc:
        raise ValueError(str(exc)) from None
    _print(result, args.json)
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    config = load_cell(args.cell)
    if args.what == "vision":
        from vservo.core.study.vision_bench import bench_vision

        result = bench_vision(config, seed=args.seed)
    elif args.what == "calibration":
        from vservo.core.calibration.bench import bench_calibration

        result = bench_calibration(config, seed=args.seed)
    elif args.what == "ui":
        from vservo.app.bench_ui import bench_ui
        from vservo.app.browser import ChromiumMissing

        try:
            result = bench_ui(config, seed=args.seed, runs=args.runs, cycle_period_s=args.cycle_period, cell=args.cell)
        except ChromiumMissing as exc:
            print(f"vservo bench: error: {exc}", file=sys.stderr)
            return 2
    elif args.soak:
        from vservo.core.progress import Progress
        from vservo.core.study.link_soak import run_soak

        progress = Progress(args.soak, "soak")
        result = run_soak(config, args.soak, args.fault_rate, args.seed, args.time_scale, args.timer_a, args.timer_b,
                          on_move=progress.advance)
        progress.close()
    else:
        from vservo.core.study.link_bench import bench_jrc

        result = bench_jrc(config, samples=args.samples, seed=args.seed)
    _print(result, args.json)
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from vservo.core.production.cell_controller import CellController, CommandRefused, run_job_once
    from vservo.core.production.rig import simulated_rig
    from vservo.core.production.storage import Store

    store = Store(args.data or default_data_dir())
    controller = CellController(simulated_rig(load_cell(args.cell), args.seed, args.backend), store, seed=args.seed or 0)
    try:
        summary = run_job_once(controller, args.job)
    except CommandRefused as exc:
        print(f"vservo run: error: {exc}", file=sys.stderr)
        return 2
    finally:
        controller.close()
        store.close()
    _print(summary, args.json)
    return 0 if summary["outcome"] == "placed" else 1


def _cmd_controller(args: argparse.Namespace) -> int:
    import signal

    from vservo.core.production.cell_controller import CellController
    from vservo.core.production.channel import KEY_ENVIRONMENT, ControllerServer
    from vservo.core.production.rig import simulated_rig
    from vservo.core.production.storage import Store

    key = os.environ.get(KEY_ENVIRONMENT, "")
    try:
        authkey = bytes.fromhex(key)
    except ValueError:
        authkey = b""
    if len(authkey) < 16:
        print(f"vservo controller: error: set {KEY_ENVIRONMENT} to the channel key (32+ hex digits); "
              "`vservo serve` does this for you", file=sys.stderr)
        return 2
    store = Store(args.data or default_data_dir())
    controller = CellController(simulated_rig(load_cell(args.cell), args.seed, args.backend), store,
                                seed=args.seed or 0, cycle_period_s=args.cycle_period)
    server = ControllerServer(controller, authkey, port=args.port)
    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.set())
    if args.exit_with_parent:
        threading.Thread(target=_stop_when_orphaned, args=(os.getppid(), stop), name="parent-watch", daemon=True).start()
    print(json.dumps({"controller": {"host": server.address[0], "port": server.address[1],
                                     "backend": controller.rig.robot.name}}), flush=True)
    stop.wait()
    server.close()
    controller.close()  # holds the robot if a run is under way
    store.close()
    return 0


def _stop_when_orphaned(parent_pid: int, stop: threading.Event, period_s: float = 0.5) -> None:
    """Set ``stop`` once this process's parent is no longer ``parent_pid``.

    A parent killed outright (SIGKILL, a crash) sends no signal; its children are handed
    to init, which changes their parent id. Polling it works for every way to die.
    """
    while not stop.wait(period_s):
        if os.getppid() != parent_pid:
            print(f"vservo controller: the process that started it ({parent_pid}) is gone: holding the robot "
                  "and stopping", file=sys.stderr, flush=True)
            stop.set()


def _cmd_jrc_emulator(args: argparse.Namespace) -> int:
    import signal

    from vservo.core.sim.jrc_emulator import FaultPlan, JrcEmulator
    from vservo.core.sim.plant import SimulatedCell

    config = load_cell(args.cell)
    emulator = JrcEmulator(SimulatedCell(config), config.jrc, FaultPlan(args.fault_rate, args.seed), args.time_scale,
                           pace=args.pace)
    if args.port:
        emulator.start_on_port(args.port)
    else:
        emulator.start_on_pty()
    line = config.jrc
    print(emulator.device, flush=True)
    print(f"JRC emulator on {emulator.device}: {line.baud} baud, {line.data_bits} data bits, {line.parity} parity, "
          f"{line.stop_bits} stop bit(s); time scale {args.time_scale:g}, faults {args.fault_rate:.0%}; "
          "Ctrl-C or SIGTERM stops it", file=sys.stderr, flush=True)
    stopped = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stopped.set())
    stopped.wait()
    emulator.stop()
    print(f"served {emulator.exchanges} exchanges, {len(emulator.executed)} moves; "
          f"faults injected {dict(emulator.faults.injected)}", file=sys.stderr)
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
    import logging

    from vservo.app.controller_process import ControllerStartError
    from vservo.app.roles import TOKEN_ENVIRONMENT, new_token
    from vservo.app.server import ServeOptions, serve

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    token = args.token or os.environ.get(TOKEN_ENVIRONMENT) or new_token()
    if not token.strip():
        print("vservo serve: error: --token: the operator token is empty", file=sys.stderr)
        return 2
    config = load_cell(args.cell)
    options = ServeOptions(backend=args.backend or config.robot_backend, host=args.host, port=args.port,
                           data=Path(args.data or default_data_dir()), seed=args.seed, token=token,
                           cycle_period_s=args.cycle_period, cell=args.cell)
    try:
        return serve(options, config, announce=lambda line: print(line, flush=True))
    except ControllerStartError as exc:
        print(f"vservo serve: error: {exc}", file=sys.stderr)
        return 2


BACKEND_HELP = ("the robot: sim drives the simulator directly, jrc through the JRC link to an emulated controller "
                "on a pseudo-terminal (default: the cell file's [robot] backend)")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="vservo",
        description="Vision-guided robotic assembly: a camera and a laser pointer on an industrial arm.",
    )
    parser.add_argument("--cell", metavar="FILE", help="cell configuration (TOML); default: the shipped cell")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=_Parser)

    info = commands.add_parser("info", help="print the loaded robot, camera and laser settings")
    info.add_argument("--json", action="store_true", help="one JSON object")
    info.set_defaults(run=_cmd_info)

    demo = commands.add_parser("demo", help="a tour of the simulated cell: arm, camera, laser, JRC-style steps")
    demo.add_argument("--seed", type=int, default=None, help="seed of the simulated cell (default: the cell's)")
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
    simulate.add_argument("--robust", action="store_true", help="the calibration errors of Table 5-3")
    simulate.add_argument("--seed", type=int, default=None, help="seed of the simulated cell")
    simulate.add_argument("--initial", type=_pose_argument, help="initial cMo, replaces the task's")
    simulate.add_argument("--desired", type=_pose_argument, help="desired cMo, replaces the task's")
    simulate.add_argument("--gain", type=_positive(float), default=1.0, help="gain of every control law (default 1)")
    simulate.add_argument("--max-iterations", type=_positive(int), default=3000)
    simulate.add_argument("--dt", type=_positive(float), default=0.1, help="control period in s (default 0.1)")
    simulate.add_argument("--features", choices=("projected", "rendered"), default="projected",
                          help="projected points, or detections in the simulated camera's images")
    simulate.add_argument("--record", metavar="FOLDER", help="record the run (frames, features, commands, stages)")
    simulate.add_argument("--json", action="store_true", help="one JSON object")
    simulate.set_defaults(run=_cmd_simulate)

    montecarlo = commands.add_parser(
        "montecarlo", help="success rate of a method from random initial poses, on all cores"
    )
    montecarlo.add_argument("--method", choices=("laser", "ibvs", "pbvs", "2.5d"), default="laser")
    montecarlo.add_argument("--n", type=_positive(int), default=100, help="number of initial poses (default 100)")
    montecarlo.add_argument("--seed", type=int, default=0, help="seed of the initial poses (default 0)")
    montecarlo.add_argument("--processes", type=_positive(int), default=None, help="worker processes (default: all cores)")
    montecarlo.add_argument("--json", action="store_true", help="one JSON object")
    montecarlo.set_defaults(run=_cmd_montecarlo)

    reproduce = commands.add_parser(
        "reproduce", help="every task and method of chapter 5: results.json, report.md and figures"
    )
    reproduce.add_argument("--out", required=True, metavar="DIR", help="folder for the results (created)")
    reproduce.add_argument("--montecarlo", type=int, default=500, metavar="N",
                           help="random initial poses per method for the Monte Carlo table (default 500, 0 skips it)")
    reproduce.add_argument("--seed", type=int, default=0, help="seed of the Monte Carlo poses (default 0)")
    reproduce.set_defaults(run=_cmd_reproduce)

    detect = commands.add_parser(
        "detect", help="the laser spot, the four corners and the object region found in one image file"
    )
    detect.add_argument("image", help="image file (8- or 16-bit, grey or colour)")
    detect.add_argument("--spot-threshold", type=int, default=250, help="fixed level of the laser spot (default 250)")
    detect.add_argument("--region-threshold", type=int, default=100, help="fixed level of the object region (default 100)")
    detect.add_argument("--json", action="store_true", help="one JSON object")
    detect.set_defaults(run=_cmd_detect)

    replay_command = commands.add_parser(
        "replay", help="play a recorded run back through the vision and the controller and compare"
    )
    replay_command.add_argument("folder", help="a recording (vservo simulate --record FOLDER)")
    replay_command.add_argument("--json", action="store_true", help="one JSON object")
    replay_command.set_defaults(run=_cmd_replay)

    run = commands.add_parser(
        "run", help="one headless assembly of a taught job on the simulated cell (exit 0 when placed)"
    )
    run.add_argument("--job", required=True, help="job name (the shipped 'demo' is always there)")
    run.add_argument("--data", metavar="DIR", help="data folder with the jobs and runs (default $VSERVO_DATA or "
                     "~/.local/share/vservo)")
    run.add_argument("--seed", type=int, default=None, help="seed of the simulated cell and of the part's arrival")
    run.add_argument("--backend", choices=ROBOT_BACKENDS, help=BACKEND_HELP)
    run.add_argument("--json", action="store_true", help="one JSON object")
    run.set_defaults(run=_cmd_run)

    controller = commands.add_parser(
        "controller", help="the controller process: owns the cell, serves the app over an authenticated local channel"
    )
    controller.add_argument("--port", type=int, default=0, help="TCP port on 127.0.0.1 (default: any free one)")
    controller.add_argument("--data", metavar="DIR", help="data folder (default $VSERVO_DATA or ~/.local/share/vservo)")
    controller.add_argument("--seed", type=int, default=None, help="seed of the simulated cell")
    controller.add_argument("--backend", choices=ROBOT_BACKENDS, help=BACKEND_HELP)
    controller.add_argument("--cycle-period", type=float, default=0.05, metavar="S",
                            help="shortest servo cycle in s, so a simulated run can be watched (default 0.05)")
    controller.add_argument("--exit-with-parent", action="store_true",
                            help="hold the robot and exit when the process that started this one is gone "
                                 "(`vservo serve` sets it: a killed app leaves no controller holding the cell)")
    controller.set_defaults(run=_cmd_controller)

    serve = commands.add_parser(
        "serve", help="the operator application in the browser (viser), with the controller as its own process",
        description="Serve the operator application: teach and assemble in the browser. Prints the URL and the "
        "operator token; one browser at a time takes control with the token, every other one is a read-only "
        "monitor. Stop with Ctrl-C: the controller holds the robot and exits.")
    serve.add_argument("--backend", choices=ROBOT_BACKENDS, help=BACKEND_HELP)
    serve.add_argument("--host", default="127.0.0.1",
                       help="interface to serve on (default 127.0.0.1: this PC only; 0.0.0.0 opens it to the network)")
    serve.add_argument("--port", type=_positive(int), default=8080, help="HTTP port (default 8080; the next free "
                       "one if taken)")
    serve.add_argument("--data", metavar="DIR", help="data folder (default $VSERVO_DATA or ~/.local/share/vservo)")
    serve.add_argument("--seed", type=int, default=None, help="seed of the simulated cell and of the parts' arrival")
    serve.add_argument("--token", help="operator token (default $VSERVO_OPERATOR_TOKEN, else a new random one; a "
                       "token on the command line is visible to other users in ps, the variable is not)")
    serve.add_argument("--cycle-period", type=float, default=0.05, metavar="S",
                       help="shortest servo cycle in s, so a simulated run can be watched (default 0.05)")
    serve.set_defaults(run=_cmd_serve)

    bench = commands.add_parser("bench", help="measure speed and accuracy on this machine")
    bench.add_argument("what", choices=("vision", "calibration", "jrc", "ui"),
                       help="vision: render, detection and loop times, detection accuracy; "
                       "calibration: Levenberg-Marquardt training time on 16,000 samples; jrc: RPOSC and MOVL round "
                       "trips over a pty against the wire time, or with --soak the link under injected faults; "
                       "ui: camera frames per second in the browser and the controller's loop rate, with 1 and 5 "
                       "headless Chromium pages connected")
    bench.add_argument("--seed", type=int, default=0)
    bench.add_argument("--samples", type=_positive(int), default=50, help="jrc: round trips per command (default 50)")
    bench.add_argument("--soak", type=_positive(int), metavar="MOVES", help="jrc: soak the link with MOVES incremental moves")
    bench.add_argument("--fault-rate", type=_fraction, default=0.05, help="soak: faults per exchange (default 0.05)")
    bench.add_argument("--time-scale", type=_positive(float), default=50.0, help="soak: emulator speed-up (default 50)")
    bench.add_argument("--timer-a", type=_positive(float), default=0.1, help="soak: timer A in s (default 0.1)")
    bench.add_argument("--timer-b", type=_positive(float), default=1.0, help="soak: timer B in s (default 1)")
    bench.add_argument("--runs", type=_positive(int), default=3, help="ui: assemblies per browser count (default 3)")
    bench.add_argument("--cycle-period", type=float, default=0.0, metavar="S",
                       help="ui: shortest servo cycle in s (default 0: free-running)")
    bench.add_argument("--json", action="store_true", help="one JSON object")
    bench.set_defaults(run=_cmd_bench)

    add_calibrate_command(commands)

    emulator = commands.add_parser(
        "jrc-emulator", help="emulate a JRC controller on a pseudo-terminal (or a port), on the simulated cell",
        description="Runs the controller side of the JRC host link on the kinematic simulator. Without --port it "
        "creates a raw pseudo-terminal and prints its device path on the first line of standard output: point "
        "the cell file's [jrc] port at it.",
    )
    emulator.add_argument("--port", metavar="DEV", help="serve on this serial port instead of a new pseudo-terminal")
    emulator.add_argument("--fault-rate", type=_fraction, default=0.0, help="faults injected per exchange (default 0)")
    emulator.add_argument("--seed", type=int, default=0, help="seed of the injected faults (default 0)")
    emulator.add_argument("--time-scale", type=_positive(float), default=1.0,
                          help="the simulated robot runs this many times faster than real time (default 1)")
    emulator.add_argument("--pace", action="store_true", help="send and receive bytes at the baud rate")
    emulator.set_defaults(run=_cmd_jrc_emulator)

    _accept_cell_after_commands(parser)
    return parser


def _accept_cell_after_commands(parser: argparse.ArgumentParser) -> None:
    """--cell after any (sub)command too: vservo jrc-emulator --cell my.toml, vservo calibrate train --cell my.toml."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for command in action.choices.values():
                command.add_argument("--cell", metavar="FILE", default=argparse.SUPPRESS, help="cell configuration (TOML)")
                _accept_cell_after_commands(command)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # The detectors work on small regions, where OpenCV's thread pool costs more than it
    # gives: its workers spin after every call, on a 2-core cell PC taking the core that
    # the other process (controller or app) needs. Measured on the bench: the same
    # detection time or better, and a quarter less CPU than with the pool. One thread
    # per process.
    cv2.setNumThreads(1)
    try:
        return args.run(args)
    except (ConfigError, KinematicsError, RobotError, ValueError, OSError, StoreError) as exc:
        print(f"vservo {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
