"""``vservo calibrate ...``: the calibration workflow on the command line (see workflow.py),
and ``vservo bench calibration``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from vservo.core.calibration.dataset import INPUT_SETS
from vservo.core.terminal.command_line import BenchCommand, print_result, seed


def _number(kind: type, low: float, strict: bool) -> Any:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (value > low if strict else value >= low) or value != value:
            raise argparse.ArgumentTypeError(f"expected a number {'>' if strict else '>='} {low:g}, got {text!r}")
        return value

    return parse


def _range_mm(text: str) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOW,HIGH in mm, got {text!r}") from None
    if not high >= low:
        raise argparse.ArgumentTypeError(f"expected LOW <= HIGH, got {text!r}")
    return low / 1000.0, high / 1000.0


def _levels(text: str) -> list[float]:
    try:
        levels = [float(v) for v in text.split(",")]
    except ValueError:
        levels = []
    if not levels or any(not (v >= 0.0) for v in levels):
        raise argparse.ArgumentTypeError(f"expected comma-separated pixel noises >= 0, got {text!r}")
    return levels


def _emit(result: dict[str, Any], as_json: bool) -> None:
    """One JSON object, or a table of the methods' errors with the rest as key: value lines."""
    if as_json:
        print(json.dumps(result))
        return
    for key, value in result.items():
        if key != "methods":
            print(f"{key}: {json.dumps(value) if isinstance(value, (dict, list)) else value}")
    methods = result.get("methods", {})
    if methods:
        print(f"{'method':<20}{'X mm':>10}{'Y mm':>10}{'XY mm':>10}{'max XY':>10}  true XY mm")
        for name, row in methods.items():
            true = row.get("true", {}).get("xy_mm", "")
            print(
                f"{name:<20}{row.get('x_mm', ''):>10}{row.get('y_mm', ''):>10}{row.get('xy_mm', ''):>10}"
                f"{row.get('max_xy_mm', ''):>10}  {true}"
            )


def _config(args: argparse.Namespace):
    from vservo.core.cell.config import load_cell

    return load_cell(args.cell)


def _truth(text: str) -> str:
    # Collection runs on the simulator: it is imported when the command runs, never
    # by the parser, so that `vservo controller` on a real cell loads none of it.
    from vservo.core.calibration.collection import TRUTHS

    if text not in TRUTHS:
        raise argparse.ArgumentTypeError(f"invalid choice {text!r} (choose from {', '.join(TRUTHS)})")
    return text


def _cmd_collect(args: argparse.Namespace) -> int:
    from vservo.core.calibration.collection import Workspace
    from vservo.core.calibration.workflow import CollectPlan, collect

    defaults = Workspace()
    workspace = Workspace(
        args.x_range_mm or defaults.x_range_m,
        args.y_range_mm or defaults.y_range_m,
        args.step_mm / 1000.0,
        args.height_mm / 1000.0,
    )
    plan = CollectPlan(
        workspace, not args.no_planar, args.test_views, args.rotated_views, args.varying_views, args.varying_test_views
    )
    _emit(collect(_config(args), Path(args.dir), args.truth, args.noise_px, args.seed, plan), args.json)
    return 0


def _settings(args: argparse.Namespace) -> Any:
    from vservo.core.calibration.levenberg_marquardt import LMSettings

    return LMSettings(epochs=args.epochs, goal=args.goal)


def _cmd_train(args: argparse.Namespace) -> int:
    from vservo.core.calibration.workflow import train

    _emit(
        train(_config(args), Path(args.dir), args.inputs, args.samples, args.validation, _settings(args), args.seed, args.hidden),
        args.json,
    )
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from vservo.core.calibration.workflow import evaluate

    _emit(evaluate(Path(args.dir), "test" if args.test == "held-out" else "varying_test"), args.json)
    return 0


def _cmd_track(args: argparse.Namespace) -> int:
    from vservo.core.calibration.tracking import TrackingSettings
    from vservo.core.calibration.workflow import track

    settings = TrackingSettings(gain=args.gain, seconds_per_point=args.seconds_per_point)
    _emit(
        track(_config(args), Path(args.dir), args.test, args.points, args.amplitude_mm / 1000.0, settings, args.seed), args.json
    )
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from vservo.core.calibration.workflow import compare

    result = compare(
        _config(args),
        Path(args.dir),
        args.noise_px,
        args.seed,
        samples=args.samples,
        settings=_settings(args),
        points=args.points,
    )
    if args.json:
        print(json.dumps(result))
        return 0
    print("realistic truth, random-point tracking, mean error in mm (X / Y / XY, max XY); Table 3-4 beside")
    for level, row in result["results"].items():
        print(f"pixel noise {level} px")
        for name, errors in row["track_random"].items():
            thesis = result["thesis_table_3_4"].get(name)
            beside = f"   thesis {thesis['x_mm']} / {thesis['y_mm']} / {thesis['xy_mm']}" if thesis else ""
            print(f"  {name:<20}{errors['x_mm']:>9} /{errors['y_mm']:>9} /{errors['xy_mm']:>9}, {errors['max_xy_mm']:>9}{beside}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from vservo.core.calibration.bench import bench_calibration

    print_result(bench_calibration(_config(args), seed=args.seed), args.json)
    return 0


def add_calibration_bench(bench: BenchCommand) -> None:
    """Register ``vservo bench calibration``."""
    bench.add("calibration", "Levenberg-Marquardt training time on 16,000 samples", _cmd_bench)


def add_calibrate_command(commands: argparse._SubParsersAction) -> None:
    """Register ``vservo calibrate`` and its steps on the top-level subcommands."""
    calibrate = commands.add_parser(
        "calibrate",
        help="NN hand-eye calibration and the classical methods: collect, train, evaluate, track, compare",
        description="The calibration workflow of thesis chapters 2 and 3 on the simulated cell. Files go to "
        "--dir (default ./calibration).",
    )
    steps = calibrate.add_subparsers(dest="step", metavar="STEP", required=True, parser_class=type(calibrate))

    def step(name: str, help_text: str, default_dir: str = "calibration") -> argparse.ArgumentParser:
        parser = steps.add_parser(name, help=help_text)
        parser.add_argument("--dir", default=default_dir, help=f"folder of the calibration files (default {default_dir})")
        parser.add_argument("--json", action="store_true", help="one JSON object")
        return parser

    collect = step("collect", "move the camera over the checkerboard and record the corners and robot readings")
    collect.add_argument(
        "--truth",
        type=_truth,
        default="realistic",
        help="ideal (the nominal cell exactly), realistic (lens, camera mount and arm errors) or cell "
        "(the cell file's [simulation]); default realistic",
    )
    collect.add_argument(
        "--noise-px",
        type=_number(float, 0.0, False),
        default=None,
        help="Gaussian pixel noise on every corner (default 0 for ideal, 0.25 for realistic)",
    )
    collect.add_argument("--seed", type=seed, default=1, help="seed of the simulated cell and the noise (default 1)")
    collect.add_argument("--step-mm", type=_number(float, 0.0, True), default=20.0, help="grid step (default 20)")
    collect.add_argument(
        "--height-mm", type=_number(float, 0.0, True), default=300.0, help="camera height over the table (default 300)"
    )
    collect.add_argument("--x-range-mm", type=_range_mm, help="workspace X range LOW,HIGH (default -800,-100)")
    collect.add_argument("--y-range-mm", type=_range_mm, help="workspace Y range LOW,HIGH (default -350,350)")
    collect.add_argument("--test-views", type=_number(int, 0, True), default=40, help="held-out random viewpoints")
    collect.add_argument(
        "--rotated-views",
        type=_number(int, 0, False),
        default=30,
        help="viewpoints with wrist rotations, for AX=XB and the camera calibration (0: none)",
    )
    collect.add_argument(
        "--varying-views",
        type=_number(int, 0, False),
        default=0,
        help="viewpoints at varying height, tilt and yaw for the 6-DOF variant (0: none)",
    )
    collect.add_argument("--varying-test-views", type=_number(int, 0, True), default=60)
    collect.add_argument("--no-planar", action="store_true", help="skip the grid and the held-out views (planar.npz, test.npz)")
    collect.set_defaults(run=_cmd_collect)

    def lm_options(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--samples", type=_number(int, 0, True), default=16000, help="training corners (default 16000)")
        parser.add_argument("--epochs", type=_number(int, 0, True), default=500, help="epoch limit (default 500)")
        parser.add_argument(
            "--goal",
            type=_number(float, 0.0, False),
            default=1e-10,
            help="mean squared error goal on the normalised outputs (default 1e-10; the thesis's 1e-8 "
            "leaves about 0.03 mm on noise-free data, Table 3-2 needs 0.005)",
        )

    train = step("train", "train the NN by Levenberg-Marquardt and fit the classical calibrations")
    train.add_argument(
        "--inputs",
        choices=tuple(INPUT_SETS),
        default="planar",
        help="planar (u, v, Tx, Ty), height (+Tz) or pose (+Tz and tilt: the 6-DOF variant)",
    )
    lm_options(train)
    train.add_argument("--validation", type=_number(int, 0, True), default=2000, help="validation corners (default 2000)")
    train.add_argument("--seed", type=seed, default=0, help="seed of the sample draw and initial weights (default 0)")
    train.add_argument("--hidden", type=_number(int, 0, True), default=20, help="hidden units (default 20, as the thesis)")
    train.set_defaults(run=_cmd_train)

    evaluate = step("evaluate", "world-coordinate errors of every calibration on held-out viewpoints")
    evaluate.add_argument(
        "--test",
        choices=("held-out", "varying"),
        default="held-out",
        help="held-out: test.npz; varying: varying_test.npz (height and tilt varying)",
    )
    evaluate.set_defaults(run=_cmd_evaluate)

    track = step("track", "PBVS tracking (eq. 2-47) with every calibration")
    track.add_argument(
        "--test",
        choices=("sinusoid", "random"),
        default="sinusoid",
        help="the 41 points of eq. 3-1, or random points from held-out viewpoints",
    )
    track.add_argument("--points", type=_number(int, 0, True), default=40, help="random points (default 40)")
    track.add_argument(
        "--amplitude-mm",
        type=_number(float, 0.0, True),
        default=40.0,
        help="sinusoid amplitude (default 40: the UPJ's shell cannot reach the thesis's 100)",
    )
    track.add_argument("--gain", type=_number(float, 0.0, True), default=1.0, help="K of eq. 2-47 in 1/s (default 1)")
    track.add_argument("--seconds-per-point", type=_number(float, 0.0, True), default=10.0)
    track.add_argument("--seed", type=seed, default=0, help="seed of the random points (default 0)")
    track.set_defaults(run=_cmd_track)

    compare = step(
        "compare", "realistic truth at several pixel noises: every method beside Table 3-4", default_dir="calibration/compare"
    )
    compare.add_argument("--noise-px", type=_levels, default=[0.1, 0.25, 0.5], help="pixel noises (default 0.1,0.25,0.5)")
    compare.add_argument("--seed", type=seed, default=1)
    compare.add_argument("--points", type=_number(int, 0, True), default=40, help="random points per noise (default 40)")
    lm_options(compare)
    compare.set_defaults(run=_cmd_compare)
