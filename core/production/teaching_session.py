"""Teaching a job: the draft, each teach command's work, and the place and pocket checks.

The controller owns one TeachingSession. It calls each method under its command lock
once its guards allow the command (teaching under way, no e-stop), so the methods here
only do the work: read the robot, fill the draft, say on the state what was taught and
what is still missing.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from vservo.core.cell.scene import Cube
from vservo.core.geometry.pose_estimation import PoseEstimationError, pose_from_planar_points
from vservo.core.geometry.spatial import Matrix, inverse, rot_x, rot_z, transform
from vservo.core.perception.camera_source import Frame
from vservo.core.perception.features import DesiredImage, ImageFeatures, pattern_scale
from vservo.core.production.controller_state import Publisher, TeachDraft
from vservo.core.production.cup_centring import CellMotions, Centred, CentringError, centre_cup
from vservo.core.production.jobs import Job, JobError, TaughtModel
from vservo.core.production.part_view import ViewError, ViewMotions, view_part
from vservo.core.production.placement_check import CheckView
from vservo.core.production.pocket import PocketFit, flange_in_pocket, part_on_flange, pocket_fit
from vservo.core.production.protocol import CommandRefused, Phase, Teaching
from vservo.core.production.protocol.catalogue import Refusal
from vservo.core.production.protocol.commands import PART_SIDE_M
from vservo.core.production.rig import Rig
from vservo.core.production.storage import DEMO_JOB, Store
from vservo.core.robot.backend import RobotError
from vservo.core.servo.teaching import TeachError, desired_from_features

log = logging.getLogger("vservo.controller")

# A test pick lifts the part this far: enough for the vacuum sensor to feel its weight,
# little enough that a part that falls lands where it lay.
TEST_PICK_LIFT_M = 0.005
# The check view's part may lie this far from where the taught pick and place carry the
# part of the desired view before the operator is warned (deg; the position's bound is
# the job's placement tolerance): beyond it the part moved between the desired image and
# the pick, or slipped on the cup, and every run would place it so.
PLACE_TURN_WARNING_DEG = 2.0
# "View the part" leaves the part this large against the demo job's desired view: the camera
# about 180 mm over it (nominally; 150 mm with Table 5-5's shorter true focal length), the
# vacuum cup, 150 mm under the flange, well clear of the part and the table.
VIEW_SCALE = 0.9


class TeachingSession:
    """The job being taught and the images captured for it."""

    def __init__(self, rig: Rig, store: Store, publisher: Publisher) -> None:
        self.rig, self.store, self.publisher = rig, store, publisher
        self._draft: TeachDraft | None = None
        self._test_pick_held: bool | None = None  # the last test pick's grip, for the Teach tab's next step
        self._desired_image: np.ndarray | None = None
        self._check_image: np.ndarray | None = None

    @property
    def draft(self) -> TeachDraft:
        if self._draft is None:  # the controller's guard lets teach commands through only while teaching
            raise CommandRefused("nothing is being taught: Teach first", Refusal.NOT_NOW)
        return self._draft

    def begin(self, template: str | None) -> None:
        """Start a draft, from scratch or from an existing job's poses and settings."""
        draft = TeachDraft()
        if template:
            job = self.store.load_job(template)
            # The images are captured again (the check view's goes with the desired one).
            draft = TeachDraft(
                template,
                None,
                None,
                job.start_bMe,
                job.eMe_pick,
                job.bMe_place,
                job.threshold_px,
                job.gain,
                job.approach_m,
                placement_tolerance_mm=job.placement_tolerance_mm,
            )
        self._draft = draft
        self._check_image = None
        self._test_pick_held = None
        # The job shown is the template taught from; a new job has none until it is saved.
        self.publisher.update(
            phase=Phase.TEACHING, detail="jog to the desired view and capture it", job=template or None, teaching=self._teaching()
        )

    def _set_draft(self, detail: str, **changes: Any) -> None:
        self._draft = replace(self.draft, **changes)
        self.publisher.update(detail=detail, teaching=self._teaching())

    def _part_held(self, draft: TeachDraft) -> Matrix | None:
        """eMo: the desired image's part as the taught pick holds it (None until both are taught).

        On a cell whose model is measured, as the desired image saw it through the model; on
        one never commissioned that is as far off as the model (22 mm with Table 5-5's errors),
        so the part is taken as centred on the cup (as "Centre the cup on the part" leaves it),
        its top face on the cup's face (the compensator extended once it is lifted), only its
        turn about the cup's axis from the image: then neither the camera's model nor the
        hand-eye enters the pocket's aids, only the cup's mount eMv."""
        if draft.taught_bMe is None or draft.seen_bMo is None or draft.eMe_pick is None:
            return None
        eMo = part_on_flange(draft.taught_bMe, draft.eMe_pick, draft.seen_bMo)
        if self.rig.config.model_measured:
            return eMo
        eMv = self.rig.config.nominal.eMv
        x_v = (inverse(eMv) @ eMo)[:3, 0]
        side = PART_SIDE_M
        vMo_centred = inverse(transform(rot_x(np.pi), (side / 2, side / 2, 0.0)))
        return eMv @ transform(rot_z(float(np.arctan2(x_v[1], x_v[0])))) @ vMo_centred

    def _placed(self, draft: TeachDraft) -> Matrix | None:
        """bMo: where the taught pick and place set the desired image's part down (None until taught)."""
        eMo = self._part_held(draft)
        return None if eMo is None or draft.bMe_place is None else draft.bMe_place @ eMo

    def _pocket_fit(self) -> PocketFit | None:
        """Where the taught pick and place set the desired image's part down, against the
        cell file's pocket; None until all three are taught, or without a [metal_part]."""
        pocket, bMo = self.rig.config.metal_part, self._placed(self.draft)
        return None if pocket is None or bMo is None else pocket_fit(bMo, pocket, PART_SIDE_M)

    def _teaching(self) -> Teaching:
        """What the state says of the draft: the steps taught, and the poses the Teach tab may
        go to once known: the desired view; from the cell file's [metal_part], the flange pose
        that sets the picked part centred in its pocket and where the taught place sets it."""
        draft, pocket = self.draft, self.rig.config.metal_part
        eMo = self._part_held(draft)
        if pocket is None or eMo is None or draft.seen_bMo is None:
            return Teaching(
                draft.taught, self._test_pick_held, view_bMe=draft.taught_bMe, model_measured=self.rig.config.model_measured
            )
        fit = self._pocket_fit()
        return Teaching(
            draft.taught,
            self._test_pick_held,
            view_bMe=draft.taught_bMe,
            pocket_bMe=flange_in_pocket(eMo, pocket, PART_SIDE_M, draft.seen_bMo),
            place_bMo=None if fit is None else fit.bMo,
            model_measured=self.rig.config.model_measured,
        )

    def _place_words(self) -> str:
        """The place check (said as soon as the place is taught): how far off the pocket's
        centre and how turned, modulo the part's quarter turns, every run will set the part
        down; a warning beyond the placement tolerance or PLACE_TURN_WARNING_DEG."""
        if self.rig.config.metal_part is None:
            return " (the cell file has no [metal_part]: no place check)"
        fit = self._pocket_fit()
        if fit is None:
            return ""
        if abs(fit.turn_deg) > PLACE_TURN_WARNING_DEG:
            return (
                f"; WARNING: {fit.words()}: the part in the desired image is turned {fit.turn_deg:+.1f} deg from "
                "how it must sit in the pocket; turn the cup by the opposite at the place, or teach the desired "
                "image with the part turned as the pocket is"
            )
        if fit.offset_mm > self.draft.placement_tolerance_mm:
            return f"; WARNING: {fit.words()}: beyond the placement tolerance; move the cup over the pocket's centre"
        return f": {fit.words()}"

    def capture_desired(self, frame: Frame, features: ImageFeatures, part_side_m: float) -> DesiredImage:
        """The desired image from a fresh frame taken here (Fig. C-2): the four corners and the laser spot must be seen."""
        try:
            desired = desired_from_features(features, self.rig.config.nominal.camera, part_side_m)
        except TeachError as exc:
            raise CommandRefused(str(exc), Refusal.PART_NOT_SEEN) from exc
        self._desired_image = frame.image
        taught_bMe = self.rig.robot.read_pose()
        self._set_draft(
            f"desired image captured, laser depth {1000 * desired.depth_m:.1f} mm",
            desired=desired,
            taught_bMe=taught_bMe,
            taught_model=TaughtModel.of(self.rig.config.nominal, self.rig.config.model_measured),
            seen_bMo=self._part_seen(taught_bMe, features.corners_px, part_side_m),
        )
        return desired

    def capture_check_view(self, frame: Frame, features: ImageFeatures) -> CheckView:
        """The check view from a fresh frame taken here: the part placed in the metal part, the
        camera over it seeing its four top-face corners. After each run the arm comes back
        here and the part's displacement from these corners is its placement error."""
        if not features.all_corners_visible:
            raise CommandRefused(
                "the check view must show the part's four top-face corners: "
                "put the part in the metal part and the camera over it",
                Refusal.PART_NOT_SEEN,
            )
        check = CheckView(check_bMe=self.rig.robot.read_pose(), corners_px=features.corners_px)
        self._check_image = frame.image
        self._set_draft(f"check view captured{self._place_check(check)}", check=check)
        return check

    def _part_seen(self, bMe: Matrix, corners_px: Matrix, side_m: float = PART_SIDE_M) -> Matrix | None:
        """bMo of the part from its four corners seen from bMe (None when the pose cannot be had)."""
        model = self.rig.config.nominal
        try:
            return bMe @ model.eMc @ pose_from_planar_points(corners_px, Cube(np.eye(4), side_m).corners_o, model.camera)
        except PoseEstimationError:
            return None

    def _place_check(self, check: CheckView) -> str:
        """The check view's part against where the taught pick and place put the part the
        desired image saw: the words to add to the state (a warning beyond the bounds)."""
        draft = self.draft
        if not self.rig.config.model_measured:
            return (
                ": this cell was never commissioned, so the camera's model cannot say in mm where the part lies "
                "(no place check); the runs measure their placement against this view in the image, which needs no model"
            )
        expected = self._placed(draft)  # the part held as the pick found it, set down by the place pose
        placed = None if expected is None else self._part_seen(check.check_bMe, check.corners_px)
        if expected is None or placed is None:
            return ""
        offset_mm = 1000.0 * float(np.linalg.norm(placed[:2, 3] - expected[:2, 3]))
        turn = np.arctan2(placed[1, 0], placed[0, 0]) - np.arctan2(expected[1, 0], expected[0, 0])
        turn_deg = float(np.rad2deg(np.angle(np.exp(1j * turn))))
        where = f"the part lies {offset_mm:.1f} mm and {turn_deg:+.1f} deg from where the taught pick and place put it"
        if offset_mm > draft.placement_tolerance_mm or abs(turn_deg) > PLACE_TURN_WARNING_DEG:
            return (
                f"; WARNING: {where}: the part moved between the desired image and the pick, or slipped on "
                "the cup; teach the desired image, the pick and the place again on one part left where it lies"
            )
        return f": {where}"

    def set_start_pose(self) -> None:
        self._set_draft("start pose set here", start_bMe=self.rig.robot.read_pose())

    def set_pick_pose(self) -> None:
        """The cup is on the part now: store the motion from the desired view to here."""
        taught_bMe = self.draft.taught_bMe
        if taught_bMe is None:
            raise CommandRefused("capture the desired image first: the pick is taught relative to it", Refusal.NOT_TAUGHT_YET)
        self._set_draft("pick pose set here", eMe_pick=np.linalg.inv(taught_bMe) @ self.rig.robot.read_pose())

    def set_place_pose(self) -> None:
        """The cup has carried the part into the metal part: the place pose is taught only
        with the part on the cup, so the vacuum sensor must say so."""
        if not self._holding():
            raise CommandRefused(
                "the place pose is taught with the part on the cup, and the vacuum sensor "
                "reports none: at the pick, Suction on, then carry the part into the metal part",
                Refusal.CUP_EMPTY,
            )
        self._draft = replace(self.draft, bMe_place=self.rig.robot.read_pose())
        self._set_draft(f"place pose set here{self._place_words()}")

    def _holding(self) -> bool:
        try:
            return self.rig.gripper.holding()
        except RobotError as exc:
            raise CommandRefused(f"the vacuum sensor cannot be read: {exc}", Refusal.VACUUM_FAULT) from exc

    def suction(self, on: bool) -> bool:
        """Switch the cup's suction; whether the vacuum sensor then reports a part."""
        try:
            self.rig.gripper.set_vacuum(on)
        except RobotError as exc:
            raise CommandRefused(f"suction {'on' if on else 'off'}: {exc}", Refusal.VACUUM_FAULT) from exc
        holding = self._holding()
        sensor = "a part on the cup" if holding else "no part on the cup"
        self.publisher.update(
            detail=f"suction {'on' if on else 'off'}: the vacuum sensor reports {sensor}", **self.publisher.robot_readout()
        )
        return holding

    def view_part(self, move_to: Callable[[Matrix], None], features: Callable[[], ImageFeatures]) -> None:
        """The camera over the part by the image alone (core/production/part_view.py): the
        laser spot on the part's centre, the part as large in the image as the demo job's
        desired view shows it (VIEW_SCALE of it): where to capture the desired image, right on a
        cell never commissioned."""
        demo = self.store.load_job(DEMO_JOB)
        k = self.rig.config.nominal.camera.intrinsics
        motions = ViewMotions(move_to, self.rig.robot.read_pose, features)
        try:
            _, moves = view_part(motions, VIEW_SCALE * pattern_scale(demo.desired.corners_px), np.array([k.u0, k.v0]))
        except ViewError as exc:
            raise CommandRefused(str(exc), Refusal.PART_NOT_SEEN) from exc
        self.publisher.update(
            detail=f"the part in view by the image alone ({moves} moves), the laser spot on its centre: Capture desired image",
            **self.publisher.robot_readout(),
        )

    def centre_cup(self, move_to: Callable[[Matrix], None], corners_px: Callable[[], Matrix]) -> Centred:
        """The cup on the middle of the part the camera sees from here, by the camera and the
        vacuum sensor alone (core/production/cup_centring.py), left pressed on it with the
        suction off: the pick pose to test and set, right on a cell never commissioned."""
        if self._holding():
            raise CommandRefused("the cup holds a part already: Suction off first", Refusal.CUP_HOLDS_PART)
        model = self.rig.config.nominal
        motions = CellMotions(move_to, self.rig.robot.read_pose, corners_px, self._grips)
        try:
            centred = centre_cup(motions, model.eMv, model.eMc)
        except CentringError as exc:
            raise CommandRefused(str(exc), Refusal.PART_NOT_SEEN) from exc
        self.publisher.update(
            detail=f"cup centred on the part by the camera and the vacuum sensor: moved {1000 * centred.offset_m:.1f} mm "
            f"across, the top face felt at Z {1000 * centred.face_z_m:.1f} mm: Test pick, then Set pick pose here",
            **self.publisher.robot_readout(),
        )
        return centred

    def _grips(self) -> bool:
        """Suction on, the vacuum sensor read, suction off: whether the cup would grip here."""
        try:
            self.rig.gripper.set_vacuum(True)
            return self._holding()
        finally:
            self.rig.gripper.set_vacuum(False)

    def test_pick(self, move_to: Callable[[Matrix], None]) -> bool:
        """Try the pick here, the way a run will: suction on, lift TEST_PICK_LIFT_M by
        ``move_to``, read the vacuum sensor, put the part back down where it was and
        release it. True when it held; a grip that failed is refused (NO_GRIP, GRIP_WEAK)
        once the state says so, and the Teach tab offers the test pick again."""
        if self._holding():
            raise CommandRefused("the cup holds a part already: Suction off first", Refusal.CUP_HOLDS_PART)
        bMe = self.rig.robot.read_pose()
        lifted = bMe.copy()
        lifted[2, 3] += TEST_PICK_LIFT_M
        gripped = self.suction(True)
        held = False
        try:
            if gripped:
                move_to(lifted)
                held = self._holding()
                move_to(bMe)
        finally:
            self.rig.gripper.set_vacuum(False)
        lift = f"{1000 * TEST_PICK_LIFT_M:.0f} mm"
        detail = (
            f"test pick: the part held through a {lift} lift and is back down: grip good"
            if held
            else f"test pick: the part fell during the {lift} lift: grip weak"
            if gripped
            else "test pick: no grip: the vacuum sensor reports no part after suction on "
            "(put the cup on the middle of the part's top face, pressed a few mm)"
        )
        self._test_pick_held = held
        self.publisher.update(detail=detail, teaching=self._teaching(), **self.publisher.robot_readout())
        if not held:
            raise CommandRefused(detail, Refusal.GRIP_WEAK if gripped else Refusal.NO_GRIP)
        return held

    def set_settings(self, threshold_px: float, gain: float, approach_m: float, placement_tolerance_mm: float | None) -> None:
        """The run's settings; the placement tolerance is kept unless given."""
        tolerance = self.draft.placement_tolerance_mm if placement_tolerance_mm is None else placement_tolerance_mm
        for name, value in (
            ("threshold_px", threshold_px),
            ("gain", gain),
            ("approach_m", approach_m),
            ("placement_tolerance_mm", tolerance),
        ):
            if not (np.isfinite(value) and value > 0):
                raise CommandRefused(f"{name} must be a positive number, got {value!r}", Refusal.OUT_OF_RANGE)
        self._set_draft(
            "settings changed", threshold_px=threshold_px, gain=gain, approach_m=approach_m, placement_tolerance_mm=tolerance
        )

    def save(self, name: str, description: str, part_side_m: float) -> Job:
        """Store the draft as job ``name``; the draft ends."""
        draft = self.draft
        if draft.missing:
            raise CommandRefused(
                f"cannot save yet: teach {', '.join(step.value for step in draft.missing)}", Refusal.NOT_TAUGHT_YET
            )
        assert draft.desired is not None and draft.taught_bMe is not None  # missing checked them
        assert draft.start_bMe is not None and draft.eMe_pick is not None and draft.bMe_place is not None
        try:
            job = Job(
                name=name,
                description=description,
                part_side_m=part_side_m,
                desired=draft.desired,
                taught_bMe=draft.taught_bMe,
                start_bMe=draft.start_bMe,
                eMe_pick=draft.eMe_pick,
                bMe_place=draft.bMe_place,
                approach_m=draft.approach_m,
                threshold_px=draft.threshold_px,
                gain=draft.gain,
                check=draft.check,
                placement_tolerance_mm=draft.placement_tolerance_mm,
                taught_model=draft.taught_model,
            )
        except JobError as exc:
            raise CommandRefused(str(exc), Refusal.JOB_PROBLEM) from exc
        self.store.save_job(job, self._desired_image, self._check_image if draft.check is not None else None)
        self._draft = None
        self.publisher.update(phase=Phase.IDLE, detail=f"job {name!r} saved", job=name, teaching=None)
        return job

    def cancel(self) -> None:
        self._draft = None
        self.publisher.update(phase=Phase.IDLE, detail="teaching cancelled", teaching=None)
