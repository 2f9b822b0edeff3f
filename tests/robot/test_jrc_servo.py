"""A whole assembly servo through the JRC link: the laser method on task 2, the loop
commanding a JRC backend behind the safety layer, over a pty (or the Ethernet server's
loopback TCP port), to the JRC emulator that moves the very SimulatedCell the camera
looks at."""

from contextlib import ExitStack

import pytest

from tests.jrc_fixtures import jrc_link, short_timer_cell
from vservo.core.cell.config import HostTransport
from vservo.core.robot.safety import SafetyLayer
from vservo.core.servo.step_policy import DividedPositionStep
from vservo.core.study.run import RunSettings, run_task
from vservo.core.study.tasks import TASKS

pytestmark = pytest.mark.usefixtures("no_leaked_threads")

# The emulated robot runs 1000 times faster than real time; the host's sampling period
# shrinks by as much, so one cycle is the thesis's 2 s in the emulator's time.
TIME_SCALE = 1000.0


@pytest.mark.slow
@pytest.mark.parametrize("transport", list(HostTransport))
def test_the_laser_servo_of_task_2_converges_through_the_jrc_link(transport):
    # No faults are injected here: the line's timers are ones a loaded host keeps (the test
    # timers' 50 ms timer A lapsed once under a load of 5 on two cores).
    config = short_timer_cell(jrc={"timer_a_s": 1.0, "retry_1": 10})
    motion = config.motion
    emulators = []

    with ExitStack() as links:

        def through_the_jrc(cell):
            robot, emulator = links.enter_context(jrc_link(cell, config, time_scale=TIME_SCALE, transport=transport))
            emulators.append(emulator)
            robot.servo(True)
            return SafetyLayer.from_config(robot, config)

        policy = DividedPositionStep(motion.divide_factor, motion.sampling_period_s, motion.speed_m_s)
        result = run_task(config, TASKS[2], RunSettings(method="laser"), robot=through_the_jrc, policy=policy)

    outcome = result.outcome
    assert outcome.converged, outcome.reason
    assert outcome.final_error_px <= 1.0
    assert result.final_translation_m < 5e-3 and result.final_rotation_rad < 0.03
    assert [s["stage"] for s in outcome.stages] == ["1A", "2", "3"]
    # Every step but the last cycle's went over the wire as one MOVL, each once.
    (emulator,) = emulators
    assert len(emulator.executed) == outcome.iterations - 1
    assert all(command.startswith("MOVL 0,50.00,0,") for command in emulator.executed)

    # The same steps on the direct simulator backend: the wire's resolution (0.001 mm,
    # 0.01 deg) changes the path by little.
    direct = run_task(
        config,
        TASKS[2],
        RunSettings(method="laser"),
        policy=DividedPositionStep(motion.divide_factor, motion.sampling_period_s, motion.speed_m_s),
    )
    assert direct.outcome.converged
    assert abs(result.path_length_m - direct.path_length_m) < 0.02 * direct.path_length_m
    assert abs(outcome.iterations - direct.outcome.iterations) < 0.1 * direct.outcome.iterations
