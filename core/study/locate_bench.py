"""``vservo bench locate``: a job that locates its part, run on parts put anywhere in its
survey view (issue's figure: the share assembled of 40 random placements).

The bench needs a commissioned cell (its [commissioning] nn_file) with a fixture that can
put the part at a given place (the virtual cell's ``POST /part``, or the simulated cell).
It makes the locating variant of ``--job``: the same taught job surveying from the
centre of the network's grid (flange tool-down at the grid's height), saved as
``<job>-locate`` in the bench's data folder. Each placement is drawn uniformly in the
part of the table the survey camera sees, a margin inside the image's edges (through the
cell file's calibrated model), at a random turn, where the arm can serve it: the start
pose, the desired view (through the cell's hand-eye, where the servo ends) and the pick
pose moved with the part, and every pose 5 mm around them, must be reachable (the UPJ's
tool-down workspace at the taught heights is a thin shell around its base, and the
servo's path wanders about those poses), and the moves the run makes between them must
pass the safety layer's checks all along their paths. Places
the fixture refuses (on the metal part) or the arm cannot serve are drawn again, and
counted. Every run is an ordinary assembly of the controller.
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.cell.config import CellConfig, ConfigError
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.geometry.spatial import Matrix, rot_z, transform
from vservo.core.production.assembly import Outcome, lifted
from vservo.core.production.cell_controller import CellController
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.fixture import FixtureError
from vservo.core.production.jobs import Job, TaughtModel
from vservo.core.production.locate import PartLocator
from vservo.core.production.retarget import desired_view_for_part, retarget, start_pose_for_part
from vservo.core.production.rig import Rig
from vservo.core.production.storage import Store
from vservo.core.robot.safety import SafetyRefusal
from vservo.core.terminal.progress import Progress

# Placements keep the part's centre this far inside the survey image's edges (px).
MARGIN_PX = 60.0
# How far around the poses of a run the arm must reach for a place to count as servable.
SERVO_MARGIN_M = 0.005


def survey_pose(locator: PartLocator) -> Matrix:
    """The flange pose at the centre of the network's grid, in the grid's orientation."""
    bMe = np.array(locator.grid_bMe[0], dtype=float)
    bMe[:2, 3] = locator.grid_bMe[:, :2, 3].mean(axis=0)
    return bMe


def survey_footprint(locator: PartLocator, bMe: Matrix, part_side_m: float, margin_px: float = MARGIN_PX) -> Matrix:
    """The table's (x, y) (4, 2) under the survey image's corners pulled in by ``margin_px``,
    at the part's top face (through the calibrated camera and hand-eye)."""
    camera = locator.model.camera
    width, height = camera.image_size
    pixels = np.array(
        [
            [margin_px, margin_px],
            [width - margin_px, margin_px],
            [width - margin_px, height - margin_px],
            [margin_px, height - margin_px],
        ]
    )
    bMc = bMe @ locator.model.eMc
    rays = np.column_stack((camera.pixel_to_normalized(pixels), np.ones(4))) @ bMc[:3, :3].T
    depth = (locator.table_z_m + part_side_m - bMc[2, 3]) / rays[:, 2]
    return (bMc[:3, 3] + rays * depth[:, None])[:, :2]


def _servable(rig: Rig, job: Job, bMo: Matrix) -> bool:
    """Whether the arm serves a part at bMo on the paths the run takes (run_assembly): the
    joint move from the survey pose to the start pose, the straight moves from the desired
    view down to the pick and from above the pick to above the place, each step through
    the safety layer's checks (SafetyLayer.joint_path / linear_path, as the run's moves
    plan them), and the poses SERVO_MARGIN_M around the start pose, the desired view and
    the pick, radially and vertically (the servo's path wanders about them). No motion.

    The job as the run sees it: retargeted to the cell's model, as the controller retargets
    every run. The servo ends where the camera sees the part at the desired cdMo, so the
    flange's goal is bMo cdMo^-1 eMc^-1 through the cell's hand-eye: on a commissioned cell
    whose eMc is turned by degrees from the taught one, that goal lies tens of millimetres
    from the taught model's and may be past joint 2's or 3's limit where the taught one is not."""
    job = retarget(job, rig.config.nominal)
    assert job.survey_bMe is not None  # the bench's job surveys (bench_locate sets the pose)
    taught = job.taught_model or TaughtModel.of(rig.config.nominal)
    start = start_pose_for_part(job, taught, bMo)
    view = desired_view_for_part(job, taught, bMo)
    pick = view @ job.eMe_pick
    above_pick, above_place = lifted(pick, job.approach_m), lifted(job.bMe_place, job.approach_m)
    poses = [start, view, pick, above_pick]
    speed_m_s = rig.config.motion.move_speed_m_s
    robot = rig.robot
    try:
        # The poses themselves first: most places that fail, fail there, and a failed IK is slow.
        for bMe in poses + [_moved(bMe, shift) for bMe in poses for shift in _margin_shifts(bMe)]:
            robot.check_target(bMe, speed_m_s, bMe_now=bMe)
        robot.joint_path(job.survey_bMe, start, speed_m_s)
        robot.linear_path(view, above_pick, speed_m_s)
        robot.linear_path(above_pick, pick, speed_m_s)
        robot.linear_path(above_pick, above_place, speed_m_s)
    except (SafetyRefusal, UnreachableTarget):
        return False
    return True


def _margin_shifts(bMe: Matrix) -> list[Matrix]:
    """SERVO_MARGIN_M towards and away from the base axis, and up and down."""
    radial = np.append(bMe[:2, 3] / np.linalg.norm(bMe[:2, 3]), 0.0)
    up = np.array([0.0, 0.0, 1.0])
    return [SERVO_MARGIN_M * d for d in (radial, -radial, up, -up)]


def _moved(bMe: Matrix, shift: Matrix) -> Matrix:
    moved = np.array(bMe, dtype=float)
    moved[:3, 3] += shift
    return moved


def failure_kind(reason: str) -> str:
    """A failed run's reason without its figures, so that alike failures count together:
    the words before the first parenthesis, and the joint at its limit if one is named."""
    limit = re.search(r"\w+ at its (upper|lower) limit", reason)
    head = reason.split(" (")[0]
    return f"{head}, {limit.group(0)}" if limit else head


def _inside(polygon: Matrix, point: Matrix) -> bool:
    """Whether ``point`` lies in the convex ``polygon`` (corners in order)."""
    edges = np.roll(polygon, -1, axis=0) - polygon
    to_point = point - polygon
    cross = edges[:, 0] * to_point[:, 1] - edges[:, 1] * to_point[:, 0]
    return bool(np.all(cross >= 0) or np.all(cross <= 0))


def bench_locate(config: CellConfig, job_name: str, runs: int, seed: int, data: Path) -> dict[str, Any]:
    rig = build_rig(config, seed)
    if rig.locator is None:
        rig.close()
        raise ConfigError(f"{config.source}: not commissioned (no [commissioning] nn_file): run vservo commission first")
    if rig.place_part is None:
        rig.close()
        raise ConfigError(
            f"{config.source}: the cell cannot put a part at a given place (no [fixture] url): the "
            "locate bench needs the virtual cell's or the simulated cell's fixture"
        )
    store = Store(data)
    controller = CellController(rig, store, seed=seed)
    try:
        job = store.load_job(job_name)
        survey_bMe = survey_pose(rig.locator)
        located = replace(job, name=f"{job.name}-locate", survey_bMe=survey_bMe)
        store.save_job(located, store.job_image(job_name), store.job_image(job_name, check=True))
        footprint = survey_footprint(rig.locator, survey_bMe, job.part_side_m)
        low, high = footprint.min(axis=0), footprint.max(axis=0)
        rng = np.random.default_rng([seed, 17])
        results: list[dict[str, Any]] = []  # one JSON record a run
        unservable = 0
        progress = Progress(runs, "bench locate")
        for _ in range(runs):
            while True:
                xy = rng.uniform(low, high)
                yaw = float(rng.uniform(-np.pi, np.pi))
                if not _inside(footprint, xy):
                    continue
                # The part frame O is a top-face corner: put the part's centre at xy.
                half = 0.5 * job.part_side_m * np.array([np.cos(yaw) - np.sin(yaw), np.sin(yaw) + np.cos(yaw)])
                bMo = transform(rot_z(yaw)[:3, :3], (xy[0] - half[0], xy[1] - half[1], rig.locator.table_z_m + job.part_side_m))
                if not _servable(rig, located, bMo):
                    unservable += 1
                    continue
                try:
                    rig.place_part(float(xy[0] - half[0]), float(xy[1] - half[1]), yaw)
                except (ValueError, FixtureError):
                    continue
                break
            if controller.state.phase in ("fault", "e-stopped"):
                controller.reset()
            controller.start(located.name)
            controller.wait()
            outcome = controller.last_outcome
            assert outcome is not None  # wait() returns once the run has its outcome
            results.append(
                {
                    "x_mm": round(1000 * float(xy[0]), 2),
                    "y_mm": round(1000 * float(xy[1]), 2),
                    "yaw_deg": round(float(np.degrees(yaw)), 1),
                    "outcome": str(outcome.outcome),
                    "reason": outcome.reason,
                    "placement_error_mm": outcome.placement_error_mm,
                    "gauge_placement_error_mm": outcome.gauge_placement_error_mm,
                }
            )
            progress.advance(str(outcome.outcome))
        progress.close()
    finally:
        controller.close()
        store.close()
    placed = [r for r in results if r["outcome"] == Outcome.PLACED]
    errors = [r["placement_error_mm"] for r in placed if r["placement_error_mm"] is not None]
    return {
        "job": located.name,
        "runs": runs,
        "unservable_draws": unservable,
        "placed": len(placed),
        "placed_share": round(len(placed) / runs, 4),
        "survey_bMe_mm": [round(1000 * v, 2) for v in survey_bMe[:3, 3]],
        "footprint_mm": np.round(1000 * footprint, 1).tolist(),
        "placement_error_mm": {
            "median": round(float(np.median(errors)), 4) if errors else None,
            "max": round(float(np.max(errors)), 4) if errors else None,
        },
        "failures_by_reason": dict(
            Counter(failure_kind(r["reason"]) for r in results if r["outcome"] != Outcome.PLACED).most_common()
        ),
        "failures": [r for r in results if r["outcome"] != Outcome.PLACED],
        "results": results,
    }
