"""The ``vservo`` command line: the app's commands, and ``main``, which builds the parser
from every layer's own ``cli.py`` and runs the command."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import cv2

from vservo.core.calibration.cli import add_calibrate_command, add_calibration_bench
from vservo.core.cell.cli import add_info_command, add_password_hash_command
from vservo.core.cell.config import ROBOT_BACKENDS, load_cell
from vservo.core.errors import VservoError
from vservo.core.perception.cli import add_detect_command
from vservo.core.production.cli import BACKEND_HELP, TIME_SCALE_HELP, add_production_commands, time_scale
from vservo.core.production.storage import default_data_dir
from vservo.core.sim.cli import add_jrc_emulator_command, add_virtual_cell_command
from vservo.core.study.cli import (
    add_cell_time_bench,
    add_jrc_bench,
    add_locate_bench,
    add_stream_bench,
    add_study_commands,
    add_vision_bench,
)
from vservo.core.terminal.command_line import CYCLE_PERIOD, BenchCommand, Parser, bounded, positive, print_result, seed
from vservo.core.terminal.logs import add_log_options, configure_logging


def _cmd_serve(args: argparse.Namespace) -> int:
    from vservo.app.controller_process import ControllerStartError
    from vservo.app.roles import TokenError, TokenSource, operator_token
    from vservo.app.server import ServeOptions, serve
    from vservo.app.web_guard import normalise_origin

    configure_logging(args, "serve")
    try:
        token = operator_token(
            args.token,
            args.token_file,
            os.environ,
            args.host,
            warn=lambda line: print(f"vservo serve: warning: {line}", file=sys.stderr),
        )
        origins = tuple(normalise_origin(origin) for origin in args.allow_origin)
    except (TokenError, ValueError) as exc:
        print(f"vservo serve: error: {exc}", file=sys.stderr)
        return 2
    config = load_cell(args.cell)
    options = ServeOptions(
        backend=args.backend or config.robot_backend,
        host=args.host,
        port=args.port,
        data=Path(args.data or default_data_dir()),
        seed=args.seed,
        token=token.value,
        cycle_period_s=args.cycle_period,
        time_scale=args.time_scale,
        cell=args.cell,
        show_token=token.source is TokenSource.GENERATED,
        allowed_origins=origins,
        log_options=("--log-level", args.log_level, "--log-format", args.log_format),
    )
    try:
        return serve(options, config, announce=lambda line: print(line, flush=True))
    except ControllerStartError as exc:
        print(f"vservo serve: error: {exc}", file=sys.stderr)
        return 2


def _cmd_bench_ui(args: argparse.Namespace) -> int:
    from vservo.app.bench_ui import bench_ui
    from vservo.app.browser import ChromiumMissing
    from vservo.app.light_monitor import Monitors

    config = load_cell(args.cell)
    try:
        result = bench_ui(
            config,
            seed=args.seed,
            runs=args.runs,
            monitors=Monitors(args.monitors),
            light_counts=tuple(args.light_clients),
            cycle_period_s=args.cycle_period,
            cell=args.cell,
        )
    except ChromiumMissing as exc:
        print(f"vservo bench: error: {exc}", file=sys.stderr)
        return 2
    print_result(result, args.json)
    return 0


def _cmd_bench_browsers(args: argparse.Namespace) -> int:
    from vservo.app.bench_memory import bench_browsers

    print_result(bench_browsers(args.clients, args.batch, args.cell), args.json)
    return 0


def _add_serve_command(commands: argparse._SubParsersAction) -> None:
    serve = commands.add_parser(
        "serve",
        help="the operator application in the browser (viser), with the controller as its own process",
        description="Serve the operator application: teach and assemble in the browser. Prints the URL and the "
        "operator token; one browser at a time takes control with the token, every other one is a read-only "
        "monitor. Stop with Ctrl-C: the controller holds the robot and exits.",
    )
    serve.add_argument("--backend", choices=ROBOT_BACKENDS, help=BACKEND_HELP)
    serve.add_argument(
        "--host",
        default="127.0.0.1",
        help="interface to serve on (default 127.0.0.1: this PC only; 0.0.0.0 opens it to the network)",
    )
    serve.add_argument(
        "--port", type=bounded(int, 1, 65535), default=8080, help="HTTP port (default 8080; the next free one if taken)"
    )
    serve.add_argument("--data", metavar="DIR", help="data folder (default $VSERVO_DATA or ~/.local/share/vservo)")
    serve.add_argument("--seed", type=seed, default=None, help="seed of the simulated cell and of the parts' arrival")
    token = serve.add_mutually_exclusive_group()
    token.add_argument(
        "--token-file",
        metavar="FILE",
        help="read the operator token from FILE (default "
        "$VSERVO_OPERATOR_TOKEN, else a new random one, printed); beyond 127.0.0.1 at least 16 characters",
    )
    token.add_argument(
        "--token",
        help="operator token, on this PC's loopback only: other users see it in ps (a "
        "warning says so); --token-file or $VSERVO_OPERATOR_TOKEN do not show",
    )
    serve.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        metavar="URL",
        help="a web page's origin (http://host:port) besides the app's own that may open its "
        "WebSocket, e.g. a reverse proxy; repeat for more",
    )
    serve.add_argument(
        "--cycle-period",
        type=CYCLE_PERIOD,
        default=0.05,
        metavar="S",
        help="shortest servo cycle in s, so a simulated run can be watched (default 0.05)",
    )
    serve.add_argument("--time-scale", type=time_scale, default=1.0, metavar="S", help=TIME_SCALE_HELP)
    add_log_options(serve)
    serve.set_defaults(run=_cmd_serve)


def _add_ui_bench(bench: BenchCommand) -> None:
    from vservo.app.light_monitor import LIGHT_COUNTS, Monitors

    ui = bench.add(
        "ui",
        "camera frames per second reaching the monitors, their CPU and the controller's loop rate: "
        "light WebSocket clients (1, 5, 20, each against none) and 1 and 5 headless Chromium pages",
        _cmd_bench_ui,
    )
    ui.add_argument(
        "--monitors",
        choices=[kind.value for kind in Monitors],
        default=Monitors.BOTH.value,
        help="ui: light (WebSocket clients that decode every message, render nothing), chromium "
        "(headless pages) or both (default both)",
    )
    ui.add_argument(
        "--light-clients",
        type=positive(int),
        nargs="+",
        default=list(LIGHT_COUNTS),
        metavar="N",
        help=f"ui: numbers of light clients, each paired run for run with runs without any "
        f"(default {' '.join(map(str, LIGHT_COUNTS))})",
    )
    ui.add_argument(
        "--runs",
        type=positive(int),
        default=3,
        help="ui: assemblies per monitor count (default 3; with light clients, as many again without any)",
    )
    ui.add_argument(
        "--cycle-period",
        type=CYCLE_PERIOD,
        default=0.0,
        metavar="S",
        help="ui: shortest servo cycle in s (default 0: free-running)",
    )


def _add_browsers_bench(bench: BenchCommand) -> None:
    browsers = bench.add(
        "browsers",
        "vservo serve's memory after 200 browsers (light monitors) connected and left, against after the first 10",
        _cmd_bench_browsers,
    )
    browsers.add_argument(
        "--clients", type=bounded(int, 1, 10000), default=200, help="browsers: light monitors in all (default 200)"
    )
    browsers.add_argument("--batch", type=bounded(int, 1, 100), default=10, help="browsers: connected at a time (default 10)")


def build_parser() -> argparse.ArgumentParser:
    """Every command of ``vservo``, each registered by the package it belongs to (lowest layer first)."""
    parser = Parser(
        prog="vservo",
        description="Vision-guided robotic assembly: a camera and a laser pointer on an industrial arm.",
    )
    parser.add_argument("--cell", metavar="FILE", help="cell configuration (TOML); default: the shipped cell")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=Parser)
    add_info_command(commands)
    add_password_hash_command(commands)
    add_detect_command(commands)
    add_jrc_emulator_command(commands)
    add_virtual_cell_command(commands)
    add_calibrate_command(commands)
    add_production_commands(commands)
    add_study_commands(commands)
    _add_serve_command(commands)

    bench = BenchCommand(commands.add_parser("bench", help="measure speed and accuracy on this machine"))
    add_vision_bench(bench)
    add_stream_bench(bench)
    add_locate_bench(bench)
    add_calibration_bench(bench)
    add_jrc_bench(bench)
    add_cell_time_bench(bench)
    _add_ui_bench(bench)
    _add_browsers_bench(bench)
    bench.close()

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
    except (VservoError, ValueError, OSError) as exc:  # vservo's own errors, bad values, files: one line
        print(f"vservo {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
