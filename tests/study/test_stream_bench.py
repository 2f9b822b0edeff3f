"""``vservo bench stream``: the cell's views through a real MJPEG stream read by OpenCV."""

import json
import subprocess
import sys

from vservo.app.cli import main
from vservo.core.cell.config import load_cell
from vservo.core.study.stream_bench import bench_stream


def test_two_views_through_the_stream_keep_their_corners_and_spot(capsys):
    assert main(["bench", "stream", "--views", "2", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["views"] == 2 and result["jpeg_quality"] == 100 and result["image_size"] == "640x480"
    corners, spot = result["corners"], result["spot"]
    assert corners["n"] == 8 and corners["views_disagreeing"] == 0  # every corner found in both images
    assert corners["max_px"] < 0.5 and spot["n"] == 2 and spot["max_px"] < 0.5
    assert result["jpeg_kib_median"] > 0 and result["exposure_to_read"]["median_ms"] > 0


def test_a_coarse_jpeg_costs_more_than_a_fine_one():
    """The bench sees what the compression does: it is not comparing an image with itself."""
    config = load_cell(None)
    fine, coarse = (bench_stream(config, views=2, quality=q) for q in (100, 20))
    assert coarse["jpeg_kib_median"] < fine["jpeg_kib_median"]
    assert coarse["corners"]["median_px"] > 5 * fine["corners"]["median_px"]


def test_a_bad_quality_is_refused_in_one_line():
    process = subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "bench", "stream", "--quality", "101"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert process.returncode == 2 and "a JPEG quality is an integer in 0..100, got '101'" in process.stderr
