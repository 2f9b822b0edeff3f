"""``vservo replay``: play a recorded run back through the vision and the control law.

Two checks an integrator runs on a recording from the field or from the simulator:
the detectors, run again on every recorded frame, find the corners the run found; and
the control law, given every recorded cycle's features, takes the same stage and
commands the same twist. A difference means the software or its settings changed since
the recording, or the recording is not what it claims.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.cell.config import load_cell
from vservo.core.cell.scene import Cube
from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.features import DesiredImage, ImageFeatures, ObjectRegion
from vservo.core.perception.recording import Recording
from vservo.core.perception.vision.pipeline import ImageFeatureExtractor, front_winding
from vservo.core.servo.laws.base import Stage
from vservo.core.servo.methods import LaserLaw, build_law
from vservo.core.sim.render_settings import RenderSettings
from vservo.core.study.run import RunSettings


def _array(value: Any, shape: tuple[int, ...]) -> Matrix:
    """A recorded array; null (NaN when recorded) comes back as NaN."""
    return np.array(value if value is not None else np.full(shape, np.nan), dtype=float).reshape(shape)


def _desired(record: dict[str, Any]) -> DesiredImage:
    return DesiredImage(
        corners_px=_array(record["corners_px"], (4, 2)),
        laser_spot_px=_array(record["laser_spot_px"], (2,)),
        depth_m=float(record["depth_m"]),
        cdMo=_array(record["cdMo"], (4, 4)),
        corner_depths_m=_array(record["corner_depths_m"], (4,)),
    )


def _features(cycle: dict[str, Any]) -> ImageFeatures:
    region = cycle["region"]
    return ImageFeatures(
        corners_px=np.array([[np.nan, np.nan] if c is None else c for c in cycle["corners_px"]], dtype=float),
        laser_spot_px=_array(cycle["laser_spot_px"], (2,)),
        laser_depth_m=np.nan if cycle["laser_depth_m"] is None else float(cycle["laser_depth_m"]),
        region=ObjectRegion(float(region["area_px2"]), _array(region["centroid_px"], (2,))),
        corner_depths_m=np.full(4, np.nan),
        reference_px=np.full(2, np.nan),
    )


def replay(folder: str | Path, cell_path: str | Path | None = None) -> dict[str, Any]:
    """Compare a recording with what this software computes from it."""
    recording = Recording.open(folder)
    description = recording.description
    settings_record = dict(description["settings"])
    settings_record["render"] = RenderSettings(**settings_record["render"])
    # A recording from before the robust law ran the thesis's.
    settings_record["laser_law"] = LaserLaw(settings_record.get("laser_law", LaserLaw.THESIS))
    settings = RunSettings(**{**settings_record, "record_to": None})
    desired = _desired(description["desired"])
    model = load_cell(cell_path).nominal
    law = build_law(model, settings)
    extractor = ImageFeatureExtractor(model.camera, model.laser, front_winding(Cube(np.eye(4)).corners_o))

    corner_differences, twist_differences = [], []
    stage_mismatches = 0
    previous_stage, previous_corners = None, None
    for cycle in recording.cycles:
        recorded = _features(cycle)
        frame = recording.frame_of(cycle)
        if frame is not None:
            seen, _ = extractor.extract(frame.image, previous_corners)
            both = seen.corners_visible & recorded.corners_visible
            if both.any():
                corner_differences.append(float(np.abs(seen.corners_px[both] - recorded.corners_px[both]).max()))
            if recorded.all_corners_visible:
                previous_corners = recorded.corners_px
        output = law.step(recorded, desired, previous_stage)
        twist_differences.append(float(np.abs(output.cVc - _array(cycle["cVc"], (6,))).max()))
        stage_mismatches += output.stage != cycle["stage"]
        previous_stage = Stage(cycle["stage"])

    return {
        "recording": str(folder),
        "cycles": len(recording.cycles),
        "frames": len(recording.frame_paths),
        "truncated_last_line": recording.truncated_last_line,
        "outcome": recording.summary.get("outcome") if recording.summary else None,
        "corner_difference_px_max": max(corner_differences) if corner_differences else None,
        "twist_difference_max": max(twist_differences) if twist_differences else None,
        "stage_mismatches": stage_mismatches,
    }
