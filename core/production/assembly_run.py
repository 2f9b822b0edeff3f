"""One assembly run as the controller carries it out: its thread's body.

The controller retargets the job (``retargeted_job``), enables motion, opens the run in
the store and starts a thread on ``AssemblyRun.run``. The run records every servo cycle
(a recording that fails stops, the run goes on and says so), publishes each cycle's figures
and frame, and at its end stores the outcome and publishes it. Whatever goes wrong, a bug
included, the robot is left held and the run's end is on record.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from vservo.core.cell.config import CellConfig
from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.camera_source import CameraSourceError
from vservo.core.perception.recording import RecorderThread, RecordingError, RunRecorder
from vservo.core.perception.vision.pipeline import CameraPerception
from vservo.core.production.assembly import (
    AssemblyEvent,
    AssemblyOutcome,
    Outcome,
    Phase,
    PhaseChange,
    hold_after_fault,
    run_assembly,
)
from vservo.core.production.controller_state import EStopLatch, FrameView, Publisher
from vservo.core.production.jobs import Job, JobError
from vservo.core.production.protocol import CommandRefused, RunFigures
from vservo.core.production.protocol.catalogue import Refusal, RunEnd
from vservo.core.production.retarget import retarget, retarget_note, transfer_refusal
from vservo.core.production.rig import Rig
from vservo.core.production.storage import Store, StoreError
from vservo.core.servo.loop import Cycle, cycle_record

log = logging.getLogger("vservo.controller")

TRAIL_LENGTH = 400  # feature positions kept for the trajectories drawn on the image


def retargeted_job(store: Store, config: CellConfig, job_name: str) -> tuple[Job, str | None]:
    """The stored job ``job_name`` retargeted to the cell's model (core/production/retarget.py),
    and how it was retargeted (None: as taught): a job taught through another calibration of
    the camera, hand-eye or laser sees the same part through this one. Refused, before
    anything moves, for a job taught through a measured model on a cell never commissioned
    (retarget.transfer_refusal)."""
    model = config.nominal
    try:
        stored = store.load_job(job_name)
        job = retarget(stored, model)
    except JobError as exc:
        raise CommandRefused(str(exc), Refusal.JOB_PROBLEM) from exc
    refusal = transfer_refusal(stored, config.model_measured)
    if refusal is not None:
        raise CommandRefused(refusal, Refusal.CELL_NOT_COMMISSIONED)
    note = retarget_note(stored, model)
    if note:
        log.info("job %r: %s", job.name, note)
    return job, note


def _closed_quietly(recorder: RecorderThread) -> None:
    """Close a recorder that failed to write (as aborted); its close raises that failure, or
    fails alike (the same full disk)."""
    try:
        recorder.close()
    except (RecordingError, OSError) as exc:
        log.warning("closed the failed recording %s: %s", recorder.folder, exc)


class AssemblyRun:
    """One run of ``job``, already retargeted to the cell's model; ``note`` says how (None: as taught)."""

    def __init__(
        self,
        job: Job,
        run_id: int,
        note: str | None,
        *,
        record: bool,
        rig: Rig,
        store: Store,
        publisher: Publisher,
        estop: EStopLatch,
        cycle_period_s: float,
        part_id: str | None = None,
    ) -> None:
        self.job, self.run_id, self.note, self.record = job, run_id, note, record
        self.part_id = part_id
        self.rig, self.store, self.publisher, self.estop = rig, store, publisher, estop
        self.cycle_period_s = cycle_period_s  # a floor on the servo cycle, so a fast simulator can be watched
        self._recorder: RecorderThread | None = None
        self._recording_note: str | None = None
        self._recorded_to: Path | None = None
        self._trail: list[Matrix] = []
        self._perception: CameraPerception  # the run's own tracker, made as it starts
        self._last_cycle_at = 0.0

    def run(self) -> AssemblyOutcome:
        """The run thread's body: assemble, then store and publish how it ended."""
        if self.record:
            self._open_recording()
        self._perception = self.rig.perception()
        self._last_cycle_at = time.monotonic()
        outcome = self._assemble()
        if outcome.outcome is Outcome.ESTOPPED:
            outcome = replace(outcome, reason=self.estop.reason, end=RunEnd.ESTOPPED)
        if self.note:
            outcome = replace(outcome, notes=(*outcome.notes, self.note))
        outcome = self._stored(self._recording_closed(outcome))
        phase = Phase.ESTOPPED if self.estop.is_set() else Phase.FAULT if outcome.outcome is Outcome.FAULT else Phase.DONE
        self.publisher.update(phase=phase, detail=outcome.reason, last_outcome=outcome.record(), **self.publisher.robot_readout())
        return outcome

    def _open_recording(self) -> None:
        folder = self.store.run_folder(self.run_id)
        try:
            recorder = RunRecorder(folder, {"job": self.job.name, "run": self.run_id, "desired": self.job.desired})
            self._recorder = RecorderThread(recorder)  # off the loop's path: the servo may run at the camera's rate
            self._recorded_to = folder
        except (RecordingError, OSError) as exc:  # a full disk, a leftover folder: run, and say so
            self._recording_note = f"not recorded: {exc}"
            log.error("run %d: %s", self.run_id, self._recording_note)

    def _assemble(self) -> AssemblyOutcome:
        """run_assembly on the rig; a lost camera or a bug ends the run as a fault, the robot held."""
        robot = self.rig.robot
        try:
            return run_assembly(
                self.job,
                robot,
                self.rig.gripper,
                self._perception,
                self.rig.config.nominal,
                self.rig.policy,
                speed_m_s=self.rig.config.motion.move_speed_m_s,
                on_event=self._on_event,
                measure_placement=self.rig.measure_placement,
                estopped=self.estop.is_set,
                locator=self.rig.locator,
            )
        except CameraSourceError as exc:
            reason = f"camera: {exc}{hold_after_fault(robot)}"
            return AssemblyOutcome(Outcome.FAULT, reason, float("nan"), None, 0.0, [], 0, end=RunEnd.CAMERA_LOST)
        except Exception as exc:  # a bug must still leave the robot held and the run on record
            log.exception("assembly run %d crashed", self.run_id)
            reason = f"internal error: {exc!r}{hold_after_fault(robot)}"
            return AssemblyOutcome(Outcome.FAULT, reason, float("nan"), None, 0.0, [], 0, end=RunEnd.INTERNAL_ERROR)

    def _on_event(self, event: AssemblyEvent) -> None:
        if isinstance(event, PhaseChange):
            if event.phase not in (Phase.DONE, Phase.FAULT, Phase.ESTOPPED):
                self.publisher.update(phase=event.phase, detail=event.detail, **self.publisher.robot_readout())
            return
        self._cycle_done(event.cycle)

    def _cycle_done(self, cycle: Cycle) -> None:
        """Record a servo cycle, publish its figures and frame, and keep to the cycle's floor."""
        frame = self._perception.last_frame
        if self._recorder is not None:
            try:
                self._recorder.record(frame, cycle_record(cycle))
            except (RecordingError, OSError) as exc:  # the disk filled up: the run goes on unrecorded
                self._recording_note = str(exc)  # "recording stopped at cycle ...", the write's own cycle
                log.error("run %d: %s", self.run_id, self._recording_note)
                _closed_quietly(self._recorder)
                self._recorder = None
        self._trail = (self._trail + [cycle.features.corners_px])[-TRAIL_LENGTH:]
        note = cycle.output.note  # without one, the detail said last stands
        error_px = float(cycle.output.error_px) if np.isfinite(cycle.output.error_px) else None
        self.publisher.update(
            run=RunFigures(self.run_id, cycle.output.stage, cycle.iteration + 1, error_px, cycle.output.cVc, self.part_id),
            **({"detail": note} if note else {}),
            # The cup does not change while the servo runs (suction comes at the pick): no I/O read.
            **self.publisher.robot_readout(cycle.measurement.bMe, vacuum=False, q=cycle.measurement.q),
        )
        if frame is not None:
            corners, spot = cycle.features.corners_px, cycle.features.laser_spot_px
            self.publisher.publish_frame(FrameView(frame, corners, spot, self.job.desired, np.array(self._trail)))
        if self.cycle_period_s:
            time.sleep(max(0.0, self.cycle_period_s - (time.monotonic() - self._last_cycle_at)))
        self._last_cycle_at = time.monotonic()

    def _recording_closed(self, outcome: AssemblyOutcome) -> AssemblyOutcome:
        """Close the recording with the outcome's summary; the outcome notes what was not recorded."""
        if self._recorder is not None:
            try:
                self._recorder.close(outcome.summary())
            except (RecordingError, OSError) as exc:
                failed_write = self._recorder.failure is not None  # a cycle's, seen only now: it says where it stopped
                self._recording_note = str(exc) if failed_write else f"the recording's summary was not written: {exc}"
        if self._recording_note:
            outcome = replace(outcome, notes=(*outcome.notes, self._recording_note))
        return outcome

    def _stored(self, outcome: AssemblyOutcome) -> AssemblyOutcome:
        """Store the run's end; when it cannot be, the outcome says so (the next start marks it interrupted)."""
        try:
            self.store.finish_run(
                self.run_id,
                outcome.outcome,
                outcome.reason,
                outcome.final_error_px,
                outcome.placement_error_mm,
                outcome.duration_s,
                outcome.stages,
                self._recorded_to,
            )
        except (StoreError, OSError) as exc:  # the operator learns now
            log.error("run %d: its end could not be stored: %s", self.run_id, exc)
            outcome = replace(outcome, notes=(*outcome.notes, f"its end could not be stored: {exc}"))
        return outcome
