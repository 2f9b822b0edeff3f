"""A test cell with short JRC timers, and a JRC link to an emulator of a simulated cell."""

from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from tests.cell.test_config import default_data
from vservo.core.cell.config import CellConfig, StepPolicyKind, parse_cell, write_thesis_policy_cell
from vservo.core.robot.jrc import JrcBackend
from vservo.core.sim.jrc_emulator import FaultPlan, JrcEmulator

# Timers short enough for tests, long enough for a loaded 2-core machine.
TEST_LINE = {"timer_a_s": 0.05, "timer_b_s": 0.5, "retry_1": 3, "retry_2": 3, "jwait_slice_s": 0.2}
TIME_SCALE = 50.0


def with_the_thesis_policy(config: CellConfig) -> CellConfig:
    """A cell servoed with the thesis's step policy: hundreds of servo cycles, one per 2 s,
    long enough for a test to act in the middle of a servo (the shipped fast policy's takes
    a handful)."""
    return replace(config, motion=replace(config.motion, policy=StepPolicyKind.THESIS))


def thesis_policy_cell_file(folder: Path) -> str:
    """The shipped cell file on the thesis's step policy, for a test's child process
    (`vservo run`, `vservo virtual-cell`, `vservo serve`)."""
    return str(write_thesis_policy_cell(folder))


def short_timer_cell(**sections):
    """The shipped cell with the test timers, and any table's keys replaced: safety={...}."""
    data = default_data()
    data["jrc"].update(TEST_LINE)
    for name, keys in sections.items():
        data[name].update(keys)
    return parse_cell(data, "test cell")


@contextmanager
def jrc_link(cell, config, faults=FaultPlan(), time_scale=TIME_SCALE):
    """(a connected JrcBackend, the emulator of ``cell`` it talks to over a pty, its I/O
    wired as the cell file's [vacuum] says)."""
    with JrcEmulator(cell, config.jrc, faults, time_scale, vacuum=config.vacuum_device) as emulator:
        robot = JrcBackend(config.jrc, emulator.device)
        robot.connect()
        try:
            yield robot, emulator
        finally:
            robot.close()
