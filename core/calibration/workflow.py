"""The calibration workflow an integrator runs, step by step, on files in one folder.

    collect   datasets: planar.npz (the grid of section 3.2), test.npz (held-out random
              viewpoints), rotated.npz (wrist rotations for AX = XB and the camera
              calibration) and, on request, varying_train.npz / varying_test.npz (height,
              tilt and yaw varying: the 6-DOF variant)
    train     nn.npz (or nn_height.npz, nn_pose.npz) by Levenberg-Marquardt, and the
              classical calibrations free_hand_eye.npz, axxb.npz, planar_homography.npz
    evaluate  world-coordinate errors of every calibration on the held-out corners
    track     PBVS tracking (eq. 2-47) with every calibration: sinusoid or random points
    compare   the realistic truth at several pixel noises: every method, beside Table 3-4

Every step returns one JSON-ready dict. The tracking cell is rebuilt from the metadata of
the data (cell file, truth, seed, pixel noise), so it is the same simulated cell.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.calibration.baselines import (
    FreeHandEye,
    HandEyeAXXB,
    PlanarCalibration,
    PlanarHomography,
    calibrate_camera,
    load_classical,
    save_classical,
)
from vservo.core.calibration.collection import Collector, Workspace, add_pixel_noise, cell_with_truth
from vservo.core.calibration.dataset import INPUT_SETS, CalibrationDataset, DatasetError
from vservo.core.calibration.levenberg_marquardt import LMSettings
from vservo.core.calibration.mlp import HIDDEN_UNITS, NNCalibration, train_nn
from vservo.core.calibration.tracking import (
    Tracker,
    TrackingSettings,
    error_summary,
    random_targets,
    sinusoid_points,
    tracking_summary,
)
from vservo.core.cell.config import CellConfig
from vservo.core.terminal.progress import Progress

CLASSICAL = ("free_hand_eye", "axxb", "planar_homography")
NN_FILES = {"planar": "nn", "height": "nn_height", "pose": "nn_pose"}
# Table 3-4 (experiment, mean error in mm: X, Y, XY).
THESIS_TABLE_3_4 = {
    "free_hand_eye": {"x_mm": 2.70, "y_mm": 2.46, "xy_mm": 3.79},
    "axxb": {"x_mm": 0.78, "y_mm": 1.45, "xy_mm": 1.73, "note": "Motai's hand-eye calibration"},
    "nn": {"x_mm": 0.28, "y_mm": 0.43, "xy_mm": 0.58},
}
THESIS_TABLE_3_2 = {"nn": {"x_mm": 0.0048, "y_mm": 0.0098, "xy_mm": 0.0050}}
DEFAULT_NOISE_PX = {"ideal": 0.0, "realistic": 0.25}


@dataclass(frozen=True)
class CollectPlan:
    """What to collect: the workspace grid and held-out viewpoints (``planar``), rotated
    and varying viewpoints (none when their count is 0)."""

    workspace: Workspace = Workspace()
    planar: bool = True
    test_views: int = 40
    rotated_views: int = 30
    varying_views: int = 0
    varying_test_views: int = 60


def _path(folder: Path, name: str) -> Path:
    return folder / f"{name}.npz"


def collect(
    config: CellConfig, folder: Path, truth: str, noise_px: float | None, seed: int, plan: CollectPlan = CollectPlan()
) -> dict[str, Any]:
    """Collect every dataset of the plan into ``folder`` (module docstring)."""
    noise = DEFAULT_NOISE_PX.get(truth, config.plant().pixel_noise_px) if noise_px is None else noise_px
    collector = Collector(config, truth, seed, plan.workspace)
    rng = np.random.default_rng([seed, 3])
    grid, unreachable = collector.grid_targets()
    sets: list[tuple[str, list]] = []
    if plan.planar:
        sets += [("planar", grid), ("test", collector.heldout_targets(plan.test_views, rng))]
    if plan.rotated_views:
        centre = tuple(np.mean([M[:2, 3] for M in grid], axis=0)) if grid else (0.0, 0.0)
        sets.append(("rotated", collector.rotated_targets(plan.rotated_views, rng, centre)))
    if plan.varying_views:
        sets.append(("varying_train", collector.varying_targets(plan.varying_views, rng)))
        sets.append(("varying_test", collector.varying_targets(plan.varying_test_views, rng)))
    summary: dict[str, Any] = {
        "truth": truth,
        "pixel_noise_px": noise,
        "seed": seed,
        "folder": str(folder),
        "workspace": plan.workspace.as_dict(),
        "grid": {"viewpoints": len(grid) + unreachable, "reachable": len(grid)},
        "sets": {},
    }
    for stream, (name, targets) in enumerate(sets):
        progress = Progress(len(targets), f"collect {name}")
        dataset, counts = collector.collect(targets, on_view=progress.advance)
        progress.close()
        dataset = add_pixel_noise(dataset, noise, seed, stream)
        dataset = replace(
            dataset,
            metadata={
                **dataset.metadata,
                "set": name,
                "counts": counts.as_dict(),
                "grid_unreachable": unreachable if name == "planar" else 0,
            },
        )
        dataset.save(_path(folder, name))
        summary["sets"][name] = {"file": str(_path(folder, name)), **counts.as_dict()}
    return summary


def load_dataset(folder: Path, name: str) -> CalibrationDataset:
    path = _path(folder, name)
    if not path.is_file():
        raise DatasetError(
            f"{path}: no such file; run vservo calibrate collect first"
            + (" with --varying-views N" if name.startswith("varying") else "")
        )
    return CalibrationDataset.load(path)


def _split(dataset: CalibrationDataset, samples: int, validation: int, seed: int) -> tuple[CalibrationDataset, ...]:
    order = np.random.default_rng([seed, 5]).permutation(dataset.size)
    if dataset.size < samples + validation:
        samples = max(dataset.size - validation, dataset.size // 2)
    return dataset.subset(order[:samples]), dataset.subset(order[samples : samples + validation])


def train(
    config: CellConfig,
    folder: Path,
    inputs: str = "planar",
    samples: int = 16000,
    validation: int = 2000,
    settings: LMSettings = LMSettings(),
    seed: int = 0,
    hidden: int = HIDDEN_UNITS,
) -> dict[str, Any]:
    """Train the NN on ``samples`` corners (validation on others) and, for planar inputs,
    fit the classical calibrations; every result is saved in ``folder``."""
    data = load_dataset(folder, "planar" if inputs == "planar" else "varying_train")
    fit, check = _split(data, samples, validation, seed)
    progress = Progress(settings.epochs, f"train nn ({inputs})")
    model = train_nn(
        fit,
        inputs,
        validation=check,
        hidden=hidden,
        settings=settings,
        seed=seed,
        on_epoch=lambda epoch, mse: progress.advance(f"mse {mse:.3g}"),
    )
    progress.close()
    model.save(_path(folder, NN_FILES[inputs]))
    summary: dict[str, Any] = {
        "nn": {
            "file": str(_path(folder, NN_FILES[inputs])),
            "inputs": list(INPUT_SETS[inputs]),
            "hidden": hidden,
            **{k: v for k, v in model.training.items() if k != "dataset"},
        }
    }
    if inputs != "planar":
        return summary
    nominal = config.nominal.camera
    free = FreeHandEye.fit(data, nominal)
    save_classical(free, _path(folder, free.name))
    summary[free.name] = {"file": str(_path(folder, free.name)), "k1": free.camera.distortion.k1}
    if _path(folder, "rotated").is_file():
        rotated = load_dataset(folder, "rotated")
        axxb = HandEyeAXXB.fit(rotated, nominal)
        camera, _, rms = calibrate_camera(rotated, nominal)
        planar = PlanarHomography.fit(data, camera)
        for calibration in (axxb, planar):
            save_classical(calibration, _path(folder, calibration.name))
        summary[axxb.name] = {"file": str(_path(folder, axxb.name)), "camera_rms_px": round(rms, 4), "views": rotated.views}
        summary[planar.name] = {"file": str(_path(folder, planar.name))}
    else:
        summary["axxb"] = summary["planar_homography"] = {"skipped": "no rotated.npz (collect with --rotated-views > 0)"}
    return summary


def load_calibrations(folder: Path) -> dict[str, PlanarCalibration]:
    """Every calibration saved in ``folder``, by method name."""
    found: dict[str, PlanarCalibration] = {}
    for inputs, name in NN_FILES.items():
        if _path(folder, name).is_file():
            found[name] = NNCalibration.load(_path(folder, name), inputs)
    for name in CLASSICAL:
        if _path(folder, name).is_file():
            found[name] = load_classical(_path(folder, name))
    if not found:
        raise DatasetError(f"{folder}: no calibration found; run vservo calibrate train first")
    return found


def evaluate(folder: Path, test_set: str = "test") -> dict[str, Any]:
    """World-coordinate errors of every calibration on the corners of a held-out dataset."""
    test = load_dataset(folder, test_set)
    bMe = test.bMe[test.view]
    methods = {}
    for name, calibration in load_calibrations(folder).items():
        errors = calibration.world_of(test.pixels_px, bMe) - test.world_m
        methods[name] = error_summary(errors[np.all(np.isfinite(errors), axis=1)])
    return {
        "test": test_set,
        "corners": test.size,
        "views": test.views,
        "truth": test.metadata.get("truth"),
        "pixel_noise_px": test.metadata.get("pixel_noise_px"),
        "methods": methods,
    }


def tracker_for(config: CellConfig, folder: Path, settings: TrackingSettings) -> tuple[Tracker, CalibrationDataset]:
    """The simulated cell the data came from (cell, truth, seed and pixel noise of planar.npz)."""
    planar = load_dataset(folder, "planar")
    meta = planar.metadata
    if meta.get("cell") != config.source:
        raise DatasetError(
            f"{_path(folder, 'planar')}: collected on the cell {meta.get('cell')!r}, not {config.source!r}: pass the same --cell"
        )
    settings = replace(
        settings,
        pixel_noise_px=float(meta.get("pixel_noise_px", 0.0)),
        camera_height_m=float(meta["workspace"]["camera_height_mm"]) / 1000.0,
    )
    return Tracker(config, str(meta["truth"]), int(meta["seed"]), settings), planar


def track(
    config: CellConfig,
    folder: Path,
    test: str,
    points: int = 40,
    amplitude_m: float = 0.040,
    settings: TrackingSettings = TrackingSettings(),
    seed: int = 0,
    methods: Sequence[str] | None = None,
) -> dict[str, Any]:
    """PBVS tracking with every planar calibration in ``folder`` (tracking module docstring)."""
    calibrations = {name: c for name, c in load_calibrations(folder).items() if name in (methods or ("nn", *CLASSICAL))}
    results: dict[str, Any] = {}
    summary: dict[str, Any] = {"test": test}
    for name, calibration in calibrations.items():
        tracker, planar = tracker_for(config, folder, settings)
        if test == "sinusoid":
            targets = sinusoid_points(amplitude_m)
            progress = Progress(len(targets), f"track {name}")
            outcome = tracker.track_path(calibration, targets, on_point=lambda r: progress.advance())
            summary["amplitude_mm"] = 1000 * amplitude_m
        elif test == "random":
            ws = planar.metadata["workspace"]
            targets, starts = random_targets(
                tracker, points, seed, tuple(np.array(ws["x_range_mm"]) / 1000), tuple(np.array(ws["y_range_mm"]) / 1000)
            )
            progress = Progress(len(targets), f"track {name}")
            outcome = tracker.track_from(calibration, targets, starts, on_point=lambda r: progress.advance())
        else:
            raise ValueError(f"unknown tracking test {test!r}: sinusoid or random")
        progress.close()
        results[name] = tracking_summary(outcome)
        summary["truth"], summary["pixel_noise_px"] = planar.metadata.get("truth"), tracker.settings.pixel_noise_px
    summary["points"] = len(targets)
    summary["methods"] = results
    return summary


def compare(
    config: CellConfig,
    folder: Path,
    noise_levels: Sequence[float] = (0.1, 0.25, 0.5),
    seed: int = 1,
    plan: CollectPlan = CollectPlan(),
    samples: int = 16000,
    settings: LMSettings = LMSettings(),
    points: int = 40,
) -> dict[str, Any]:
    """The realistic truth at each pixel noise: collect once (noise-free detections), then
    per noise level add the noise, train every method, evaluate and track random points."""
    base = folder / "noise_free"
    collect(config, base, "realistic", 0.0, seed, plan)
    rows: dict[str, Any] = {}
    for level in noise_levels:
        level_folder = folder / f"noise_{level:g}px"
        for stream, name in enumerate(("planar", "test", "rotated")):
            if _path(base, name).is_file():
                noisy = add_pixel_noise(load_dataset(base, name), level, seed, stream)
                noisy.save(_path(level_folder, name))
        train(config, level_folder, "planar", samples, settings=settings, seed=seed)
        rows[f"{level:g}"] = {
            "evaluate": evaluate(level_folder)["methods"],
            "track_random": track(config, level_folder, "random", points, seed=seed)["methods"],
        }
    return {
        "truth": "realistic",
        "noise_px": list(noise_levels),
        "results": rows,
        "thesis_table_3_4": THESIS_TABLE_3_4,
        "truth_parameters": _realistic_description(config),
    }


def _realistic_description(config: CellConfig) -> dict[str, Any]:
    from vservo.core.calibration import collection

    truth = cell_with_truth(config, "realistic").plant()
    return {
        "distortion_k1_k2_p1_p2_k3": truth.truth.camera.distortion.as_opencv().tolist(),
        "eMc_error_mm_deg": list(collection.REALISTIC_eMc_MM_DEG),
        "joint_placement_error_mm_deg": [
            truth.joint_placement_error_m * 1000,
            float(np.rad2deg(truth.joint_placement_error_rad)),
        ],
        "repeatability_mm_deg": [truth.repeatability_m * 1000, float(np.rad2deg(truth.repeatability_rad))],
    }
