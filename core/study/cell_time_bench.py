"""``vservo bench cell-time``: a job's cell time through the JRC link, against the floor of its moves.

The job runs once in process, as ``vservo run --job NAME --backend jrc --seed N`` runs it:
through the JRC link to the emulator on a pseudo-terminal (BSC at the cell file's baud
rate), from the home pose, the part presented by the seed. Its cell time is the
emulator's count of what a real JRC would take (core/sim/controller_clock.py), split by
phase as the assembly splits it; the same seed reads the same figure on every run.

The floor is the least the moves the run made can take on that line: each move's
command (MOVL) crossing to the controller, then the longer of its motion (the emulator's
motion model: its translation at the commanded speed or its rotation at the controller's
rate) and the command's answer with the next wait's request, then the answer that
reports the motion's end (JWAIT's); plus one pose read (RPOSC), which the first move
needs. Anything else on the line (more pose reads, status reads, a wait's answer while
the arm still moves does not count) is what the measured figure has above the floor.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vservo.core.cell.config import CellConfig
from vservo.core.production.assembly import run_assembly
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.production.storage import Store
from vservo.core.servo.step_policy import DividedPositionStep
from vservo.core.sim.controller_clock import MOTION_COMMANDS, CountedExchange, Ended

POSE_READ = "RPOSC"


@dataclass(frozen=True)
class PhaseFloor:
    """One phase of a run: its moves, their motion time and link time in the floor, the
    floor, and the cell time measured."""

    phase: str
    moves: int
    motion_s: float
    link_s: float
    measured_s: float

    @property
    def floor_s(self) -> float:
        return self.motion_s + self.link_s


def move_floors(exchanges: list[CountedExchange]) -> list[tuple[int, float, float]]:
    """(the index of its command among ``exchanges``, motion s, link s) of each move, as the
    floor counts it (module docstring): the command's request, the longer of the motion
    and the command's answer with the next wait's request, the answer reporting its end."""
    floors = []
    for i, command in enumerate(exchanges):
        if command.name not in MOTION_COMMANDS:
            continue
        end = next((e for e in exchanges[i + 1 :] if e.ended is Ended.ENDED), None)
        wait_request_s, end_reply_s = (end.request_s, end.reply_s) if end is not None else (0.0, 0.0)
        overlapped_s = command.reply_s + wait_request_s  # crosses while the arm moves
        motion_s = command.motion_s
        floors.append((i, motion_s, command.request_s + max(overlapped_s - motion_s, 0.0) + end_reply_s))
    return floors


def phase_floors(exchanges: list[CountedExchange], started_s: float, by_phase_s: dict[str, float]) -> list[PhaseFloor]:
    """The floor of each phase of a run that began at ``started_s`` on the controller's
    clock and spent ``by_phase_s`` (in order) in its phases: each move counts in the phase
    whose span its command ends in; the first phase also counts one pose read."""
    edges = started_s + np.cumsum([0.0, *by_phase_s.values()])
    read = next((e for e in exchanges if e.name == POSE_READ and e.ends_s > started_s), None)
    moves = move_floors(exchanges)
    phases = []
    for k, (phase, measured_s) in enumerate(by_phase_s.items()):
        inside = [(motion_s, link_s) for i, motion_s, link_s in moves if edges[k] < exchanges[i].ends_s <= edges[k + 1]]
        read_s = read.request_s + read.reply_s if k == 0 and read is not None else 0.0
        phases.append(
            PhaseFloor(phase, len(inside), sum(m for m, _ in inside), read_s + sum(link for _, link in inside), measured_s)
        )
    return phases


def bench_cell_time(config: CellConfig, job_name: str = "demo", seed: int = 0, data: Path | None = None) -> dict:
    """Run ``job_name`` once through the JRC link (module docstring); the floor and the
    measured cell time, whole and by phase."""
    rig = simulated_rig(config, seed, backend="jrc")
    if isinstance(rig.policy, DividedPositionStep):
        rig.close()
        raise ValueError(
            "bench cell-time: the thesis's step policy waits out a sampling period each step, which no floor of "
            'the moves counts: use a cell with [motion] policy = "fast"'
        )
    emulator = rig.emulator
    assert emulator is not None  # the jrc backend's rig has one
    store = Store(data or Path(tempfile.mkdtemp(prefix="vservo-bench-cell-time-")))
    try:
        job = store.load_job(job_name)
        rig.robot.connect()
        rig.robot.servo(True)
        if rig.present_part is not None:
            rig.present_part(np.random.default_rng(seed))  # the part's arrival as `vservo run --seed` draws it
        started_s = emulator.cell_time_s()
        outcome = run_assembly(
            job,
            rig.robot,
            rig.gripper,
            rig.perception(),
            config.nominal,
            rig.policy,
            speed_m_s=config.motion.move_speed_m_s,
            measure_placement=rig.measure_placement,
            locator=rig.locator,
        )
        exchanges = list(emulator.clock.exchanges)
    finally:
        store.close()
        rig.close()
    by_phase = outcome.cell_time_by_phase_s or {}
    phases = phase_floors(exchanges, started_s, by_phase)
    floor_s = sum(p.floor_s for p in phases)
    measured_s = float(outcome.cell_time_s or 0.0)
    run = [e for e in exchanges if e.ends_s > started_s]
    return {
        "job": job_name,
        "seed": seed,
        "outcome": str(outcome.outcome),
        "baud": config.jrc.baud,
        "moves": sum(p.moves for p in phases),
        "pose_reads": sum(e.name == POSE_READ for e in run),
        "floor_s": round(floor_s, 3),
        "cell_time_s": round(measured_s, 3),
        "ratio": round(measured_s / floor_s, 3) if floor_s > 0 else None,
        "by_phase": {
            p.phase: {
                "moves": p.moves,
                "motion_s": round(p.motion_s, 3),
                "link_s": round(p.link_s, 3),
                "floor_s": round(p.floor_s, 3),
                "cell_time_s": round(p.measured_s, 3),
            }
            for p in phases
        },
    }
