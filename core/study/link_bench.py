"""``vservo bench jrc``: how long the host link takes per command, against the wire.

Over a pseudo-terminal to the JRC emulator, it times RPOSC (read the pose) and
MOVL (start a linear move) round trips, from the host's ENQ to the JRC's EOT,
and counts the bytes each moves in both directions. The wire time of those bytes at the
cell's baud rate (start, data, parity and stop bits per byte) is what a real RS-232 line
cannot beat; a pseudo-terminal is not baud-limited, so the emulator can also pace every
byte it sends and receives at the baud rate, which shows the link as a real line would
carry it. Times are medians and 95th percentiles; a shared 2-core machine is noisy.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from vservo.core.cell.config import CellConfig
from vservo.core.geometry.spatial import transform
from vservo.core.robot.jrc import JrcBackend
from vservo.core.sim.jrc_emulator import JrcEmulator
from vservo.core.sim.plant import SimulatedCell
from vservo.core.study.vision_bench import _stats_ms

STEP_M = 0.001  # each timed MOVL goes 1 mm back or forth
TIME_SCALE = 1000.0  # the motions themselves are not what is timed


def _round_trips(
    robot: JrcBackend, send: Callable[[int], object], samples: int, then: Callable[[], object] | None = None
) -> dict[str, Any]:
    """Time ``send(i)`` and count its bytes, ``samples`` times; ``then()`` runs untimed after each."""
    channel = robot.station.channel
    seconds, sizes = [], []
    for i in range(samples):
        before = channel.bytes_in + channel.bytes_out
        started = time.perf_counter()
        send(i)
        seconds.append(time.perf_counter() - started)
        sizes.append(channel.bytes_in + channel.bytes_out - before)
        if then is not None:
            then()
    size = int(np.median(sizes))
    wire_ms = robot.line.wire_time_s(size) * 1000.0
    stats = _stats_ms(seconds)
    return {**stats, "bytes": size, "wire_ms": round(wire_ms, 3), "median_over_wire": round(stats["median_ms"] / wire_ms, 3)}


def _measure(config: CellConfig, samples: int, pace: bool, seed: int) -> dict[str, Any]:
    cell = SimulatedCell(config, seed)
    with JrcEmulator(cell, config.jrc, time_scale=TIME_SCALE, pace=pace) as emulator:
        robot = JrcBackend(config.jrc, emulator.device)
        robot.connect()
        try:
            robot.servo(True)
            bMe = robot.read_pose()
            speed = config.motion.speed_m_s
            rposc = _round_trips(robot, lambda i: robot.read_pose(), samples)
            movl = _round_trips(
                robot,
                lambda i: robot.move_to(transform(t=(STEP_M * (i % 2 == 0), 0.0, 0.0)) @ bMe, speed),
                samples,
                then=robot.wait_motion,
            )
        finally:
            robot.close()
    return {"RPOSC": rposc, "MOVL": movl}


def bench_jrc(config: CellConfig, samples: int = 50, seed: int = 0) -> dict[str, Any]:
    """RPOSC and MOVL round trips over a pty, unpaced and paced at the cell's baud rate."""
    line = config.jrc
    parity = {"even": "E", "odd": "O", "none": "N"}[line.parity]
    return {
        "line": f"{line.baud} {line.data_bits}{parity}{line.stop_bits}, {line.bits_per_character} bits per byte",
        "samples": samples,
        "pty": _measure(config, samples, pace=False, seed=seed),
        "paced_at_baud": _measure(config, samples, pace=True, seed=seed),
    }
