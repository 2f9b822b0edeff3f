"""A test cell with short JRC timers, and a JRC link to an emulator of a simulated cell,
over a pseudo-terminal (BSC) or a loopback TCP port (the Ethernet server)."""

from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from tests.cell.test_config import default_data
from vservo.core.cell.config import CellConfig, HostTransport, StepPolicyKind, parse_cell, write_thesis_policy_cell
from vservo.core.robot.jrc import JrcBackend
from vservo.core.sim.jrc_emulator import FaultPlan, JrcEmulator

# Timers short enough for tests, long enough for a loaded 2-core machine.
TEST_LINE = {"timer_a_s": 0.05, "timer_b_s": 0.5, "retry_1": 3, "retry_2": 3, "jwait_slice_s": 0.2}
# Over TCP nothing is repeated: one timer A, as long as the serial line's retries together.
ETHERNET_TIMER_A_S = 0.5
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
def jrc_link(cell, config, faults=FaultPlan(), time_scale=TIME_SCALE, transport=HostTransport.SERIAL):
    """(a connected JrcBackend, the emulator of ``cell`` it talks to over a pty or a
    loopback TCP port, as ``transport`` says, its I/O wired as the cell file's [vacuum] says)."""
    emulator = JrcEmulator(cell, config.jrc, faults, time_scale, vacuum=config.vacuum_device)
    line = emulator.start_for(replace(config.jrc, transport=transport, time_scale=time_scale))
    if transport is HostTransport.ETHERNET:
        # The host reads the status every status_poll_s of the emulator's time, as a
        # virtual cell's file says (its time_scale); a pendant hold then lasts many reads.
        line = replace(line, timer_a_s=ETHERNET_TIMER_A_S)
    robot = JrcBackend(line, controller_clock=emulator.cell_time_s)
    try:
        robot.connect()
        yield robot, emulator
    finally:
        robot.close()
        emulator.stop()
