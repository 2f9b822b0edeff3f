"""A run's stage timeline as a chart: one bar per servo stage, in the order they ran, as long
as the stage's share of the cycles, in the stage's colour, labelled in the operator's words.

Drawn with OpenCV into an image (viser has no bar chart), the same in every browser.
"""

from __future__ import annotations

import cv2
import numpy as np

from vservo.app.banner import stage_words
from vservo.core.production.protocol import RunEntry

WIDTH, ROW, LEFT = 640, 34, 250
STAGE_BGR = {
    "1A": (180, 119, 31),
    "1B": (14, 127, 255),
    "2": (44, 160, 44),
    "3": (40, 39, 214),
    "ibvs": (189, 103, 148),
    "pbvs": (75, 86, 140),
}
OTHER_BGR = (127, 127, 127)


def stage_chart(run: RunEntry | None) -> np.ndarray:
    """The chart of a run's stages (servo cycles per stage, in order) as a BGR image; a one-line
    image that says so when the run recorded no servo cycles (or there is no run)."""
    stages = [s for s in (run.stages if run is not None else ()) if s.iterations > 0]
    total = sum(s.iterations for s in stages)
    image = np.full((ROW * max(1, len(stages)) + 30, WIDTH, 3), 255, np.uint8)
    if not total:
        cv2.putText(image, "no servo cycles recorded", (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
        return image
    start = 0
    scale = (WIDTH - LEFT - 60) / total
    for row, stage in enumerate(stages):
        count = stage.iterations
        top = 8 + row * ROW
        x0, x1 = LEFT + int(round(start * scale)), LEFT + max(int(round((start + count) * scale)), 1 + int(round(start * scale)))
        cv2.rectangle(image, (x0, top), (x1, top + ROW - 10), STAGE_BGR.get(stage.stage, OTHER_BGR), -1)
        cv2.putText(image, stage_words(stage.stage), (8, top + 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(image, str(count), (x1 + 5, top + 17), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (60, 60, 60), 1, cv2.LINE_AA)
        start += count
    axis_y = image.shape[0] - 14
    cv2.line(image, (LEFT, axis_y), (WIDTH - 60, axis_y), (0, 0, 0), 1)
    cv2.putText(
        image, f"servo cycles (of {total})", (LEFT, axis_y + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA
    )
    return image
