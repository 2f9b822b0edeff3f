"""Monte Carlo study: how often each method converges from random initial poses.

Distribution (documented in the report): the desired pose is task 2's. The initial
camera pose, relative to the desired camera frame, is a rotation about a uniformly
random axis by an angle uniform in [0, pi] and a translation in a uniformly random
direction with a length uniform in [0, 0.4] m. A sample is kept when the camera looks
at the cube from above the table, the cube's face is 0.08 .. 0.6 m in front of it, at
least part of the face is in the image (so partly visible starts are included), and
the arm can reach the pose (a free camera, ``arm`` none, reaches every pose); otherwise
it is drawn again. "From above" is at least 30 mm
over the plane of the face. Sample i depends only on
(seed, i), so every method meets the same initial poses.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace
from multiprocessing import get_context
from typing import Any

import numpy as np

from vservo.core.cell.config import CellConfig
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.geometry.spatial import Matrix, exp_twist, inverse
from vservo.core.sim import Arm
from vservo.core.sim.plant import visible_region
from vservo.core.study.run import RunSettings, run_task
from vservo.core.study.tasks import TASKS

MAX_TRANSLATION_M = 0.4
MAX_ROTATION_RAD = np.pi
DEPTH_RANGE_M = (0.08, 0.6)
MIN_HEIGHT_M = 0.03
MAX_DRAWS = 200


def _random_unit(rng: np.random.Generator) -> Matrix:
    u = rng.normal(size=3)
    return u / np.linalg.norm(u)


def draw_initial_cMo(rng: np.random.Generator, desired_cMo: Matrix, config: CellConfig) -> Matrix:
    """One candidate initial pose of the cube in the camera frame (not yet checked for reach)."""
    camera = config.plant().truth.camera
    side = config.plant().scene.cube.side_m
    corners_o = np.array([[0.0, 0.0, 0.0], [side, 0.0, 0.0], [side, side, 0.0], [0.0, side, 0.0]])
    for _ in range(MAX_DRAWS):
        twist = np.concatenate(
            [
                _random_unit(rng) * rng.uniform(0.0, MAX_TRANSLATION_M),
                _random_unit(rng) * rng.uniform(0.0, MAX_ROTATION_RAD),
            ]
        )
        # exp of a pure rotation then a translation: the camera turned in place, then moved.
        cdMc = exp_twist(np.concatenate([np.zeros(3), twist[3:]]))
        cdMc[:3, 3] = twist[:3]
        cMo = inverse(cdMc) @ desired_cMo
        corners_c = corners_o @ cMo[:3, :3].T + cMo[:3, 3]
        face_depth = float(corners_c[:, 2].mean())
        above_face = inverse(cMo)[2, 3] > MIN_HEIGHT_M  # the camera's height over the face plane
        if not (DEPTH_RANGE_M[0] <= face_depth <= DEPTH_RANGE_M[1] and above_face and np.all(corners_c[:, 2] > 0)):
            continue
        if visible_region(camera.project(corners_c), camera.image_size).seen:
            return cMo
    raise RuntimeError(f"no acceptable initial pose in {MAX_DRAWS} draws")


@dataclass(frozen=True)
class SampleOutcome:
    index: int
    converged: bool
    failure: str | None
    stage: str  # the stage the run ended in
    path_length_m: float
    iterations: int
    draws: int


def run_sample(config: CellConfig, settings: RunSettings, seed: int, index: int) -> SampleOutcome:
    """Sample ``index`` of the study: redrawn until the arm can reach it, then servoed."""
    rng = np.random.default_rng([seed, index])
    task = TASKS[2]
    for draw in range(1, MAX_DRAWS + 1):
        initial_cMo = draw_initial_cMo(rng, task.desired_cMo, config)
        try:
            result = run_task(config, replace(task, name=f"sample {index}", initial_cMo=initial_cMo), settings, seed)
        except UnreachableTarget:
            continue  # the arm cannot start there: not a failure of the method
        summary = result.summary()
        last_stage = str(result.outcome.cycles[-1].output.stage) if result.outcome.cycles else ""
        return SampleOutcome(
            index, summary["converged"], summary["failure"], last_stage, result.path_length_m, summary["iterations"], draw
        )
    raise RuntimeError(f"sample {index}: no reachable initial pose in {MAX_DRAWS} draws")


def _worker(job: tuple[CellConfig, RunSettings, int, int]) -> SampleOutcome:
    return run_sample(*job)


def run_montecarlo(
    config: CellConfig,
    settings: RunSettings,
    n: int,
    seed: int,
    processes: int | None = None,
    on_sample: Callable[[SampleOutcome], None] | None = None,
) -> dict[str, Any]:
    """Run n samples on all cores; the summary that ``vservo montecarlo --json`` prints."""
    jobs = [(config, settings, seed, i) for i in range(n)]
    processes = processes or os.cpu_count() or 1
    outcomes: list[SampleOutcome] = []
    # spawn, not fork: Pinocchio's objects and a parent's threads do not survive a fork safely.
    with get_context("spawn").Pool(processes) as pool:
        for outcome in pool.imap_unordered(_worker, jobs, chunksize=4):
            outcomes.append(outcome)
            if on_sample is not None:
                on_sample(outcome)
    return summarize(settings.method, n, seed, sorted(outcomes, key=lambda o: o.index), Arm(settings.arm))


def _stats(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"median": None, "p95": None}
    return {"median": round(float(np.median(values)), 6), "p95": round(float(np.percentile(values, 95)), 6)}


def summarize(method: str, n: int, seed: int, outcomes: list[SampleOutcome], arm: Arm = Arm.UPJ) -> dict[str, Any]:
    """Success rate; median and 95th percentile of path and iterations over the converged runs."""
    converged = [o for o in outcomes if o.converged]
    kept = "reachable" if arm is Arm.UPJ else "carried by no arm (a free camera)"
    return {
        "method": method,
        "arm": arm.value,
        "n": n,
        "seed": seed,
        "success_rate": round(len(converged) / n, 4) if n else None,
        "path_length_m": _stats([o.path_length_m for o in converged]),
        "iterations": _stats([float(o.iterations) for o in converged]),
        "failures": dict(sorted(Counter(o.failure for o in outcomes if not o.converged).items())),
        # The same failures by the stage they ended in ("no_progress in 1A"), and which samples.
        "failures_by_stage": dict(sorted(Counter(f"{o.failure} in {o.stage}" for o in outcomes if not o.converged).items())),
        "failed_samples": [o.index for o in outcomes if not o.converged],
        # How strongly the arm's reach filters the distribution: draws per kept pose.
        "draws_per_sample": round(float(np.mean([o.draws for o in outcomes])), 2) if outcomes else None,
        "distribution": (
            f"initial camera: rotation uniform in [0, pi] about a random axis and translation uniform in "
            f"[0, {MAX_TRANSLATION_M}] m in a random direction from task 2's desired pose; kept when the face "
            f"is {DEPTH_RANGE_M[0]}..{DEPTH_RANGE_M[1]} m in front, at least partly in the image, and {kept}"
        ),
    }
