"""``vservo bench calibration``: how long Levenberg-Marquardt takes to train the NN.

The data are real calibration data (the ideal cell's checkerboard images on a 40 mm
grid, corners detected), 16,000 corners for training as in the thesis's experiment and
2,000 others for validation, the 4-20-2 network, goal 1e-8 (Appendix B). The time is
the training's wall clock; the load average says how busy the machine was.
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np
import torch

from vservo.core.calibration.collection import Collector, Workspace
from vservo.core.calibration.levenberg_marquardt import LMSettings
from vservo.core.calibration.mlp import train_nn
from vservo.core.cell.config import CellConfig

TARGET_S = 30.0


def bench_calibration(config: CellConfig, seed: int = 0, samples: int = 16000, validation: int = 2000) -> dict[str, Any]:
    started = time.perf_counter()
    collector = Collector(config, "ideal", 1, Workspace(step_m=0.040))
    targets, _ = collector.grid_targets()
    dataset, counts = collector.collect(targets)
    collected = time.perf_counter()
    if dataset.size < samples + validation:
        raise ValueError(f"the bench grid gave {dataset.size} corners, fewer than {samples + validation}")
    order = np.random.default_rng(seed).permutation(dataset.size)
    stamps: list[float] = []
    settings = LMSettings()
    start = time.perf_counter()
    model = train_nn(
        dataset.subset(order[:samples]),
        "planar",
        validation=dataset.subset(order[samples : samples + validation]),
        settings=settings,
        seed=seed,
        on_epoch=lambda epoch, mse: stamps.append(time.perf_counter()),
    )
    train_s = time.perf_counter() - start
    epochs = np.diff([start, *stamps])
    return {
        "samples": samples,
        "validation_samples": validation,
        "network": "4-20-2 tanh/linear, float64",
        "epochs": model.training["epochs"],
        "stop": model.training["stop"],
        "mse": model.training["mse"],
        "goal": settings.goal,
        "reached_goal": model.training["stop"] == "goal",
        "train_s": round(train_s, 3),
        "epoch_median_s": round(float(np.median(epochs)), 4) if len(epochs) else None,
        "target_s": TARGET_S,
        "collect_s": round(collected - started, 1),
        "views": counts.views,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
    }
