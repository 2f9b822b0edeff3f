"""No stale frames: every servo cycle sees a frame exposed after the previous motion ended.

The camera here is a stream on the simulated cell: each frame is rendered from the TRUE
view at the moment it is exposed and stamped with the plant's time, then waits in a
queue of a fixed length before a read gets it, one frame period per read, as a camera's
buffer and a stream's delay hold frames. A plain read after a move therefore returns a
view from before the move. The robot is the simulator, which notes its clock whenever it
stands still (connected, or at the end of each motion); the test compares the exposure
time of every frame the loop used with the end of the motion before it, and the frame a
taught desired image came from with the end of the jog before the capture.
"""

from collections import deque

import numpy as np

from vservo.core.geometry.spatial import transform
from vservo.core.perception.camera_source import BaseSource, CameraSourceError, Frame, Size
from vservo.core.production.cell_controller import CellController
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.production.storage import Store
from vservo.core.servo.loop import Cycle
from vservo.core.sim.backend import SimulatedBackend
from vservo.core.sim.camera import SimulatedCamera
from vservo.core.sim.plant import SimulatedCell
from vservo.core.study.run import RunSettings, run_task
from vservo.core.study.tasks import TASKS

QUEUED_FRAMES = 2
FRAME_PERIOD_S = 0.04  # 25 frames per second


class QueuedCamera(BaseSource):
    """The simulated camera behind a queue of ``queued`` frames (a buffered, delayed stream).

    Each read exposes a new frame of the current view, lets a frame period pass on the
    plant's clock and returns the oldest frame in the queue: the one exposed ``queued``
    reads earlier. Its frames carry their true exposure times, so ``read_after`` can
    discard by them.
    """

    def __init__(self, cell: SimulatedCell, queued: int = QUEUED_FRAMES, period_s: float = FRAME_PERIOD_S) -> None:
        self.cell = cell
        self.period_s = period_s
        self.camera = SimulatedCamera(cell)
        self.queue: deque[Frame] = deque(self._expose() for _ in range(queued))
        self.last_read: Frame | None = None

    @property
    def image_size(self) -> Size:
        return self.camera.image_size

    def _expose(self) -> Frame:
        frame = self.camera.read()
        self.cell.pass_time(self.period_s)
        return frame

    def read(self) -> Frame:
        self.queue.append(self._expose())
        self.last_read = self.queue.popleft()
        return self.last_read

    def read_after(self, t_s: float) -> Frame:
        # The frame a read exposes is newer than t_s, so the queue's length plus one
        # reads always find one: the bound trips only for a t_s ahead of the plant's clock.
        for _ in range(len(self.queue) + 1):
            frame = self.read()
            if frame.timestamp_s >= t_s:
                return frame
        raise CameraSourceError(f"no frame exposed after {t_s:.3f} s in {len(self.queue) + 1} reads")


class StillSince(SimulatedBackend):
    """The simulated robot, noting its clock whenever it is known to stand still."""

    def __init__(self, cell: SimulatedCell) -> None:
        super().__init__(cell)
        self.still_since: list[float] = []

    def connect(self) -> None:
        super().connect()
        self.still_since.append(self.clock_s())

    def wait_motion(self, timeout_s: float | None = None) -> bool:
        finished = super().wait_motion(timeout_s)
        self.still_since.append(self.clock_s())
        return finished


def test_a_plain_read_after_a_move_returns_a_frame_from_before_it(cell_config):
    """The queued camera really is stale for a naive reader: the test below can fail."""
    cell = SimulatedCell(cell_config)
    robot = StillSince.enabled(cell)
    camera = QueuedCamera(cell)
    robot.move_by(transform(t=(0.005, 0.0, 0.0)), 0.05)
    assert robot.wait_motion()
    motion_ended_s = robot.still_since[-1]
    assert camera.read().timestamp_s < motion_ended_s
    assert camera.read_after(motion_ended_s).timestamp_s >= motion_ended_s


def test_every_cycle_uses_a_frame_exposed_after_the_previous_motion_ended(cell_config):
    robots: list[StillSince] = []
    cameras: list[QueuedCamera] = []
    used: list[tuple[float, float]] = []  # (exposure of the frame the cycle used, the robot still since)

    def robot(cell: SimulatedCell) -> StillSince:
        robots.append(StillSince.enabled(cell))
        return robots[-1]

    def camera(cell: SimulatedCell) -> QueuedCamera:
        cameras.append(QueuedCamera(cell))
        return cameras[-1]

    def check(cycle: Cycle) -> None:
        used.append((cameras[0].last_read.timestamp_s, robots[0].still_since[-1]))

    result = run_task(
        cell_config,
        TASKS[1],
        RunSettings(method="laser", features="rendered"),
        seed=0,
        on_cycle=check,
        robot=robot,
        camera=camera,
    )
    assert result.outcome.converged, result.outcome.reason
    assert len(used) == result.outcome.iterations > 10
    stale = [(i, exposed, still) for i, (exposed, still) in enumerate(used) if exposed < still]
    assert not stale, f"{len(stale)} of {len(used)} cycles used a frame exposed before the motion ended: {stale[:3]}"


def test_the_desired_image_is_captured_from_where_the_jog_stopped(cell_config, tmp_path):
    rig = simulated_rig(cell_config, seed=3)
    rig.camera = camera = QueuedCamera(rig.cell)
    store = Store(tmp_path / "data")
    controller = CellController(rig, store, seed=3)
    try:
        demo = store.load_job("demo")
        controller.begin_teach()
        controller.move_to(demo.start_bMe)
        controller.move_to(demo.taught_bMe)  # the queue still holds views of the start pose
        stopped_s = rig.robot.clock_s()
        desired = controller.capture_desired()
    finally:
        controller.close()
        store.close()
    assert camera.last_read.timestamp_s >= stopped_s
    np.testing.assert_allclose(desired.corners_px, demo.desired.corners_px, atol=0.05)
