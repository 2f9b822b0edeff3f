"""Jobs that survive a recalibration: what a job taught, seen through another cell model.

A job's desired image and check view are pixels, seen through the camera, hand-eye and
laser of the cell it was taught on (its ``taught_model``). A recalibrated or replaced
camera, a hand-eye measured again or a re-mounted laser changes how the same part looks,
so the pixels are recomputed from what the job taught relative to the part:

* the desired view is the part's pose in the camera, cdMo (estimated at teaching from
  the taught corners); the part seen there through the new camera gives the desired
  corners (the pinhole projection with distortion, eqs. 2-1 .. 2-5 in OpenCV's
  convention, core/geometry/camera.py), and where the NEW beam cMl meets the part's
  top face gives the desired spot and its depth Z* (section 4.3; the general beam of
  core/geometry/laser.py);
* the pick is the part's pose in the flange at the servo's end, eMo = eMc cdMo: kept
  relative to the part, the flange's move from the servo's end to the pick becomes
  eMe_pick' = (eMc' cdMo) (eMc_t cdMo)^-1 eMe_pick;
* the check view is a flange pose over the metal part; the placed part's pose in the
  flange there (its four taught corners and known side through the taught camera and
  eMc) is seen through the new eMc and camera.

The start, place and check flange poses are base-frame poses of the flange: the metal
part is fixed in the cell, so they stay. On the cell the job was taught on, the captured
image is the best desired image there is (it holds whatever the model gets wrong), so
a job whose taught model is the cell's own is run unchanged.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from vservo.core.cell.config import CellModel
from vservo.core.cell.scene import Cube
from vservo.core.geometry.pose_estimation import PoseEstimationError, pose_from_planar_points
from vservo.core.geometry.spatial import Matrix, inverse
from vservo.core.perception.features import DesiredImage
from vservo.core.production.jobs import Job, JobError, TaughtModel
from vservo.core.production.placement_check import CheckView

NOT_RETARGETED = (
    "the job records no taught model (a job file before version 3): run as taught, not retargeted to this cell's calibration"
)
RETARGETED = "retargeted: the job was taught through another camera, hand-eye or laser calibration"


def retarget(job: Job, model: CellModel) -> Job:
    """``job`` as if taught through ``model`` (module docstring).

    Unchanged when the job has no taught model or was taught through ``model`` itself.
    The result records ``model`` as its taught model, with taught_bMe the flange pose of
    the desired view of the taught part through it, so that retargeting is idempotent
    and every relation to the part (start_pose_for_part) holds in the result as in the job.
    Raises JobError when the part at the taught view cannot be seen through the new
    model (a corner off the image, the beam off the top face): the desired view must then
    be taught again.
    """
    taught = job.taught_model
    if taught is None or taught.matches(model):
        return job
    part = Cube(np.eye(4), job.part_side_m)
    cdMo = job.desired.cdMo
    eMo_taught, eMo = taught.eMc @ cdMo, model.eMc @ cdMo
    return replace(
        job,
        desired=_desired_through(model, cdMo, part, job.name),
        taught_bMe=job.taught_bMe @ eMo_taught @ inverse(eMo),
        eMe_pick=eMo @ inverse(eMo_taught) @ job.eMe_pick,
        check=None if job.check is None else _check_through(job.check, taught, model, part, job.name),
        taught_model=TaughtModel.of(model),
    )


def transfer_refusal(job: Job, model_measured: bool) -> str | None:
    """Why ``job`` cannot run on a cell whose model is not measured (CellConfig.model_measured),
    None when it can. A job taught through a measured model holds the pixels of a known camera
    (the shipped demo job's: the simulated cell's own); on a cell never commissioned the camera,
    hand-eye and laser are the nominal ones, as far off as the parts' tolerances leave, so the
    servo would end where the taught pixels are seen through an unknown camera, the cup off
    the part by the hand-eye's error and the part released off the pocket. A job taught
    through an unmeasured model was taught on the cell it runs on (its pixels are that cell's
    camera's, whatever the model), and runs as taught."""
    taught = job.taught_model
    if model_measured or taught is None or not taught.measured:
        return None
    return (
        f"job {job.name!r} was taught on another cell, through its measured model, and this cell's model is the "
        "nominal one, never commissioned: commission this cell (vservo commission, docs/commissioning.md) so that the "
        "job is retargeted to it, or teach the job again on this cell"
    )


def retarget_note(job: Job, model: CellModel) -> str | None:
    """What a run of ``job`` on a cell of ``model`` should say about retargeting; None: nothing."""
    if job.taught_model is None:
        return NOT_RETARGETED
    return None if job.taught_model.matches(model) else RETARGETED


def _desired_through(model: CellModel, cdMo: Matrix, part: Cube, name: str) -> DesiredImage:
    """The desired image of the part at cdMo through ``model``: its corners projected, and
    the spot where the beam meets the top face (the plane z = 0 of O), with its depth Z*."""
    camera = model.camera
    corners_c = part.corners_o @ cdMo[:3, :3].T + cdMo[:3, 3]
    corners_px = camera.project(corners_c)
    if not np.all(camera.in_view(corners_px)):
        raise JobError(
            f"job {name!r}: through this cell's camera the desired view does not show the part's four "
            "corners: teach the desired image again"
        )
    normal_c = cdMo[:3, 2]
    spot_c = model.laser.spot_on_plane(normal_c, float(normal_c @ cdMo[:3, 3]))
    spot_o = None if spot_c is None else inverse(cdMo)[:3, :3] @ spot_c + inverse(cdMo)[:3, 3]
    if spot_c is None or spot_o is None or not np.all((spot_o[:2] >= 0.0) & (spot_o[:2] <= part.side_m)):
        raise JobError(
            f"job {name!r}: this cell's laser beam misses the part's top face at the desired view: teach the desired image again"
        )
    spot_px = camera.project(spot_c)[0]
    if not camera.in_view(spot_px)[0]:
        raise JobError(
            f"job {name!r}: through this cell's camera the desired view's laser spot is off the image: "
            "teach the desired image again"
        )
    # The corners' depths follow from cdMo alone, which a new model does not change.
    return DesiredImage(corners_px, spot_px, float(spot_c[2]), cdMo, corners_c[:, 2])


def _check_through(check: CheckView, taught: TaughtModel, model: CellModel, part: Cube, name: str) -> CheckView:
    """The check view's corners seen through ``model``: the placed part's pose in the flange,
    eMo = eMc_t c_tMo (c_tMo from the taught corners and the part's side), seen from the
    new camera at eMc'^-1 eMo."""
    try:
        ctMo = pose_from_planar_points(check.corners_px, part.corners_o, taught.camera)
    except PoseEstimationError as exc:
        raise JobError(f"job {name!r}: the check view's corners give no pose ({exc}): teach it again") from exc
    cMo = inverse(model.eMc) @ taught.eMc @ ctMo
    corners_px = model.camera.project(part.corners_o @ cMo[:3, :3].T + cMo[:3, 3])
    if not np.all(model.camera.in_view(corners_px)):
        raise JobError(
            f"job {name!r}: through this cell's camera the check view does not show the placed part's "
            "four corners: teach the check view again"
        )
    return CheckView(check.check_bMe, corners_px)


def start_pose_for_part(job: Job, model: TaughtModel, bMo: Matrix) -> Matrix:
    """The flange pose to start the servo from for a part found at ``bMo``: the taught start
    pose relative to the part, moved with the part.

    The part stood at bMo_taught = taught_bMe eMc cdMo when the desired image was taken;
    the start pose relative to it is oMe_start = bMo_taught^-1 start_bMe, and the start for
    the part found is bMo oMe_start, turned with the part all the way. The vision numbers
    the corners from the orientation mark (corner 0 nearest it), so the servo ends at the
    desired view of the part as marked, whatever its turn: a start a quarter turn short of
    that (a cube's face looks the same) would leave the servo the quarter turn to make,
    its path wandering far from both ends, and the pick where the servo ends, not where
    the start promised.

    model: the model the job was taught through (``job.taught_model``; for a job without
    one, the cell's current model).
    """
    bMo_taught = job.taught_bMe @ model.eMc @ job.desired.cdMo
    return np.asarray(bMo, dtype=float) @ inverse(bMo_taught) @ job.start_bMe


def desired_view_for_part(job: Job, model: TaughtModel, bMo: Matrix) -> Matrix:
    """The flange pose the servo ends at for a part found at ``bMo``: the taught desired
    view moved with the part (for a job retargeted to the cell's model, through the cell's
    hand-eye, as the servo sees it)."""
    return start_pose_for_part(replace(job, start_bMe=job.taught_bMe), model, bMo)


def taught_part_on_table(job: Job, model: TaughtModel, eMv: Matrix) -> tuple[Matrix, float]:
    """Where the job's part lay when it was taught: its top face's centre (x, y in the base
    frame, m) and its turn about the vertical (rad). The centre is where the taught pick put
    the cup (taught_bMe eMe_pick eMv: the cup is taught onto the face's middle), so no camera
    calibration enters it; the turn is the desired view's, through ``model`` (the model the
    job was taught through), a few degrees off at most on a cell never commissioned."""
    cup_b = job.taught_bMe @ job.eMe_pick @ np.asarray(eMv, dtype=float)
    bMo = job.taught_bMe @ model.eMc @ job.desired.cdMo
    return cup_b[:2, 3].copy(), float(np.arctan2(bMo[1, 0], bMo[0, 0]))
