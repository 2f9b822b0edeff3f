"""``vservo jrc-emulator``: the JRC's side of the host link, on the simulated cell."""

from __future__ import annotations

import argparse
import sys
import threading

from vservo.core.cell.config import load_cell
from vservo.core.terminal.command_line import fraction, positive


def _cmd_jrc_emulator(args: argparse.Namespace) -> int:
    import signal

    from vservo.core.sim.jrc_emulator import FaultPlan, JrcEmulator
    from vservo.core.sim.plant import SimulatedCell

    config = load_cell(args.cell)
    emulator = JrcEmulator(SimulatedCell(config), config.jrc, FaultPlan(args.fault_rate, args.seed), args.time_scale,
                           pace=args.pace, vacuum=config.vacuum_device)
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


def add_jrc_emulator_command(commands: argparse._SubParsersAction) -> None:
    """Register ``vservo jrc-emulator`` on the top-level subcommands."""
    emulator = commands.add_parser(
        "jrc-emulator", help="emulate a JRC on a pseudo-terminal (or a port), on the simulated cell",
        description="Runs the JRC's side of the host link on the kinematic simulator. Without --port it "
        "creates a raw pseudo-terminal and prints its device path on the first line of standard output: point "
        "the cell file's [jrc] port at it.",
    )
    emulator.add_argument("--port", metavar="DEV", help="serve on this serial port instead of a new pseudo-terminal")
    emulator.add_argument("--fault-rate", type=fraction, default=0.0, help="faults injected per exchange (default 0)")
    emulator.add_argument("--seed", type=int, default=0, help="seed of the injected faults (default 0)")
    emulator.add_argument("--time-scale", type=positive(float), default=1.0,
                          help="the simulated robot runs this many times faster than real time (default 1)")
    emulator.add_argument("--pace", action="store_true", help="send and receive bytes at the baud rate")
    emulator.set_defaults(run=_cmd_jrc_emulator)
