"""``vservo run`` and ``vservo controller``: one headless assembly, and the controller process."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vservo.core.cell.config import ROBOT_BACKENDS, load_cell
from vservo.core.production.storage import default_data_dir
from vservo.core.terminal.command_line import CYCLE_PERIOD, TCP_PORT, print_result, seed
from vservo.core.terminal.logs import add_log_options, announce, configure_logging

if TYPE_CHECKING:  # imported when a command runs: `vservo --help` stays quick
    from vservo.core.cell.config import CellConfig
    from vservo.core.production.cell_controller import CellController
    from vservo.core.production.rig import Rig
    from vservo.core.production.storage import RunRecord, Store

BACKEND_HELP = (
    "the simulated cell's robot: sim drives the simulator directly, jrc through the JRC link to an "
    "emulated JRC on a pseudo-terminal (default: the cell file's [robot] backend; a real cell's is its JRC)"
)


def _cmd_run(args: argparse.Namespace) -> int:
    import signal

    from vservo.core.production.assembly import Outcome
    from vservo.core.production.cell_controller import CommandRefused, run_job_once
    from vservo.core.production.cell_rig import build_rig
    from vservo.core.production.storage import Store

    configure_logging(args, "run")
    config = load_cell(args.cell)
    store = Store.for_controller(args.data or default_data_dir(), config.recordings)
    controller = _controller_on(build_rig(config, args.seed, args.backend), store, seed=args.seed or 0)
    try:
        summary = run_job_once(controller, args.job, args.part_id)
    except CommandRefused as exc:
        print(f"vservo run: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # Ctrl-C: hold the robot and let the run end on record (e-stopped) before exiting;
        # a second Ctrl-C must not cut that short.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        controller.estop("Ctrl-C on vservo run")
        controller.wait()
        print(f"vservo run: interrupted: {controller.state.detail}", file=sys.stderr)
        return 130
    finally:
        controller.close()
        store.close()
    print_result(summary, args.json)
    return 0 if summary["outcome"] == Outcome.PLACED else 1


def _cmd_controller(args: argparse.Namespace) -> int:
    import signal

    from vservo.core.production.cell_rig import build_rig
    from vservo.core.production.channel import ControllerServer
    from vservo.core.production.plc.service import PlcService
    from vservo.core.production.protocol import KEY_ENVIRONMENT
    from vservo.core.production.storage import Store

    configure_logging(args, "controller")
    key = os.environ.get(KEY_ENVIRONMENT, "")
    try:
        authkey = bytes.fromhex(key)
    except ValueError:
        authkey = b""
    if len(authkey) < 16:
        print(
            f"vservo controller: error: set {KEY_ENVIRONMENT} to the channel key (32+ hex digits); "
            "`vservo serve` does this for you",
            file=sys.stderr,
        )
        return 2
    config = load_cell(args.cell)
    store = Store.for_controller(args.data or default_data_dir(), config.recordings)
    controller = _controller_on(
        build_rig(config, args.seed, args.backend, args.time_scale), store, seed=args.seed or 0, cycle_period_s=args.cycle_period
    )
    server = ControllerServer(controller, authkey, port=args.port)
    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.set())
    if args.exit_with_parent:
        threading.Thread(target=_stop_when_orphaned, args=(os.getppid(), stop), name="parent-watch", daemon=True).start()
    address: dict[str, Any] = {"host": server.address[0], "port": server.address[1], "backend": controller.rig.robot.name}
    plc, line_services = None, []
    try:
        plc = PlcService.start(controller)  # the PLC handshake of [line.plc], if the cell file has one
        line_services = _line_services(controller, config, address)
    except BaseException:
        if plc is not None:
            plc.close()
        server.close()
        controller.close()
        store.close()
        raise
    announced = {"controller": address}
    print(json.dumps(announced if plc is None else {**announced, "plc": plc.where()}), flush=True)
    stop.wait()
    # The stop is under way: a second signal (the app's SIGTERM after a service manager's SIGINT
    # to both) must not cut it short, nor kill the process as the interpreter restores the
    # default handlers on its way out.
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, signal.SIG_IGN)
    for service in line_services:
        service.close()
    if plc is not None:
        plc.close()
    server.close()
    controller.close()  # holds the robot if a run is under way
    store.close()
    return 0


def _line_services(controller: CellController, config: CellConfig, address: dict[str, Any]) -> list[Any]:
    """The cell file's [line] services on the controller: its metrics endpoint and its OPC UA
    server, each started when enabled; their addresses go into the controller's first line."""
    services: list[Any] = []
    try:
        if config.line.metrics.enabled:
            from vservo.core.production.metrics import ControllerMetrics

            metrics = ControllerMetrics(controller)
            services.append(metrics)
            host, port = metrics.serve(config.line.metrics)
            address["metrics"] = f"http://{host}:{port}/metrics"
        if config.line.opcua.enabled:
            from vservo.core.production.opcua_server import CellOpcUaServer

            opcua = CellOpcUaServer(controller, config.line.opcua)
            services.append(opcua)
            address["opcua"] = opcua.start()
    except BaseException:
        for service in services:
            service.close()
        raise
    return services


# What `vservo runs` exports of each run, in this order (the CSV's columns).
RUN_FIELDS = (
    "id",
    "job",
    "part_id",
    "started_at",
    "finished_at",
    "outcome",
    "reason",
    "placement_error_mm",
    "final_error_px",
    "duration_s",
    "backend",
    "recording",
)


def _cmd_runs(args: argparse.Namespace) -> int:
    """The runs of a data folder started in [--since, --until), for traceability."""
    import csv

    from vservo.core.production.storage import Store

    store = Store(args.data or default_data_dir())
    try:
        runs = store.runs_between(args.since, args.until)
    finally:
        store.close()
    rows = [_run_row(run) for run in runs if args.job is None or run.job == args.job]
    if args.csv:
        writer = csv.DictWriter(sys.stdout, RUN_FIELDS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    else:
        print(json.dumps(rows, indent=None if args.json else 1))
    return 0


def _run_row(run: RunRecord) -> dict[str, Any]:
    """One run as `vservo runs` exports it: times in ISO 8601 UTC, the outcome by name."""

    def iso(t: float | None) -> str | None:
        return None if t is None else datetime.fromtimestamp(t, timezone.utc).isoformat(timespec="milliseconds")

    row = {field: getattr(run, field) for field in RUN_FIELDS}
    row.update(
        started_at=iso(run.started_at),
        finished_at=iso(run.finished_at),
        outcome=None if run.outcome is None else run.outcome.value,
    )
    return row


def _instant(text: str) -> float:
    """--since / --until: an ISO 8601 date or date and time (local time unless it says its
    zone), as a Unix time."""
    try:
        moment = datetime.fromisoformat(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected an ISO 8601 date or date and time (2026-11-28 or 2026-11-28T06:00), got {text!r}"
        ) from None
    return moment.timestamp()


def _controller_on(rig: Rig, store: Store, **settings: Any) -> CellController:
    """The cell controller on ``rig``; the rig closed if it cannot start (a robot port another
    program holds, say), so no camera thread is left reading at the interpreter's exit."""
    from vservo.core.production.cell_controller import CellController

    try:
        return CellController(rig, store, **settings)
    except BaseException:
        rig.close()
        raise


def _cmd_commission(args: argparse.Namespace) -> int:
    from vservo.core.cell.config import ConfigError, read_cell_data
    from vservo.core.production.cell_rig import build_rig
    from vservo.core.production.commissioned_file import commissioned_tables, write_commissioned_cell
    from vservo.core.production.commissioning import (
        Commissioning,
        CommissioningError,
        CommissionSettings,
        Step,
        commission_summary,
        model_errors,
    )
    from vservo.core.terminal.progress import Progress

    try:
        steps = [Step(name) for name in args.steps.split(",")]
    except ValueError:
        print(f"vservo commission: error: --steps {args.steps!r}: choose from {','.join(Step)}", file=sys.stderr)
        return 2
    if not args.cell:
        print(
            "vservo commission: error: --cell FILE is required: the cell file of the cell to commission "
            "(it is never overwritten)",
            file=sys.stderr,
        )
        return 2
    out = Path(args.out)
    if out.resolve() == Path(args.cell).resolve():
        print(f"vservo commission: error: --out {out} is the input cell file: commissioning writes a new one", file=sys.stderr)
        return 2
    if out.exists() and not args.force:
        print(
            f"vservo commission: error: --out {out} exists: commissioning writes a new file (--force replaces it)",
            file=sys.stderr,
        )
        return 2
    config = load_cell(args.cell)
    reference = _reference_model(args.reference, args.cell) if args.reference else None
    folder = Path(args.data_folder) if args.data_folder else out.with_name(out.stem + "-commissioning")
    rig = build_rig(config, args.seed)
    bars: dict[str, Progress] = {}

    def on_progress(progress) -> None:
        bar = bars.get(progress.step)
        if bar is None:
            bar = bars[progress.step] = Progress(progress.total, f"commission {progress.step}")
        bar.advance(progress.note)

    try:
        rig.robot.connect()
        if not rig.robot.status().servo_on:
            rig.robot.servo(True)
        result = Commissioning(rig, folder, CommissionSettings(seed=args.seed or 0), on_progress).run(steps)
    except (CommissioningError, ConfigError) as exc:
        print(f"vservo commission: error: {exc}", file=sys.stderr)
        return 1
    finally:
        for bar in bars.values():
            bar.close()
        rig.close()
    summary = commission_summary(result)
    summary["data_folder"] = str(folder)
    if reference is not None:
        summary["against_reference"] = model_errors(result.model, reference, 0.162)
    if result.good:
        tables, _ = read_cell_data(args.cell)
        write_commissioned_cell(config.source, commissioned_tables(tables, result, out, folder, steps), out)
        summary["out"] = str(out)
    else:
        summary["out"] = None
    print_result(summary, args.json)
    return 0 if result.good else 1


def _reference_model(path: str, cell: str):
    """The model a reference file says the cell is: its [simulation.truth.*] laid over the
    --cell file's nominal model (a virtual cell's truth file), or, for a cell file
    without truth tables (the last commissioning), its nominal model."""
    from vservo.core.cell.config import load_cell, model_with_truth, read_cell_data

    reference, source = read_cell_data(path)
    truth = reference.get("simulation", {}).get("truth")
    if isinstance(truth, dict) and truth:
        return model_with_truth(read_cell_data(cell)[0], truth, source)
    return load_cell(path).nominal


def _stop_when_orphaned(parent_pid: int, stop: threading.Event, period_s: float = 0.5) -> None:
    """Set ``stop`` once this process's parent is no longer ``parent_pid``.

    A parent killed outright (SIGKILL, a crash) sends no signal; its children are handed
    to init, which changes their parent id. Polling it works for every way to die.
    """
    while not stop.wait(period_s):
        if os.getppid() != parent_pid:
            announce(f"vservo controller: the process that started it ({parent_pid}) is gone: holding the robot and stopping")
            stop.set()


TIME_SCALE_HELP = (
    "the simulated cell runs S times faster than the real cell (default 1: its pace, a run "
    "watched as it happens; 0: as fast as this computer can)"
)


def time_scale(text: str) -> float | None:
    """--time-scale: a non-negative number; 0 (as fast as the host can) is None."""
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a non-negative number (0: as fast as this computer can), got {text!r}")
    return value or None


def add_production_commands(commands: argparse._SubParsersAction) -> None:
    """Register ``vservo run`` and ``vservo controller`` on the top-level subcommands."""
    run = commands.add_parser("run", help="one headless assembly of a taught job on the cell of --cell (exit 0 when placed)")
    run.add_argument("--job", required=True, help="job name (the shipped 'demo' is always there)")
    run.add_argument(
        "--data", metavar="DIR", help="data folder with the jobs and runs (default $VSERVO_DATA or ~/.local/share/vservo)"
    )
    run.add_argument("--seed", type=seed, default=None, help="seed of the simulated cell and of the part's arrival")
    run.add_argument("--backend", choices=ROBOT_BACKENDS, help=BACKEND_HELP)
    run.add_argument("--json", action="store_true", help="one JSON object")
    run.add_argument("--part-id", metavar="ID", help="the part's ID, stored with the run for traceability (`vservo runs`)")
    add_log_options(run)
    run.set_defaults(run=_cmd_run)

    runs = commands.add_parser("runs", help="export the runs of a data folder with their figures (JSON, or CSV with --csv)")
    runs.add_argument("--data", metavar="DIR", help="data folder (default $VSERVO_DATA or ~/.local/share/vservo)")
    runs.add_argument("--since", type=_instant, default=0.0, metavar="WHEN", help="runs started at or after WHEN (ISO 8601)")
    runs.add_argument("--until", type=_instant, default=math.inf, metavar="WHEN", help="runs started before WHEN (ISO 8601)")
    runs.add_argument("--job", help="only the runs of this job")
    form = runs.add_mutually_exclusive_group()
    form.add_argument("--csv", action="store_true", help="CSV with a header line, one run a line")
    form.add_argument("--json", action="store_true", help="one JSON array on one line")
    runs.set_defaults(run=_cmd_runs)

    controller = commands.add_parser(
        "controller", help="the controller process: owns the cell, serves the app over an authenticated local channel"
    )
    controller.add_argument("--port", type=TCP_PORT, default=0, help="TCP port on 127.0.0.1 (default: any free one)")
    controller.add_argument("--data", metavar="DIR", help="data folder (default $VSERVO_DATA or ~/.local/share/vservo)")
    controller.add_argument("--seed", type=seed, default=None, help="seed of the simulated cell")
    controller.add_argument("--backend", choices=ROBOT_BACKENDS, help=BACKEND_HELP)
    controller.add_argument(
        "--cycle-period",
        type=CYCLE_PERIOD,
        default=0.05,
        metavar="S",
        help="shortest servo cycle in s, so a simulated run can be watched (default 0.05)",
    )
    controller.add_argument("--time-scale", type=time_scale, default=1.0, metavar="S", help=TIME_SCALE_HELP)
    controller.add_argument(
        "--exit-with-parent",
        action="store_true",
        help="hold the robot and exit when the process that started this one is gone "
        "(`vservo serve` sets it: a killed app leaves no controller holding the cell)",
    )
    add_log_options(controller)
    controller.set_defaults(run=_cmd_controller)

    commission = commands.add_parser(
        "commission",
        help="measure the connected cell's camera, hand-eye, laser and NN on its board and write a new "
        "cell file (docs/commissioning.md)",
    )
    commission.add_argument("--out", required=True, metavar="NEW_FILE", help="the commissioned cell file to write")
    commission.add_argument(
        "--steps", default="camera,hand-eye,laser,nn", help="comma-separated steps: camera, hand-eye, laser, nn (default: all)"
    )
    commission.add_argument(
        "--data-folder", metavar="DIR", help="where the views, datasets and the NN go (default: NEW_FILE's name + -commissioning)"
    )
    commission.add_argument(
        "--reference",
        metavar="FILE",
        help="a cell file to compare the measured model with: a virtual cell's --truth file, or the last commissioned file",
    )
    commission.add_argument(
        "--seed", type=seed, default=None, help="seed of the views' random tilts and turns (and of a simulated cell)"
    )
    commission.add_argument("--force", action="store_true", help="replace NEW_FILE if it exists (never the input)")
    commission.add_argument("--json", action="store_true", help="one JSON object")
    commission.set_defaults(run=_cmd_commission)
