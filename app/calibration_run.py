"""The NN hand-eye calibration workflow run from the app, in the background.

The steps are the command line's (``vservo calibrate collect | train | evaluate | track``,
core/calibration/), each run as its own process on the simulated cell, into a fresh
folder under the data folder: the app stays responsive, a step can be stopped, and
what is computed is exactly what the command line computes. Progress comes from the
steps' progress bars on standard error; results from their JSON on standard output.

Two presets: the thesis's defaults (the workflow as documented, minutes), and a quick
one (a coarser grid, fewer views and samples) that runs in about a minute, for a look.
Viser-free.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vservo.core.errors import VservoError

STEPS = ("collect", "train", "evaluate", "track")
QUICK = "quick (coarse grid, about a minute)"
THESIS = "thesis defaults (about 3 to 6 minutes)"
# Extra arguments per step; steps not named run with their defaults.
PRESETS: dict[str, dict[str, tuple[str, ...]]] = {
    QUICK: {
        "collect": ("--step-mm", "60", "--test-views", "10", "--rotated-views", "8"),
        "train": ("--samples", "3000", "--validation", "500", "--epochs", "40"),
        "track": ("--test", "random", "--points", "10"),
    },
    THESIS: {"track": ("--test", "random")},
}
_BAR = re.compile(r"\[[#.]+\] (\d+)/(\d+)")


class CalibrationFailed(VservoError, RuntimeError):
    """A step ended with an error; the message is the step's own last line."""


def bar_fraction(line: str) -> float | None:
    """How far a progress bar line (core/terminal/progress.py) is, 0..1; None for other lines."""
    match = _BAR.search(line)
    if match is None:
        return None
    done, total = int(match.group(1)), int(match.group(2))
    return min(done / max(total, 1), 1.0)


def step_command(step: str, folder: Path, preset: str, cell: str | None) -> list[str]:
    return [
        sys.executable,
        "-m",
        "vservo.app.cli",
        *(["--cell", cell] if cell else []),
        "calibrate",
        step,
        "--dir",
        str(folder),
        "--json",
        *PRESETS[preset].get(step, ()),
    ]


@dataclass
class CalibrationProgress:
    """Where the workflow is: its step, the overall fraction, and the results so far."""

    step: str = ""
    fraction: float = 0.0
    line: str = ""
    results: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    finished: bool = False
    started_s: float = field(default_factory=time.monotonic)


class CalibrationRun:
    """One workflow in a background thread; ``on_change`` hears every progress change."""

    def __init__(self, folder: Path, preset: str, cell: str | None, on_change: Callable[[CalibrationProgress], None]) -> None:
        if preset not in PRESETS:
            raise ValueError(f"unknown calibration preset {preset!r}: {', '.join(PRESETS)}")
        self.folder, self.preset, self.cell = folder, preset, cell
        self.on_change = on_change
        self.progress = CalibrationProgress()
        self._process: subprocess.Popen | None = None
        self._cancelled = threading.Event()
        self._thread = threading.Thread(target=self._run, name="app-calibration", daemon=True)

    def start(self) -> CalibrationRun:
        self._thread.start()
        return self

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def cancel(self) -> None:
        self._cancelled.set()
        process = self._process
        if process is not None and process.poll() is None:
            process.terminate()

    def wait(self, timeout_s: float | None = None) -> None:
        self._thread.join(timeout_s)

    def _run(self) -> None:
        progress = self.progress
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            for index, step in enumerate(STEPS):
                if self._cancelled.is_set():
                    raise CalibrationFailed("stopped by the operator")
                progress.step, progress.fraction = step, index / len(STEPS)
                self.on_change(progress)
                progress.results[step] = self._step(step, index)
            progress.fraction = 1.0
        except (CalibrationFailed, OSError) as exc:
            progress.error = str(exc)
        progress.finished = True
        self.on_change(progress)

    def _step(self, step: str, index: int) -> dict[str, Any]:
        command = step_command(step, self.folder, self.preset, self.cell)
        self._process = process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        stdout, stderr = process.stdout, process.stderr
        assert stdout is not None and stderr is not None  # both piped
        # Standard output (one JSON object) is small and read at the end; standard error
        # carries the progress lines as they come.
        last_line = ""
        for line in stderr:
            line = line.strip()
            if not line:
                continue
            last_line = line
            fraction = bar_fraction(line)
            if fraction is not None:
                self.progress.fraction = (index + fraction) / len(STEPS)
                self.progress.line = line
                self.on_change(self.progress)
        output = stdout.read()
        code = process.wait()
        stdout.close()
        stderr.close()
        if self._cancelled.is_set():
            raise CalibrationFailed("stopped by the operator")
        if code != 0:
            raise CalibrationFailed(f"{step} failed: {last_line or f'exit code {code}'}")
        try:
            return json.loads(output)
        except ValueError:
            raise CalibrationFailed(f"{step} printed no JSON result") from None


# The methods as an operator would call them (the table in the Engineering fold keeps the codes).
METHOD_WORDS = {
    "nn": "the network",
    "nn_height": "the network with the part's height",
    "nn_pose": "the network with the camera's pose",
    "free_hand_eye": "hand-eye from free views",
    "axxb": "hand-eye from turned views",
    "planar_homography": "the table's plane seen as a homography",
}


def summary_markdown(results: dict[str, Any]) -> str:
    """In plain words, best first: how far each method puts board corners it did not see (mm)."""
    held_out = (results.get("evaluate") or {}).get("methods") or {}
    ranked = sorted((row["xy_mm"], name) for name, row in held_out.items() if row.get("xy_mm") is not None)
    if not ranked:
        return ""
    lines = [f"- {METHOD_WORDS.get(name, name)}: {xy:.2f} mm off on average" for xy, name in ranked]
    return "Where each calibration puts board corners it was not shown, best first:\n\n" + "\n".join(lines)


def results_markdown(results: dict[str, Any]) -> str:
    """The per-method table (the Engineering fold): errors on the held-out corners and in PBVS tracking (measured
    by the calibration, and against the simulated cell's truth), mean over points, mm."""
    held_out = (results.get("evaluate") or {}).get("methods") or {}
    tracking = (results.get("track") or {}).get("methods") or {}
    if not held_out and not tracking:
        return "No results yet."
    lines = ["| method | held-out X | Y | XY | max XY | tracking XY | tracking XY, true |", "|---|---|---|---|---|---|---|"]
    for name in dict.fromkeys([*held_out, *tracking]):
        row, track = held_out.get(name, {}), tracking.get(name, {})

        def cell(values: dict, key: str) -> str:
            return "-" if values.get(key) is None else f"{values[key]:.3f}"

        lines.append(
            f"| {name} | {cell(row, 'x_mm')} | {cell(row, 'y_mm')} | {cell(row, 'xy_mm')} | "
            f"{cell(row, 'max_xy_mm')} | {cell(track, 'xy_mm')} | {cell(track.get('true', {}), 'xy_mm')} |"
        )
    evaluate = results.get("evaluate") or {}
    lines.append("")
    lines.append(
        f"mm; {evaluate.get('corners', '?')} held-out corners from {evaluate.get('views', '?')} views, "
        f"truth {evaluate.get('truth', '?')}, pixel noise {evaluate.get('pixel_noise_px', '?')} px; tracking: "
        f"{(results.get('track') or {}).get('points', '?')} {(results.get('track') or {}).get('test', '')} "
        "points (eq. 2-47)."
    )
    return "\n".join(lines)
