"""The link soak: thousands of incremental moves over a pseudo-terminal (or the Ethernet
server's TCP port) with faults injected.

The host (a JrcBackend) sends IMOV after IMOV to the JRC emulator, which injects
faults of every kind at the given rate. A fault the link recovers from leaves no trace
but its counters; one it cannot (a silence beyond the retries, an alarm or a pendant
hold in the middle of a move) is reported as a RobotError, and the soak then does what
an operator's recovery procedure would: wait for the pendant hold to be released, reset
the alarm, release the command hold, turn servo power on, read where the robot is and
send an IMOV for whatever of the move is missing.

What it proves: no move lost (the final pose is the start plus the sum of the commanded
increments), none carried out twice (every command the JRC accepted was sent
once), every fault either recovered or reported. A fault of the link (corrupted BCC,
dropped or delayed bytes, missing ACK, NAK, a silence; over TCP a dropped connection,
a late answer, a silence) counts as recovered when the host
command it struck still returned its reply, as reported when that command raised; an
alarm or a pendant hold counts as reported when its move raised (MotionStopped, or a
LinkError whose recovery then found the alarm or the hold). The
increments are translations; the orientation never changes.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from vservo.core.cell.config import CellConfig, HostTransport, JrcLineConfig
from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix, pose_error, transform
from vservo.core.robot.backend import MotionStopped, RobotError
from vservo.core.robot.ethernet_link import EthernetLink
from vservo.core.robot.jrc import JrcBackend, Reply
from vservo.core.sim.jrc_emulator import ETHERNET_FAULT_KINDS, FAULT_KINDS, MOTION_FAULTS, FaultInjector, FaultPlan, JrcEmulator
from vservo.core.sim.plant import SimulatedCell

SPEED_M_S = 0.05
MAX_STEP_MM = 2.0
PULL_BACK = 0.05  # each increment pulls a twentieth of the way back to the start, so the walk stays near it
AT_TARGET_MM = 0.002  # RPOSC's 0.001 mm resolution, and the IK's 1e-4 mm
# The JRC's IK leaves up to 1e-4 mm per move, and IMOV starts from where the arm is:
# over thousands of moves the flange may drift this far from the exact sum.
ON_PATH_MM = 0.02
MAX_RECOVERY_ATTEMPTS = 30


class SoakFailure(VservoError, RuntimeError):
    """The soak could not bring the robot back on its path."""


def soak_increments(moves: int, seed: int) -> Matrix:
    """(moves, 3) increments in mm, 3 decimals, every one different: a walk that stays
    within a few centimetres of its start."""
    rng = np.random.default_rng(seed)
    increments: list[Matrix] = []
    offset, seen = np.zeros(3), set()
    while len(increments) < moves:
        step = np.round(rng.uniform(-MAX_STEP_MM, MAX_STEP_MM, 3) - PULL_BACK * offset, 3)
        key = tuple(step)
        if key in seen or not np.any(step):
            continue
        seen.add(key)
        increments.append(step)
        offset = offset + step
    return np.array(increments)


class _AccountedJrc(JrcBackend):
    """A JrcBackend that files the emulator's link faults under the command they struck."""

    def __init__(self, line: JrcLineConfig, port: str | None, faults: FaultInjector) -> None:
        super().__init__(line, port)
        self.faults = faults
        self.recovered: Counter[str] = Counter()
        self.reported: Counter[str] = Counter()

    def command(self, text: str, reply_wait_s: float | None = None) -> Reply:
        before = Counter(self.faults.injected)
        try:
            reply = super().command(text, reply_wait_s)
        except RobotError:
            self.reported.update(self._link_faults_since(before))
            raise
        self.recovered.update(self._link_faults_since(before))
        return reply

    def _link_faults_since(self, before: Counter[str]) -> Counter[str]:
        new = self.faults.injected - before
        return Counter({kind: n for kind, n in new.items() if kind not in MOTION_FAULTS})


def _link_counters(robot: JrcBackend) -> dict[str, int]:
    """The serial link's recoveries, or how many connections the Ethernet link made."""
    if isinstance(robot.link, EthernetLink):
        return {"connections": robot.link.connections}
    return robot.station.counters.as_dict()


class _Soak:
    def __init__(self, robot: _AccountedJrc, emulator: JrcEmulator) -> None:
        self.robot, self.emulator = robot, emulator
        self.reported: Counter[str] = Counter()  # errors by kind of cause
        self.sent: Counter[str] = Counter()  # every motion command the host sent once, by text
        self.recovery_moves = 0

    def imov(self, increment_mm: Matrix) -> None:
        robot = self.robot
        try:
            robot.move_by(transform(t=increment_mm / 1000.0), SPEED_M_S)
        finally:
            self.sent[robot.last_command] += 1
        if not robot.wait_motion():
            raise MotionStopped(f"stopped before the end of its move: {robot.status().describe()}")

    def report(self, exc: RobotError) -> None:
        cause = type(exc).__name__
        self.reported[cause] += 1

    def recover(self, target_mm: Matrix) -> None:
        """Bring the flange to target_mm (the sum of the moves so far), whatever happened."""
        robot = self.robot
        for _ in range(MAX_RECOVERY_ATTEMPTS):
            try:
                status = robot.status()
                if status.alarm:
                    robot.reset_alarms()
                if "command hold" in status.detail:
                    robot.hold(False)
                if status.held and "command hold" not in status.detail:
                    time.sleep(0.01)  # a pendant hold: only the operator releases it
                    continue
                if not status.servo_on or status.alarm:
                    robot.servo(True)
                if status.running and not robot.wait_motion():
                    continue
                missing_mm = target_mm - robot.read_pose()[:3, 3] * 1000.0
                if np.max(np.abs(missing_mm)) <= AT_TARGET_MM:
                    return
                self.recovery_moves += 1
                self.imov(np.round(missing_mm, 3))
            except RobotError as exc:
                self.report(exc)
        raise SoakFailure(
            f"the robot did not get back to {target_mm.round(3).tolist()} mm after {MAX_RECOVERY_ATTEMPTS} attempts"
        )


def run_soak(
    config: CellConfig,
    moves: int = 2000,
    fault_rate: float = 0.05,
    seed: int = 0,
    time_scale: float = 50.0,
    timer_a_s: float = 0.1,
    timer_b_s: float = 1.0,
    on_move: Callable[[], None] | None = None,
    transport: HostTransport = HostTransport.SERIAL,
) -> dict[str, Any]:
    """Soak the link: ``moves`` IMOVs with faults at ``fault_rate`` per exchange, over
    ``transport`` (its own fault kinds).

    The timers are shortened (the soak tests recovery, not patience); the emulator runs
    ``time_scale`` times faster than real time. ``on_move()`` is called after each move.
    """
    # The line knows the emulator's pace: over Ethernet the host reads the status that often.
    line = replace(config.jrc, timer_a_s=timer_a_s, timer_b_s=timer_b_s, time_scale=time_scale)
    cell = SimulatedCell(config, seed)
    increments = soak_increments(moves, seed)
    started = time.monotonic()
    motion_faults_reported: Counter[str] = Counter()
    moves_with_reports = moves_off_path = 0
    kinds = ETHERNET_FAULT_KINDS if transport is HostTransport.ETHERNET else FAULT_KINDS
    emulator = JrcEmulator(cell, line, FaultPlan(fault_rate, seed, kinds), time_scale)
    robot = _AccountedJrc(emulator.start_for(replace(line, transport=transport)), None, emulator.faults)
    try:
        robot.connect()
        soak = _Soak(robot, emulator)
        soak.recover(robot.read_pose()[:3, 3] * 1000.0)  # servo on, wherever the arm is
        bMe_start = cell.jrc_arm.fk(cell.state.q)  # evaluation: the emulator's own pose
        target_mm = bMe_start[:3, 3] * 1000.0
        for increment in increments:
            target_mm = target_mm + increment
            injected_before = Counter(emulator.faults.injected)
            try:
                soak.imov(increment)
            except RobotError as exc:
                soak.report(exc)
                soak.recover(target_mm)
                moves_with_reports += 1
                new = emulator.faults.injected - injected_before
                motion_faults_reported.update({kind: new[kind] for kind in MOTION_FAULTS})
            # Evaluation: the emulator's own pose, not what the link reports.
            off = np.abs(cell.jrc_arm.fk(cell.state.q)[:3, 3] * 1000.0 - target_mm).max()
            moves_off_path += int(off > ON_PATH_MM)
            if on_move is not None:
                on_move()
        counters = _link_counters(robot)
    finally:
        robot.close()
        emulator.stop()
    bMe_end = cell.jrc_arm.fk(cell.state.q)
    translation_error_m, rotation_error_rad = pose_error(bMe_end, transform(bMe_start[:3, :3], target_mm / 1000.0))
    accepted = Counter(emulator.executed)
    injected = emulator.faults.injected
    reported = robot.reported + motion_faults_reported
    return {
        "moves": moves,
        "fault_rate": fault_rate,
        "exchanges": emulator.exchanges,
        "transport": str(transport),
        "faults_injected": {kind: injected[kind] for kind in kinds},
        "faults_injected_total": sum(injected.values()),
        "faults_recovered": {kind: robot.recovered[kind] for kind in kinds},
        "faults_reported": {kind: reported[kind] for kind in kinds},
        "faults_unaccounted": sum((injected - robot.recovered - reported).values()),
        "moves_with_reported_errors": moves_with_reports,
        "errors_reported": dict(soak.reported),
        "recovery_moves": soak.recovery_moves,
        "moves_off_path": moves_off_path,
        "commands_accepted_twice": sum(max(0, accepted[text] - soak.sent[text]) for text in accepted),
        "final_pose_error_mm": round(translation_error_m * 1000.0, 6),
        "final_pose_error_deg": round(float(np.degrees(rotation_error_rad)), 6),
        "link_counters": counters,
        "timers_s": {"a": timer_a_s, "b": timer_b_s},
        "time_scale": time_scale,
        "elapsed_s": round(time.monotonic() - started, 2),
    }
