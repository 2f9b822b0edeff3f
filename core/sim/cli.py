"""``vservo jrc-emulator`` (the JRC's side of the host link, on the simulated cell) and
``vservo virtual-cell`` (the simulated cell as its own process, behind a real cell's interfaces)."""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
from pathlib import Path

from vservo.core.cell.config import HostTransport, load_cell
from vservo.core.terminal.command_line import fraction, positive, seed
from vservo.core.terminal.logs import add_log_options, announce, configure_logging


def _cmd_jrc_emulator(args: argparse.Namespace) -> int:
    import signal

    from vservo.core.sim.jrc_emulator import FaultPlan, JrcEmulator
    from vservo.core.sim.plant import SimulatedCell

    configure_logging(args, "jrc-emulator")
    config = load_cell(args.cell)
    emulator = JrcEmulator(
        SimulatedCell(config),
        config.jrc,
        FaultPlan(args.fault_rate, args.seed),
        args.time_scale,
        pace=args.pace,
        vacuum=config.vacuum_device,
        plc=config.plc,
    )
    line = config.jrc
    if args.tcp_port is not None:
        host, port = emulator.start_on_tcp(port=args.tcp_port)
        where, link = f"{host}:{port}", "the Ethernet server's framing"
    else:
        if args.port:
            emulator.start_on_port(args.port)
        else:
            emulator.start_on_pty()
        where = str(emulator.device)
        link = f"{line.baud} baud, {line.data_bits} data bits, {line.parity} parity, {line.stop_bits} stop bit(s)"
    print(where, flush=True)
    announce(
        f"JRC emulator on {where}: {link}; time scale {args.time_scale:g}, faults {args.fault_rate:.0%}; "
        "Ctrl-C or SIGTERM stops it"
    )
    stopped = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stopped.set())
    stopped.wait()
    emulator.stop()
    announce(
        f"served {emulator.exchanges} exchanges, {len(emulator.executed)} moves; faults injected {dict(emulator.faults.injected)}"
    )
    return 0


def add_jrc_emulator_command(commands: argparse._SubParsersAction) -> None:
    """Register ``vservo jrc-emulator`` on the top-level subcommands."""
    emulator = commands.add_parser(
        "jrc-emulator",
        help="emulate a JRC on a pseudo-terminal (or a port, or TCP as an Ethernet server), on the simulated cell",
        description="Runs the JRC's side of the host link on the kinematic simulator. Without --port it "
        "creates a raw pseudo-terminal and prints its device path on the first line of standard output: point "
        "the cell file's [jrc] port at it. With --tcp-port it serves the host commands as a DX100 or later "
        "controller's Ethernet server does, on 127.0.0.1, and prints host:port instead.",
    )
    port = emulator.add_mutually_exclusive_group()
    port.add_argument("--port", metavar="DEV", help="serve on this serial port instead of a new pseudo-terminal")
    port.add_argument(
        "--tcp-port",
        type=int,
        metavar="PORT",
        help="serve the Ethernet server's framing on this TCP port of 127.0.0.1 (0: any free one)",
    )
    emulator.add_argument("--fault-rate", type=fraction, default=0.0, help="faults injected per exchange (default 0)")
    emulator.add_argument("--seed", type=seed, default=0, help="seed of the injected faults (default 0)")
    emulator.add_argument(
        "--time-scale",
        type=positive(float),
        default=1.0,
        help="the simulated robot runs this many times faster than real time (default 1)",
    )
    emulator.add_argument("--pace", action="store_true", help="send and receive bytes at the baud rate")
    add_log_options(emulator)
    emulator.set_defaults(run=_cmd_jrc_emulator)


def _cmd_virtual_cell(args: argparse.Namespace) -> int:
    import signal

    from vservo.core.cell.config import read_cell_data_with_truth
    from vservo.core.sim.virtual_cell import Addresses, Released, VirtualCell, VirtualCellSettings

    over_ethernet = HostTransport(args.robot_link) is HostTransport.ETHERNET
    if args.jrc_link and over_ethernet:
        raise ValueError("--jrc-link names a pseudo-terminal: it needs --robot-link serial")
    if args.jrc_tcp_port and not over_ethernet:
        raise ValueError("--jrc-tcp-port is the Ethernet server's port: it needs --robot-link ethernet")
    configure_logging(args, "virtual-cell")
    tables, source = read_cell_data_with_truth(args.cell, args.truth)
    settings = VirtualCellSettings(
        time_scale=args.time_scale, fps=args.fps, exposure_latency_s=args.latency, robot_link=HostTransport(args.robot_link)
    )

    def print_released(released: Released) -> None:
        print(json.dumps(released.as_dict()), flush=True)

    stopped = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stopped.set())
    with (
        tempfile.TemporaryDirectory(prefix="vservo-virtual-cell-") as folder,
        VirtualCell(
            tables,
            source,
            args.seed,
            settings,
            on_released=print_released,
            board_laid=args.board,
            addresses=Addresses(args.jrc_link and Path(args.jrc_link), args.camera_port, args.fixture_port, args.jrc_tcp_port),
        ) as virtual,
    ):
        cell_file = virtual.write_cell_file(Path(args.out) if args.out else Path(folder) / "cell.toml")
        print(
            json.dumps(
                {
                    "cell_file": str(cell_file),
                    "jrc_port": virtual.jrc_port,
                    "camera_url": virtual.camera.url,
                    "fixture": virtual.fixture.url,
                }
            ),
            flush=True,
        )
        announce(
            f"virtual cell from {source}: JRC on {virtual.jrc_port} (time scale {args.time_scale:g}), camera "
            f"{virtual.camera.url}, fixture {virtual.fixture.url}; run the product with --cell {cell_file}; "
            "Ctrl-C or SIGTERM stops it"
        )
        stopped.wait()
    return 0


def add_virtual_cell_command(commands: argparse._SubParsersAction) -> None:
    """Register ``vservo virtual-cell`` on the top-level subcommands."""
    virtual = commands.add_parser(
        "virtual-cell",
        help="the simulated cell as its own process: a JRC on a pseudo-terminal (or TCP), a camera stream, a part fixture",
        description="Runs the simulated cell behind the interfaces a real cell has: the JRC emulator on a new "
        "pseudo-terminal, or with --robot-link ethernet on a loopback TCP port as a DX100 or later controller's "
        "Ethernet server (the vacuum cup on its I/O), the camera as an MJPEG stream OpenCV opens by URL, and a "
        "fixture (HTTP, JSON) that presents parts, lays the checkerboard and gauges where a released part ended. "
        "It writes a cell file for the controller and prints one JSON line with cell_file, jrc_port (the "
        "pseudo-terminal, or host:port), camera_url "
        "and fixture, then one line per released part. Runs until Ctrl-C or SIGTERM.",
    )
    virtual.add_argument(
        "--truth",
        metavar="FILE",
        help="a cell file whose [simulation.truth.*] tables say how the "
        "cell really differs from the nominal one, and its [simulation.scene] board_pose where the "
        "board truly lies (default: the --cell file's own)",
    )
    virtual.add_argument("--seed", type=seed, default=None, help="seed of the plant, its camera and its parts")
    virtual.add_argument(
        "--out", metavar="FILE", help="where to write the controller's cell file (default: a temporary folder removed on exit)"
    )
    virtual.add_argument(
        "--time-scale",
        type=positive(float),
        default=40.0,
        help="the JRC and the plant run this many times faster than a real cell (default 40)",
    )
    virtual.add_argument("--fps", type=positive(float), default=30.0, help="camera frames per second (default 30)")
    virtual.add_argument(
        "--latency",
        type=positive(float),
        default=0.05,
        metavar="S",
        help="camera latency from exposure to sending a frame, in s (default 0.05)",
    )
    virtual.add_argument(
        "--board",
        action="store_true",
        help="start with the calibration checkerboard of the "
        "cell file's [board] laid on the table (the parts cleared off it), as to commission the cell",
    )
    virtual.add_argument(
        "--jrc-link",
        metavar="PATH",
        help="a symbolic link to the JRC's pseudo-terminal, made at "
        "start and named as [jrc] port: a virtual cell restarted on the same PATH is where the "
        "controller left it, as a real serial adapter's /dev/serial/by-id name is",
    )
    virtual.add_argument(
        "--robot-link",
        choices=tuple(HostTransport),
        default=HostTransport.SERIAL.value,
        help="what carries the host commands to the JRC: serial, BSC on a pseudo-terminal (default), or ethernet, "
        "the Ethernet server's framing on a loopback TCP port; the written cell file's [jrc] says which",
    )
    virtual.add_argument(
        "--jrc-tcp-port",
        type=int,
        default=0,
        metavar="PORT",
        help="with --robot-link ethernet, the JRC's TCP port (default: any free one)",
    )
    virtual.add_argument(
        "--camera-port", type=int, default=0, metavar="PORT", help="the camera stream's TCP port (default: any free one)"
    )
    virtual.add_argument(
        "--fixture-port", type=int, default=0, metavar="PORT", help="the fixture's TCP port (default: any free one)"
    )
    add_log_options(virtual)
    virtual.set_defaults(run=_cmd_virtual_cell)
