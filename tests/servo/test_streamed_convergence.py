"""A streamed servo calls the goal reached where the arm will stand, not where a late frame saw it.

The arm here is the simulator's free camera under velocity control: it moves at the last
twist streamed, without waiting, and every frame reaches the loop ``lag`` frame periods
after its exposure (a loaded host, a camera's latency), carrying the pose at its exposure
as a UR's RTDE history gives it. When the frames lag, the arm is still moving towards the
goal at the speed an older, larger error asked for while the loop looks at a frame within
the threshold: it passes through the goal and stops beyond it. The frames here are
projections of the true scene; the law is the laser method's, as the shipped demo job's.
"""

from collections import deque

import numpy as np
import pytest

from vservo.core.geometry.spatial import Matrix, exp_twist
from vservo.core.perception.measurement import Measurement, features_from_measurement
from vservo.core.servo.laws.base import feature_error_px
from vservo.core.servo.loop import LoopLimits, ProjectedPerception, run_servo
from vservo.core.servo.methods import LawSettings, build_law
from vservo.core.servo.step_policy import StreamedVelocity
from vservo.core.sim import Arm
from vservo.core.sim.free_camera import FreeCameraBackend
from vservo.core.sim.plant import SimulatedCell
from vservo.core.study.run import teach
from vservo.core.study.tasks import TASKS

FRAME_PERIOD_S = 1.0 / 30.0
THRESHOLD_PX = 1.0
# The shipped cell's streamed servo: the twist held 0.1 s at most, the error falling at 6 / s.
POLICY = StreamedVelocity(hold_s=0.1, gain=6.0, max_speed_m_s=0.1, max_rotation_rad_s=np.radians(45.0))


class LaggingStream(FreeCameraBackend):
    """A velocity-controlled free camera whose frames reach the loop ``lag`` frames late: the
    robot, and the loop's measurement source.

    Each measurement lets a frame period pass at the twist streamed last, exposes a frame
    and hands over the one exposed ``lag`` frames earlier (its time and flange pose those
    of its exposure). ``stop_motion`` stops the camera where it is, as a controller's stop
    does within a control period."""

    def __init__(self, cell: SimulatedCell, lag: int) -> None:
        super().__init__(cell)
        self.connect()
        self.servo(True)
        self.eVe = np.zeros(6)
        self.stops = 0
        self.frames: deque[Measurement] = deque(cell.measure() for _ in range(lag))

    def stream_twist(self, eVe: Matrix, hold_s: float) -> None:
        self.eVe = np.asarray(eVe, dtype=float)  # the next comes a frame later, well within hold_s

    def stop_motion(self) -> None:
        self.eVe = np.zeros(6)
        self.stops += 1

    def measure(self, look: bool = True) -> Measurement:
        self.cell.fly(self.cell.flange_readout() @ exp_twist(self.eVe * FRAME_PERIOD_S), FRAME_PERIOD_S)
        self.frames.append(self.cell.measure())
        return self.frames.popleft()


def servo_streamed(cell_config, task: int, lag: int) -> tuple[bool, int, float]:
    """Task ``task`` of the study streamed on frames ``lag`` late; the arm stopped after the
    loop ends, as a run's pick does: (converged, the loop's stops, the error where it stands)."""
    model, scene = cell_config.nominal, cell_config.plant().scene
    cell = SimulatedCell(cell_config, 0, Arm.NONE)
    cell.place_cube(TASKS[task].placement.bMo(scene.table_height_m, scene.cube.side_m))
    desired = teach(cell, TASKS[task].desired_cMo, model)
    cell.place_camera(TASKS[task].initial_cMo)
    arm = LaggingStream(cell, lag)
    law = build_law(model, LawSettings(method="laser", final_threshold_px=THRESHOLD_PX))
    perception = ProjectedPerception(model.camera, model.laser)
    outcome = run_servo(arm, law, desired, model, POLICY, LoopLimits(max_iterations=600), perception=perception, robot=arm)
    stops = arm.stops
    arm.stop_motion()
    standing = features_from_measurement(cell.measure(), model.camera, model.laser)
    return outcome.converged, stops, feature_error_px(standing, desired)


@pytest.mark.parametrize("task", [2, 3])
def test_frames_three_periods_late_stop_the_arm_to_look_again_and_it_stands_within_the_threshold(cell_config, task):
    # Without the second look the arm stood 1.59 px (task 2) and 1.71 px (task 3) off,
    # converged on a frame 0.33 px off while it passed through the goal.
    converged, stops, standing_px = servo_streamed(cell_config, task, lag=3)
    assert converged
    assert standing_px <= THRESHOLD_PX
    assert stops >= 1


@pytest.mark.parametrize("task", [2, 3])
def test_a_glide_in_on_frames_a_period_late_converges_without_a_stop(cell_config, task):
    converged, stops, standing_px = servo_streamed(cell_config, task, lag=1)
    assert converged
    assert stops == 0
    assert standing_px <= THRESHOLD_PX
