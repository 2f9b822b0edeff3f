"""The simulated cell's rig: the simulator's devices behind the same interfaces as a real cell's.

The robot behind the safety layer (the kinematic simulator itself, or the JRC link over a
pseudo-terminal to the JRC emulator moving that same simulator), its vacuum cup (the
simulator's, or through the emulator's I/O when the cell file wires it there), the
synthetic camera and the detectors on the NOMINAL camera and laser. The simulator's
truth is reached only through ``measure_placement`` (the gauge that says where a
released part ended), ``present_part`` and ``place_part`` (a new part arriving on the
table) and ``lay_board`` (the checkerboard laid on it): what a test cell provides that
no JRC reads.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import replace

import numpy as np

from vservo.core.cell.config import ROBOT_BACKENDS, CellConfig
from vservo.core.production.assembly import PlacementReport
from vservo.core.production.locate import PartLocator
from vservo.core.production.rig import Rig, extractor_for
from vservo.core.robot.gripper import NoVacuum, VacuumGripper
from vservo.core.robot.jrc import JrcBackend
from vservo.core.robot.jrc_vacuum import JrcVacuum
from vservo.core.robot.safety import SafetyLayer
from vservo.core.servo.step_policy import PositionStepPolicy, step_policy_from_config
from vservo.core.sim.backend import SimulatedBackend
from vservo.core.sim.camera import SimulatedCamera
from vservo.core.sim.jrc_emulator import JrcEmulator
from vservo.core.sim.part_feeder import place_part as put_part
from vservo.core.sim.part_feeder import present_part as feed_part
from vservo.core.sim.plant import SimulatedCell
from vservo.core.sim.vacuum import SimulatedVacuum

# The emulated JRC moves this many times faster than a real one, and the host waits out
# its sampling period as much faster: a 2 s step of the thesis's cell takes 50 ms on screen.
JRC_TIME_SCALE = 40.0


def simulated_rig(
    config: CellConfig,
    seed: int | None = None,
    backend: str | None = None,
    jrc_time_scale: float = JRC_TIME_SCALE,
    time_scale: float | None = None,
) -> Rig:
    """The simulated cell's devices; ``backend`` (default: the cell file's [robot]
    backend) "sim" drives the simulator directly, "jrc" through the JRC link and an
    emulated JRC on a pseudo-terminal (or, for [jrc] transport = "ethernet", as an
    Ethernet server on a loopback TCP port). ``time_scale``: the "sim" robot's moves take
    their cell time divided by it on the wall clock (1: the real cell's pace; None: as
    fast as the host computes them)."""
    backend = backend or config.robot_backend
    if backend not in ROBOT_BACKENDS:
        raise ValueError(f"robot backend {backend!r}: choose one of {', '.join(ROBOT_BACKENDS)}")
    cell = SimulatedCell(config, seed)
    taught_bMo = config.plant().scene.cube.bMo

    def measure_placement() -> PlacementReport:
        placement = cell.ground_truth_placement()
        return PlacementReport(placement.inside, 1000.0 * placement.error_m)

    policy = step_policy_from_config(config.motion)
    emulator = None
    vacuum = config.vacuum_device
    gripper: VacuumGripper = NoVacuum() if vacuum.device == "none" else SimulatedVacuum(cell)
    if backend == "sim":
        if vacuum.device == "jrc_io":
            raise ValueError(f"{config.source}: vacuum.device = 'jrc_io' needs the JRC: use the jrc backend")
        robot = SafetyLayer.from_config(SimulatedBackend(cell, time_scale), config)
    else:
        if not isinstance(policy, PositionStepPolicy):
            raise ValueError(f'{config.source}: the JRC takes position steps; set [motion] mode = "position_steps"')
        emulator = JrcEmulator(cell, config.jrc, time_scale=jrc_time_scale, vacuum=vacuum, plc=config.plc)
        # The cell clock is the emulator's count of what the real JRC would take (each
        # motion's duration, each exchange's bytes at the line's rate), not the wall clock.
        jrc = JrcBackend(
            emulator.start_for(replace(config.jrc, time_scale=jrc_time_scale)), controller_clock=emulator.cell_time_s
        )
        robot = SafetyLayer.from_config(jrc, config)
        if vacuum.device == "jrc_io":
            gripper = JrcVacuum(jrc, *vacuum.jrc_io())
    # The emulator's thread moves the plant: the table changes between its commands.
    lock = emulator.lock if emulator is not None else nullcontext()

    def present_part(rng: np.random.Generator) -> None:
        with lock:
            feed_part(cell, taught_bMo, rng)

    def lay_board(laid: bool) -> None:
        with lock:
            cell.lay_board(laid)

    def place_part(x_m: float, y_m: float, yaw_rad: float) -> None:
        with lock:
            put_part(cell, x_m, y_m, yaw_rad)

    return Rig(
        config=config,
        robot=robot,
        gripper=gripper,
        camera=SimulatedCamera(cell),
        extractor=extractor_for(config),
        policy=policy,
        measure_placement=measure_placement,
        present_part=present_part,
        lay_board=lay_board,
        place_part=place_part,
        locator=PartLocator.from_config(config),
        cell=cell,
        emulator=emulator,
    )
