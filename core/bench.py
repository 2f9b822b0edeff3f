"""``vservo bench vision``: time and accuracy of seeing, measured on this machine.

Times are medians and 95th percentiles over many frames (a shared 2-core machine is
noisy: a single number means little). Accuracy compares detections with the TRUE
projections of the simulated cell, which only an evaluation may read.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from core.config import CellConfig
from core.render import RenderSettings, SceneRenderer
from core.servo_loop import Cycle
from core.simulator import SimulatedCell
from core.spatial import Matrix, inverse
from core.study import RunSettings, run_task
from core.tasks import TASKS
from core.vision.corners import detect_corners
from core.vision.pipeline import front_winding
from core.vision.region import detect_object_region
from core.vision.spot import detect_laser_spot

NOISE_LEVELS = (0.0, 1.0, 3.0)


def _stats_ms(seconds: list[float]) -> dict[str, float]:
    ms = 1000.0 * np.asarray(seconds)
    return {"median_ms": round(float(np.median(ms)), 3), "p95_ms": round(float(np.percentile(ms, 95)), 3), "n": len(ms)}


def _servo_joints(config: CellConfig) -> list[Matrix]:
    """The arm's joints along task 2's laser servo: the views a live loop really sees."""
    joints: list[Matrix] = []

    def remember(cycle: Cycle) -> None:
        joints.append(cycle.measurement.q)

    run_task(config, TASKS[2], RunSettings(method="laser"), on_cycle=remember)
    return joints


def bench_vision(config: CellConfig, seed: int = 0, cycles: int = 3) -> dict[str, Any]:
    """Render and detection times, whole-cycle times, and detection accuracy vs the truth."""
    rng = np.random.default_rng(seed)
    cell = SimulatedCell(config, seed)
    scene = config.simulation.scene
    cell.place_cube(TASKS[2].placement.bMo(scene.table_height_m, scene.cube.side_m))
    views = _servo_joints(config)
    winding = front_winding(cell.state.scene.cube.corners_o)
    camera_true = cell.truth.model.camera

    accuracy: dict[str, Any] = {}
    render_s: list[float] = []
    detect_s: list[float] = []
    for noise in NOISE_LEVELS:
        renderer = SceneRenderer(camera_true, RenderSettings(noise_sigma=noise))
        corner_errors, spot_errors = [], []
        for q in views:
            cell.set_joints(q)
            bMc, spot_b = cell.ground_truth_view()
            start = time.perf_counter()
            image = renderer.render(cell.state.scene, bMc, spot_b, rng)
            rendered = time.perf_counter()
            spot = detect_laser_spot(image)
            corners = detect_corners(image, spot=spot, winding=winding)
            detect_object_region(image)
            detect_s.append(time.perf_counter() - rendered)
            render_s.append(rendered - start)

            cMb = inverse(bMc)
            true_corners = camera_true.project(cell.state.scene.cube.corners_b @ cMb[:3, :3].T + cMb[:3, 3])
            if corners.found:
                corner_errors.append(np.sum((corners.corners_px - true_corners) ** 2, axis=1))
            if spot.found and spot_b is not None:
                true_spot = camera_true.project((cMb[:3, :3] @ spot_b + cMb[:3, 3])[None, :])[0]
                spot_errors.append(float(np.linalg.norm(spot.spot_px - true_spot)))
        squared = np.concatenate(corner_errors) if corner_errors else np.array([np.nan])
        accuracy[f"noise_{noise:g}"] = {
            "frames": len(views),
            "corners_found": len(corner_errors),
            "corner_rms_px": round(float(np.sqrt(np.mean(squared))), 4),
            "corner_max_px": round(float(np.sqrt(np.max(squared))), 4),
            "spot_found": len(spot_errors),
            "spot_mean_px": round(float(np.mean(spot_errors)), 4) if spot_errors else None,
            "spot_max_px": round(float(np.max(spot_errors)), 4) if spot_errors else None,
        }

    # Whole look-and-move cycles with rendered features: between two cycle callbacks lie
    # the command to the simulated robot (its IK), the robot readout, the frame, the
    # detection and the control law.
    cycle_s: list[float] = []
    stamps: list[float] = []
    rendered_settings = RunSettings(method="laser", features="rendered", render=RenderSettings(noise_sigma=1.0))
    for _ in range(cycles):
        stamps.clear()
        run_task(config, TASKS[2], rendered_settings, on_cycle=lambda cycle: stamps.append(time.perf_counter()))
        cycle_s += list(np.diff(stamps))

    return {
        "image_size": list(camera_true.image_size),
        "render": _stats_ms(render_s),
        "detection": _stats_ms(detect_s),
        "cycle": _stats_ms(cycle_s),
        "accuracy": accuracy,
        "targets": {"detection_median_ms": 5.0, "cycle_median_ms": 10.0, "corner_rms_px_clean": 0.1,
                    "corner_rms_px_noise_3": 0.3, "spot_px": 0.2},
        "views": "the arm's poses along task 2's laser servo",
    }
