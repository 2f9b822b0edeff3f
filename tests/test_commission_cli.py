"""`vservo commission` on the shipped simulated cell, and locating a part with the network it
trains: the command as an integrator runs it, its file, and the locate step's accuracy."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.test_cell_file import comments_of, is_subsequence
from vservo.core.cell.config import load_cell
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.commissioning import CommissionSettings
from vservo.core.production.locate import LocateError, PartLocator
from vservo.core.production.rig import Rig
from vservo.core.study.locate_bench import bench_locate, survey_pose

SHIPPED = Path(__file__).resolve().parents[1] / "static" / "cell.toml"


def _vservo(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vservo.app.cli", *args], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def commissioned(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("commission") / "cell-commissioned.toml"
    done = _vservo("commission", "--cell", str(SHIPPED), "--out", str(out), "--reference", str(SHIPPED), "--seed", "1", "--json")
    assert done.returncode == 0, done.stderr[-2000:]
    return out, json.loads(done.stdout)


def test_commission_measures_the_cell_and_writes_a_new_file(commissioned):
    out, summary = commissioned
    assert summary["good"] and summary["out"] == str(out)
    for key in ("fx_px", "fy_px", "principal_point_px", "distortion"):
        assert key in summary["camera"]
    assert len(summary["eMc_mm_deg"]) == len(summary["cMl_mm_deg"]) == 6
    # The shipped cell is its own truth: what is measured is what the file says.
    errors = summary["against_reference"]
    assert abs(errors["fx_percent"]) < 0.5 and errors["principal_point_px"] < 2.0
    assert errors["eMc_mm"] < 1.0 and errors["eMc_deg"] < 0.2
    assert errors["beam_direction_deg"] < 0.2 and errors["beam_at_162_mm"] < 0.5
    assert summary["laser"]["baseline_mm"] == pytest.approx(30.0, abs=0.5)
    assert summary["laser"]["alpha_deg"] == pytest.approx(80.0, abs=0.2)
    assert summary["acceptance"]["max_mm"] < 0.5
    assert summary["acceptance"]["corners"] == CommissionSettings().acceptance_corners  # unreachable corners skipped
    config = load_cell(out)
    assert config.commissioning.nn_path.is_file()
    assert config.nominal.camera.intrinsics.fx == pytest.approx(summary["camera"]["fx_px"], abs=1e-3)
    assert config.commissioning.provenance["camera"]["verdict"] == "good"
    views = json.loads((out.parent / "cell-commissioned-commissioning" / "views.json").read_text())
    assert sum("corners" in v["found"] for v in views) == summary["views"]["used"]
    # The cell's clock: at least the flange's way from view to view at the commissioning speed
    # (the turns, the settling and the acceptance check come on top).
    flange_m = np.array([np.asarray(v["bMe"])[:3, 3] for v in views if v["bMe"] is not None])
    way_m = np.linalg.norm(np.diff(flange_m, axis=0), axis=1).sum()
    assert way_m > 1.0 and summary["cell_time_s"] >= way_m / CommissionSettings().speed_m_s


def test_the_commissioned_file_keeps_every_comment_of_its_input(commissioned):
    out, _ = commissioned
    assert is_subsequence(comments_of(SHIPPED.read_text()), comments_of(out.read_text()))


def test_commission_never_writes_over_its_input_or_an_existing_file(commissioned):
    out, _ = commissioned
    same = _vservo("commission", "--cell", str(out), "--out", str(out), "--force")
    assert same.returncode == 2 and "is the input cell file" in same.stderr
    existing = _vservo("commission", "--cell", str(SHIPPED), "--out", str(out))
    assert existing.returncode == 2 and "exists" in existing.stderr
    steps = _vservo("commission", "--cell", str(SHIPPED), "--out", str(out.with_name("x.toml")), "--steps", "camera,eyes")
    assert steps.returncode == 2 and "--steps" in steps.stderr


def _seen_from_survey(rig: Rig, bMe: np.ndarray) -> np.ndarray:
    rig.robot.move_linear(bMe, 0.1)
    features, _ = rig.extractor.extract(rig.camera.read_after(rig.robot.clock_s()).image)
    return features.corners_px


@pytest.mark.parametrize("place", [(-0.400, -0.010, 0.0), (-0.440, 0.030, 0.6), (-0.370, -0.050, -1.2)])
def test_the_network_locates_a_part_anywhere_in_the_survey_view(commissioned, place):
    out, _ = commissioned
    rig = build_rig(load_cell(out), 1)
    try:
        rig.robot.connect()
        rig.robot.servo(True)
        rig.place_part(*place)
        locator = rig.locator
        assert isinstance(locator, PartLocator)
        bMe = survey_pose(locator)
        located = locator.locate(_seen_from_survey(rig, bMe), rig.robot.read_pose(), 0.020)
        bMo_true = rig.cell.state.scene.cube.bMo
        assert np.linalg.norm(located.bMo[:3, 3] - bMo_true[:3, 3]) < 1.5e-3
        turn = np.arctan2(located.bMo[1, 0], located.bMo[0, 0]) - np.arctan2(bMo_true[1, 0], bMo_true[0, 0])
        # The same up to quarter turns; the edge of a 20 mm face gives the turn to a degree or two.
        assert abs(np.angle(np.exp(4j * turn))) / 4 < np.deg2rad(2.0)
    finally:
        rig.close()


def test_a_survey_the_network_was_not_trained_for_is_refused(commissioned):
    out, _ = commissioned
    locator = PartLocator.from_config(load_cell(out))
    higher = survey_pose(locator)
    higher[2, 3] += 0.05
    with pytest.raises(LocateError, match="trained at"):
        locator.check_survey(higher)
    aside = survey_pose(locator)
    aside[0, 3] += 0.3
    with pytest.raises(LocateError, match="outside the grid"):
        locator.check_survey(aside)


def test_a_locating_job_assembles_the_parts_its_bench_draws_where_the_arm_can_serve_them(commissioned, tmp_path):
    """Seeded: the bench's servable check predicts where the servo ends (the desired view
    of the part as its mark numbers its corners), so the places it draws are served. When
    the start was a quarter turn short of that, two of these three runs ended with the
    pick beyond the arm's reach."""
    out, _ = commissioned
    result = bench_locate(load_cell(out), "demo", 3, 2, tmp_path)
    assert result["placed"] == 3, result["failures"]
    assert result["placement_error_mm"]["max"] < 0.3
