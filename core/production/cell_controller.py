"""The controller process's core: the cell's state machine, its commands and what it publishes.

It owns the rig (robot backend, vacuum, camera, vision) and the store. Commands come
from one operator at a time (the channel and the app decide who that is); every command
is checked against the current phase, and a refused one raises CommandRefused with the
reason, never moves the robot. The phases (vservo.core.production.assembly.Phase):

    idle --teach--> teaching --save/cancel--> idle   (teaching: jog, suction, test pick, present part)
    idle --manual--> manual --leave--> idle          (manual: jog and typed moves, nothing else)
    idle --start--> servoing (stages) --> picking --> placing --> done | fault
    idle --commission--> commissioning --> idle | fault
    any  --estop--> e-stopped --reset--> idle

The controller keeps the guards, the publishing, the live view, jogging, the part fixture,
e-stop and reset; it owns three parts, each in its own module, and delegates to them once
its guards let a command through: teaching (teaching_session.py), an assembly run
(assembly_run.py, the run thread's body) and commissioning (commissioning_session.py,
which measures the cell's model in the background; Apply writes the commissioned cell file
and the controller runs on it from then on: the jobs are retargeted as every run starts).

Who may change the state. The published state (``state``, a frozen ControllerState) is
replaced only by ``update_with`` (``update`` is its shorthand), from any thread: command
threads, the run thread, the commissioning thread, the e-stop's. It takes the state lock,
computes the changes from the state it holds, replaces the state and hands it to the
subscribers, in that order for every change, so the last state published is the state.
The state lock is held for nothing else: never across I/O or a move, never around another
lock but the subscribers' own (a subscriber must not block, nor call the controller back);
what a change needs from the robot (``robot_readout``) is read before it is taken.
Commands are serialised by the command lock (an RLock, so a command may call another):
only a command under it starts a thread or changes what the threads share (the rig's
model, the run thread, the teach draft). A thread's results (the run's ``last_outcome``,
a commissioning waiting for Apply) are read by commands only once it has ended, which
the guards ensure. The e-stop never takes the command lock: it sets the e-stop latch,
which every thread reads, and changes the state like any other thread.

E-stop acts at once from the caller's thread: it sends hold to the robot before it
returns, so a move the assembly thread has not yet sent is refused by the robot itself
and the arm stops within the control cycle under way. Motion needs an explicit enable:
servo power is switched on by ``start`` or a jog and a reset never restarts a run.

Subscribers get ControllerState snapshots and camera frames with the features seen in
them; they are called from the cell controller's threads and must not block.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.cell.scene import arrival
from vservo.core.geometry.spatial import Matrix, exp_twist
from vservo.core.perception.camera_source import CameraSourceError, Frame
from vservo.core.perception.features import DesiredImage, ImageFeatures
from vservo.core.production.assembly import AssemblyOutcome
from vservo.core.production.assembly_run import AssemblyRun, retargeted_job
from vservo.core.production.commissioning_session import CommissioningSession, commissioned_path, is_shipped_cell
from vservo.core.production.controller_state import EStopLatch, FrameView, TeachDraft
from vservo.core.production.fixture import FixtureError
from vservo.core.production.jobs import Job, JobError, TaughtModel
from vservo.core.production.manual_moves import home_bMe, move_refused, survey_bMe
from vservo.core.production.placement_check import CheckView
from vservo.core.production.protocol import CommandRefused, ControllerState, Phase, RunFigures
from vservo.core.production.protocol.catalogue import Refusal
from vservo.core.production.protocol.commands import PART_SIDE_M
from vservo.core.production.protocol.state import HAND_MOVES, STANDING
from vservo.core.production.retarget import taught_part_on_table
from vservo.core.production.rig import Rig
from vservo.core.production.storage import Store, validate_part_id
from vservo.core.production.teaching_session import TeachingSession
from vservo.core.robot.backend import RobotError, apply_increment
from vservo.core.robot.safety import SafetyLayer

if TYPE_CHECKING:  # commissioning's calibration (torch, the board finder) is imported when a cell is commissioned
    from vservo.core.production.commissioning import CommissionSettings, Step

# The values, and the words of the parts, callers import from here.
__all__ = [
    "HOLD_CONFIRM_S",
    "JOG_SPEED_M_S",
    "PART_SIDE_M",
    "CellController",
    "CommandRefused",
    "ControllerState",
    "FrameView",
    "TeachDraft",
    "commissioned_path",
    "is_shipped_cell",
    "run_job_once",
]

log = logging.getLogger("vservo.controller")

JOG_SPEED_M_S = 0.02
HOLD_CONFIRM_S = 1.0  # an e-stop's hold unanswered this long is reported as not confirmed

T = TypeVar("T")


def _part_origin(centre_mm: Sequence[float], turn_deg: float) -> tuple[float, float]:
    """The part's frame O (a top-face corner), x and y in m, for its top face's centre at
    ``centre_mm`` turned ``turn_deg``."""
    values = [*np.asarray(centre_mm, float).ravel(), float(turn_deg)]
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise CommandRefused(f"a part is presented at a finite X, Y (mm) and turn (deg), got {values}", Refusal.OUT_OF_RANGE)
    turn = np.deg2rad(turn_deg)
    half = PART_SIDE_M / 2
    corner = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]]) @ [half, half]
    x, y = np.asarray(values[:2]) / 1000.0 - corner
    return float(x), float(y)


def _send_hold(robot: SafetyLayer, why: str) -> tuple[str, bool]:
    """Send the e-stop's hold to the robot: what the state should say of it, and whether the robot holds."""
    try:
        robot.emergency_stop(why)
        detail, held = f"{why}: robot held", True
    except RobotError as exc:
        detail, held = f"{why}: hold could not be sent ({exc}); use the pendant's e-stop", False
    except Exception as exc:  # a bug must not hide that the hold was not sent
        log.exception("e-stop: sending the hold failed")
        detail, held = f"{why}: hold could not be sent ({exc!r}); use the pendant's e-stop", False
    log.warning(detail)
    return detail, held


class _WorkThread(threading.Thread):
    """A daemon thread that drives the cell, whose end is an Event rather than the thread's
    own lock: a Ctrl-C that interrupts ``join()`` leaves CPython 3.11 taking a running
    thread for stopped (``Thread._wait_for_tstate_lock``), and the process would then exit
    under a run still moving the robot, its end never on record."""

    def __init__(self, target: Callable[..., None], args: tuple, name: str) -> None:
        super().__init__(target=target, args=args, name=name, daemon=True)
        self.finished = threading.Event()

    def run(self) -> None:
        try:
            super().run()
        finally:
            self.finished.set()


class CellController:
    def __init__(self, rig: Rig, store: Store, *, seed: int = 0, cycle_period_s: float = 0.0) -> None:
        self.rig = rig
        self.store = store
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self.cycle_period_s = cycle_period_s  # a floor on the servo cycle, so a fast simulator can be watched
        self._lock = threading.RLock()  # the command lock: one command at a time; the camera and robot are shared
        self._state_lock = threading.Lock()  # the state lock: held only to replace and publish the state
        # The first state is made here, before any thread or subscriber exists.
        self._state = ControllerState(
            backend=rig.robot.name,
            robot=rig.config.arm,
            can_present_part=rig.present_part is not None,
            cell_file=rig.config.source,
        )
        # The joints drawn in 3D: a real JRC reports the flange pose; the safety layer's arm
        # model's inverse kinematics, from the last joints shown, turns it into an arm to draw.
        self._shown_q = rig.config.home_q.copy()
        self._estop = EStopLatch()
        self._jogging = threading.Event()  # a jog or a gizmo move is under way
        self._run_thread: _WorkThread | None = None  # an assembly run's, or commissioning's
        self._work = "an assembly run"  # what the thread does, for the refusals while it runs
        self._started_by_line = False  # the run under way was started by the PLC or OPC UA
        self._desired: DesiredImage | None = None  # drawn over the live image
        self._teaching = TeachingSession(rig, store, self)
        self._commissioning = CommissioningSession(rig, store.root, seed, self, self._estop)
        self.last_outcome: AssemblyOutcome | None = None
        self.state_subscribers: list[Callable[[ControllerState], None]] = []
        self.frame_subscribers: list[Callable[[FrameView], None]] = []
        interrupted = store.close_unfinished_runs()
        if interrupted:
            log.warning("runs %s were found unfinished (their controller died): marked interrupted", interrupted)
        self.rig.robot.connect()
        self._state = replace(self._state, **self.robot_readout())  # the first state shows the real pose
        status = self.rig.robot.status()
        if status.held:  # an earlier session's e-stop or fault: motion only after an explicit reset
            self._state = replace(
                self._state,
                phase=Phase.FAULT,
                detail=f"the robot is {status.describe()} since before this controller started: Reset releases it",
            )

    # -- publishing ------------------------------------------------------------------

    @property
    def state(self) -> ControllerState:
        return self._state

    def update(self, **changes: Any) -> None:
        """Replace these fields of the state and publish it (the state rule: the module's docstring)."""
        self.update_with(lambda state: changes)

    def update_with(self, changes: Callable[[ControllerState], dict[str, Any] | None]) -> None:
        """Replace the fields ``changes`` computes from the state as it is (None: nothing to
        change) and publish it: the one writer of the state. ``changes`` runs under the state
        lock and must be quick: no I/O."""
        with self._state_lock:
            fields = changes(self._state)
            if fields is None:
                return
            self._state = replace(self._state, time_s=time.time(), **fields)
            for subscriber in list(self.state_subscribers):
                subscriber(self._state)

    def publish_frame(self, view: FrameView) -> None:
        for subscriber in list(self.frame_subscribers):
            subscriber(view)

    def robot_readout(self, bMe: Matrix | None = None, vacuum: bool = True, q: Matrix | None = None) -> dict[str, Any]:
        """Flange pose (unless given, where the robot stands: read only when not known,
        SafetyLayer.pose), joints (``q``: the arm model's joints of a given bMe, which a servo
        cycle has solved already) and (``vacuum``: a JRC's I/O read) the vacuum sensor for the state."""
        try:
            bMe = self.rig.robot.pose() if bMe is None else bMe
            holding = {"holding_part": self.rig.gripper.holding()} if vacuum else {}
        except RobotError as exc:  # the link is down: the state says so, the last readout stands
            log.warning("robot readout failed: %s", exc)
            return {}
        return {"bMe": bMe, "q": self._joints_shown(bMe, q), **holding}

    def _joints_shown(self, bMe: Matrix, q: Matrix | None) -> Matrix:
        if self.rig.cell is not None:  # the simulated cell's plant: its true joints
            return self.rig.cell.state.q
        if q is not None and np.all(np.isfinite(q)):  # solved for this bMe by the caller: no second IK
            self._shown_q = np.asarray(q, dtype=float)
            return self._shown_q
        try:
            self._shown_q = self.rig.robot.arm.ik(bMe, self._shown_q, tolerance_m=1e-6, tolerance_rad=1e-5, restarts=0).q
        except UnreachableTarget:
            log.debug("no joints found for the reported flange pose; the 3D arm keeps its last pose")
        return self._shown_q

    def look(self, fresh: bool = False) -> tuple[Frame, ImageFeatures]:
        """Grab one frame, detect in it and publish it (the live view while no run owns the camera).

        fresh: a frame exposed after this moment, never one a camera's buffer held through
          the last jog (docs/vision.md, "No stale frames"). Between commands the robot
          stands still, so such a frame shows where it stopped: what a capture needs, at
          the cost of the camera's latency, which the live view does not pay.
        """
        with self._lock:
            if self.running:
                raise CommandRefused(f"{self._work} owns the camera", Refusal.BUSY)
            camera = self.rig.camera
            frame = camera.read_after(self.rig.robot.clock_s()) if fresh else camera.read()
        features, _ = self.rig.extractor.extract(frame.image)
        self.publish_frame(FrameView(frame, features.corners_px, features.laser_spot_px, self._desired, None))
        return frame, features

    # -- guards ------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self._run_thread is not None and not self._run_thread.finished.is_set()

    @property
    def moved_by_apps(self) -> bool:
        """A run an app started, or a jog, is moving the robot: the channel holds it if its
        last app goes away. A run the line started (PLC, OPC UA) goes on without a page: the
        line's own client watches it, and a monitor closing must not stop the line."""
        return (self.running and not self._started_by_line) or self._jogging.is_set()

    def _require(self, *phases: Phase, kind: Refusal = Refusal.NOT_NOW) -> None:
        """Refuse unless the cell is in one of ``phases`` (``kind``: how the refusal is explained)."""
        if self._estop.is_set():
            raise CommandRefused("e-stop is active: reset it first", Refusal.ESTOP_ACTIVE)
        if self.running:
            raise CommandRefused(f"{self._work} is under way", Refusal.BUSY)
        if self._state.phase not in phases:
            allowed = " or ".join(p.value for p in phases)
            raise CommandRefused(f"not possible while {self._state.phase.value} (only when {allowed})", kind)

    def _enable_motion(self) -> None:
        status = self.rig.robot.status()
        if status.alarm:
            raise CommandRefused(f"the robot is in alarm: {status.detail or 'reset the alarm on the JRC'}", Refusal.ROBOT_ALARM)
        if not status.servo_on:
            self.rig.robot.servo(True)

    def _start_work(self, work: str, target: Callable[..., None], args: tuple, name: str) -> None:
        """Start the thread of a run or a commissioning (under the command lock, motion enabled)."""
        self._work = work
        self._run_thread = _WorkThread(target, args, name)
        self._run_thread.start()

    # -- manual mode, jogging, Home and Survey, the part fixture --------------------------

    def enter_manual(self) -> None:
        """Manual mode: the operator moves the arm by hand (jogs, typed moves) until leaving it."""
        with self._lock:
            self._require(Phase.IDLE, Phase.DONE)  # after a fault the robot is held: Reset first
            self.update(phase=Phase.MANUAL, detail="manual mode: jog or type a pose; Leave manual mode when done")

    def leave_manual(self) -> None:
        with self._lock:
            self._require(Phase.MANUAL)
            self.update(phase=Phase.IDLE, detail="manual mode left: ready")

    def go_home(self) -> None:
        """To the cell file's home joints on a joint-space path (manual_moves.py)."""
        self._joint_move_to(home_bMe(self.rig.robot.arm, self.rig.config), "home")

    def go_survey(self) -> None:
        """The camera straight over the table where parts are presented (manual_moves.py)."""
        target = survey_bMe(self.rig.config)
        if target is None:
            raise CommandRefused("the cell file has no [board]: no survey pose is known", Refusal.NOT_NOW)
        self._joint_move_to(target, "the survey pose: the camera over the table")

    def move_joint(self, bMe_target: Matrix) -> None:
        """A typed target on a joint-space path, where the straight line cannot go (manual or teaching)."""
        with self._lock:
            self._require(*HAND_MOVES, kind=Refusal.NOT_MANUAL)
            self._joint_move_to(bMe_target, "the target, on a joint path")

    def _joint_move_to(self, bMe_target: Matrix, where: str) -> None:
        with self._lock:
            self._require(*STANDING)
            speed_m_s = self.rig.config.motion.move_speed_m_s
            self._move(lambda: self.rig.robot.move_joint(np.asarray(bMe_target, float), speed_m_s), bMe_target, speed_m_s)
            self.update(detail=f"arrived at {where}", **self.robot_readout())

    def _move(self, motion: Callable[[], None], bMe_target: Matrix, speed_m_s: float) -> None:
        """Carry out a hand move (motion enabled, the channel told the robot moves); a refusal by kind."""
        self._enable_motion()
        self._jogging.set()
        try:
            motion()
        except (RobotError, UnreachableTarget) as exc:
            raise move_refused(self.rig.robot, exc, np.asarray(bMe_target, float), speed_m_s) from exc
        finally:
            self._jogging.clear()

    def jog(self, translation_m: Matrix, rotation_rad: Matrix | Sequence[float] = (0.0, 0.0, 0.0), frame: str = "base") -> None:
        """Move the flange by a small step: translation and rotation (rad) in the base or tool frame."""
        with self._lock:
            self._require(*HAND_MOVES, kind=Refusal.NOT_MANUAL)
            step = np.concatenate([np.asarray(translation_m, float), np.asarray(rotation_rad, float)])
            if step.shape != (6,) or not np.all(np.isfinite(step)):
                raise CommandRefused(
                    f"a jog takes 3 finite translations and 3 rotations, got {step.tolist()}", Refusal.OUT_OF_RANGE
                )
            if frame not in ("base", "tool"):
                raise CommandRefused(f"jog frame {frame!r}: choose base or tool", Refusal.OUT_OF_RANGE)
            bMe = self.rig.robot.read_pose()
            # In the base frame: translation added, rotation about the flange's own origin.
            increment = exp_twist(np.concatenate([np.zeros(3), step[3:]]))
            increment[:3, 3] = step[:3]
            target = bMe @ exp_twist(step) if frame == "tool" else apply_increment(bMe, increment)
            self.move_to(target)

    def move_to(self, bMe_target: Matrix) -> None:
        """A linear move to a flange pose (a typed pose, the 3D gizmo, or a jog), while teaching
        or in manual mode; a target the line cannot reach is refused saying whether a joint
        path can (manual_moves.py)."""
        with self._lock:
            self._require(*HAND_MOVES, kind=Refusal.NOT_MANUAL)
            target = np.asarray(bMe_target, float)
            self._move(lambda: self.rig.robot.move_linear(target, JOG_SPEED_M_S), target, JOG_SPEED_M_S)
            self.update(**self.robot_readout())

    def present_part(self, centre_mm: Sequence[float] | None = None, turn_deg: float = 0.0, job: str | None = None) -> None:
        """A new part on the table where the cell can (the simulated cell, or a test cell's
        fixture), whenever no run or commissioning moves the robot, teaching included: with
        its top face's centre at ``centre_mm`` (X, Y in the base frame) turned ``turn_deg``
        about the vertical; else near where ``job``'s part was taught (a feeder's random
        offset and turn, core/sim/part_feeder.py, from retarget.taught_part_on_table); else
        near where the cell's feeder puts parts (the demo job's place). The cup lets go of a
        part it held."""
        with self._lock:
            self._require(*STANDING)
            if centre_mm is None and job is not None and self.rig.place_part is not None:
                centre_mm, turn_deg = self._near_the_taught_part(job)
            try:
                if centre_mm is None and self.rig.present_part is not None:
                    self.rig.present_part(self.rng)
                elif centre_mm is not None and self.rig.place_part is not None:
                    x, y = _part_origin(centre_mm, turn_deg)
                    self.rig.place_part(x, y, np.deg2rad(turn_deg))
                else:
                    raise CommandRefused("this cell has no part fixture: parts arrive by hand", Refusal.NO_FIXTURE)
            except (FixtureError, ValueError) as exc:
                raise CommandRefused(str(exc), Refusal.PART_PLACE) from None
            # A finished run's verdict is about the part taken away: the cell is ready for this one.
            phase = Phase.IDLE if self._state.phase is Phase.DONE else self._state.phase
            self.update(phase=phase, detail="a new part is on the table", **self.robot_readout())

    def _near_the_taught_part(self, job_name: str) -> tuple[tuple[float, float], float]:
        """Where a part of ``job_name`` arrives: its taught place moved by a feeder's random
        offset and turn (centre in mm, turn in deg)."""
        try:
            job = self.store.load_job(job_name)
        except JobError as exc:
            raise CommandRefused(str(exc), Refusal.JOB_PROBLEM) from None
        centre_m, yaw_rad = taught_part_on_table(
            job, job.taught_model or TaughtModel.of(self.rig.config.nominal), self.rig.config.nominal.eMv
        )
        offset_m, turn_rad = arrival(self.rng)
        x_mm, y_mm = 1000.0 * (centre_m + offset_m)
        return (float(x_mm), float(y_mm)), float(np.degrees(yaw_rad + turn_rad))

    # -- teaching (teaching_session.py) ---------------------------------------------------

    def begin_teach(self, template: str | None = None) -> None:
        """Start teaching a job, from scratch or from an existing job's poses and settings."""
        with self._lock:
            self._require(Phase.IDLE, Phase.DONE, Phase.FAULT)
            self._teaching.begin(template)
            self._desired = None  # the last job's desired corners are no part of the new one

    def _while_teaching(self, step: Callable[[], T]) -> T:
        """Carry out a teach command's ``step`` under the command lock, once the guards allow it."""
        with self._lock:
            self._require(Phase.TEACHING)
            return step()

    def capture_desired(self, part_side_m: float = PART_SIDE_M) -> DesiredImage:
        """Take the desired image here (Fig. C-2): the four corners and the laser spot must be seen."""
        with self._lock:
            self._require(Phase.TEACHING)
            self._desired = desired = self._teaching.capture_desired(*self.look(fresh=True), part_side_m)
            return desired

    def capture_check_view(self) -> CheckView:
        """Take the check view here: the part placed in the metal part, the camera over it
        seeing its four top-face corners (TeachingSession.capture_check_view)."""
        return self._while_teaching(lambda: self._teaching.capture_check_view(*self.look(fresh=True)))

    def set_start_pose(self) -> None:
        self._while_teaching(self._teaching.set_start_pose)

    def set_pick_pose(self) -> None:
        """The cup is on the part now: store the motion from the desired view to here."""
        self._while_teaching(self._teaching.set_pick_pose)

    def set_place_pose(self) -> None:
        """The cup has carried the part into the metal part (the vacuum sensor must say so)."""
        self._while_teaching(self._teaching.set_place_pose)

    def suction(self, on: bool) -> bool:
        """Switch the cup's suction while teaching; whether the vacuum sensor then reports a part."""
        return self._while_teaching(lambda: self._teaching.suction(on))

    def view_part(self) -> None:
        """The camera over the part by the image alone (TeachingSession.view_part)."""
        self._while_teaching(lambda: self._teaching.view_part(self.move_to, lambda: self.look(fresh=True)[1]))

    def centre_cup(self) -> None:
        """The cup on the middle of the part the camera sees, by the camera and the vacuum sensor
        alone (TeachingSession.centre_cup)."""
        self._while_teaching(lambda: self._teaching.centre_cup(self.move_to, lambda: self.look(fresh=True)[1].corners_px))

    def test_pick(self) -> bool:
        """Try the pick here, the way a run will (TeachingSession.test_pick). Whether it held."""
        return self._while_teaching(lambda: self._teaching.test_pick(self.move_to))

    def set_settings(
        self, threshold_px: float, gain: float, approach_m: float, placement_tolerance_mm: float | None = None
    ) -> None:
        """The run's settings; the placement tolerance is kept unless given."""
        self._while_teaching(lambda: self._teaching.set_settings(threshold_px, gain, approach_m, placement_tolerance_mm))

    def save_job(self, name: str, description: str = "", part_side_m: float = PART_SIDE_M) -> Job:
        return self._while_teaching(lambda: self._teaching.save(name, description, part_side_m))

    def cancel_teach(self) -> None:
        self._while_teaching(self._teaching.cancel)

    # -- assembly (assembly_run.py) -------------------------------------------------------

    def start(self, job_name: str, record: bool = True, part_id: str | None = None, by_line: bool = False) -> int:
        """Start one assembly of ``job_name`` in the background, its run recording ``part_id``
        (for traceability) when given; returns the run's id. ``by_line``: the PLC or OPC UA
        starts it, not an app (see moved_by_apps).

        The job is first retargeted to the cell file's model (core/production/retarget.py):
        a job taught through another calibration of the camera, hand-eye or laser sees
        the same part through this one."""
        if part_id is not None:
            validate_part_id(part_id)  # refused before anything moves
        with self._lock:
            self._require(Phase.IDLE, Phase.DONE, Phase.FAULT)
            job, note = retargeted_job(self.store, self.rig.config, job_name)
            self._enable_motion()
            run_id = self.store.start_run(job.name, self.rig.robot.name, part_id)
            self._started_by_line = by_line
            self._desired = job.desired
            self.update(
                phase=Phase.SERVOING, detail="starting", job=job.name, run=RunFigures(run_id, part_id=part_id), last_outcome=None
            )
            run = AssemblyRun(
                job,
                run_id,
                note,
                record=record,
                rig=self.rig,
                store=self.store,
                publisher=self,
                estop=self._estop,
                cycle_period_s=self.cycle_period_s,
                part_id=part_id,
            )
            self._start_work("an assembly run", self._assemble, (run,), "assembly")
            return run_id

    def _assemble(self, run: AssemblyRun) -> None:
        """The run thread: the run, then its outcome kept for ``last_outcome``."""
        self.last_outcome = run.run()

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until the run under way (if any) ends."""
        thread = self._run_thread
        if thread is not None:
            thread.finished.wait(timeout_s)

    # -- commissioning (commissioning_session.py) ------------------------------------------

    def commission(
        self,
        steps: Sequence[Step | str] | None = None,
        out_path: str | Path | None = None,
        settings: CommissionSettings | None = None,
    ) -> Path:
        """Commission the cell in the background: the robot shows the camera the board and the
        chosen steps (default: all) measure the model (docs/commissioning.md). Progress, then
        the summary, are published in the state's ``commissioning``; the e-stop stops it
        between views (and any move under way at once). Returns the cell file Apply will
        write (default: ``commissioned_path``)."""
        with self._lock:
            self._require(Phase.IDLE, Phase.DONE, Phase.FAULT)
            plan = self._commissioning.plan(steps, out_path, settings)
            self._enable_motion()
            self._commissioning.begin(plan)
            self._start_work("commissioning", self._commissioning.run, (plan,), "commissioning")
            return plan.out_path

    def apply_commissioning(self) -> Path:
        """Write the commissioned cell file and run on its model from now on
        (CommissioningSession.apply)."""
        with self._lock:
            self._require(Phase.IDLE, Phase.DONE, Phase.FAULT)
            return self._commissioning.apply()

    # -- safety ----------------------------------------------------------------------------

    def estop(self, why: str = "e-stop pressed") -> None:
        """Hold the robot now and refuse every move until reset (never waits for the command lock, never raises).

        ``why`` is what the state, the log and the run's record say stopped it. The hold
        goes out from its own thread: a link that went silent in the middle of another
        thread's request keeps the line until that request's timers run out (tens of
        seconds on the factory timers), and the operator must not wait for it. After
        HOLD_CONFIRM_S without the JRC's answer the state says the hold is not confirmed
        and why; it says "robot held" (or that the hold failed) once the answer comes.
        A run or a commissioning that has already said how the e-stop stopped it keeps
        its words over "robot held".
        """
        pressed = self._state  # before the latch: whatever a stopped thread says of it comes after
        self._estop.press(why)
        pending = (
            f"{why}: hold NOT confirmed after {HOLD_CONFIRM_S:g} s (the robot link is silent or busy): use the pendant's e-stop"
        )
        settled = threading.Lock()  # the answer and the timeout: whichever comes first writes the state
        answer: dict[str, str | bool] = {}
        answered = threading.Event()

        def send_hold() -> None:
            detail, held = _send_hold(self.rig.robot, why)
            with settled:
                answer["detail"], answer["held"] = detail, held
                answered.set()
                if "late" in answer:  # the state says not confirmed: the answer replaces it unless newer words did
                    self.update_with(
                        lambda state: {"phase": Phase.ESTOPPED, "detail": detail} if state.detail == pending else None
                    )

        threading.Thread(target=send_hold, name="estop-hold", daemon=True).start()
        answered.wait(HOLD_CONFIRM_S)
        with settled:
            if "detail" not in answer:
                answer["late"] = True
                log.error(pending)
            detail, held = str(answer.get("detail", pending)), answer.get("held") is True
            self.update_with(
                lambda state: (
                    {"phase": Phase.ESTOPPED}
                    if held and state is not pressed and state.phase is Phase.ESTOPPED
                    else {"phase": Phase.ESTOPPED, "detail": detail}
                )
            )

    def reset(self) -> None:
        """Clear an e-stop or a fault once the run has stopped: open again a device lost
        with the fault (the robot's port, the camera), release the hold, back to idle."""
        if self.running:
            raise CommandRefused("the run is still stopping; try again", Refusal.BUSY)
        with self._lock:
            if self._state.phase not in (Phase.ESTOPPED, Phase.FAULT, Phase.DONE):
                raise CommandRefused(f"nothing to reset while {self._state.phase.value}", Refusal.NOT_NOW)
            try:
                self.rig.reconnect()
            except RobotError as exc:
                raise CommandRefused(f"reset failed: the robot link: {exc}", Refusal.RESET_FAILED) from exc
            except CameraSourceError as exc:
                raise CommandRefused(f"reset failed: the camera: {exc}", Refusal.RESET_FAILED) from exc
            try:
                self.rig.robot.reset_emergency_stop()
                self.rig.robot.reset_alarms()
                self.rig.robot.hold(False)
            except RobotError as exc:
                raise CommandRefused(f"reset failed: {exc}", Refusal.RESET_FAILED) from exc
            self._estop.release()
            self.update(phase=Phase.IDLE, detail="reset: ready", **self.robot_readout())

    def close(self) -> None:
        """Stop: hold the robot if a run is under way, then release the devices."""
        if self.running:
            self.estop("e-stop: the controller process is stopping")
            self.wait(10.0)
        self.rig.close()


def run_job_once(controller: CellController, job_name: str, part_id: str | None = None) -> dict:
    """One headless assembly (``vservo run``): a new part where the cell can present one,
    start, wait. The command is the operator's explicit go: a hold left by an earlier
    session's fault is released first, as its Reset would."""
    if controller.state.phase is Phase.FAULT:
        controller.reset()
    if controller.rig.present_part is not None:
        controller.present_part(job=job_name)
    run_id = controller.start(job_name, part_id=part_id)
    controller.wait()
    outcome = controller.last_outcome
    if outcome is None:  # the run thread stores one whatever happens; a bug otherwise
        raise RuntimeError(f"run {run_id} of {job_name!r} ended without an outcome")
    return {**outcome.summary(), "job": job_name, "run_id": run_id, "part_id": part_id}
