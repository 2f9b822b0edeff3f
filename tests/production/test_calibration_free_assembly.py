"""A cell whose truth is Table 5-5's errors away from its (nominal) cell file assembles a job
taught on it whatever the part's turn: the chain from the taught view to the release rests
on no calibration (core/production/grasp.py)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.controller_fixtures import simulated_controller
from vservo.core.cell.config import parse_cell, read_cell_data_with_truth
from vservo.core.production.assembly import Outcome, Phase
from vservo.core.production.demo_job import teach_demo_job

TABLE_5_5 = Path(__file__).resolve().parents[2] / "static" / "truths" / "table-5-5.toml"


@pytest.mark.slow
def test_parts_turned_over_the_whole_circle_are_placed_within_a_few_tenths_of_a_millimetre(tmp_path):
    config = parse_cell(*read_cell_data_with_truth(None, TABLE_5_5))
    assert not np.allclose(config.plant().truth.eMc, config.nominal.eMc)  # the model is off
    job, image, check_image = teach_demo_job(config)  # taught on this cell, through its nominal model
    rng = np.random.default_rng(1)
    bMo = config.plant().scene.cube.bMo
    centre_mm = 1000.0 * (bMo @ np.array([0.01, 0.01, 0.0, 1.0]))[:2]
    yaw_deg = np.degrees(np.arctan2(bMo[1, 0], bMo[0, 0]))
    with simulated_controller(config, tmp_path / "data") as controller:
        controller.store.save_job(replace(job, name="turned"), image, check_image)
        outcomes = []
        for turn_deg in np.linspace(-180.0, 180.0, 8, endpoint=False) + rng.uniform(0.0, 45.0):
            offset_mm = rng.uniform(0.0, 30.0) * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a)])
            if controller.state.phase == Phase.FAULT.value:
                controller.reset()
            controller.present_part(tuple(centre_mm + offset_mm), yaw_deg + turn_deg)
            controller.start("turned")
            controller.wait()
            outcomes.append((turn_deg, controller.last_outcome))
    placed = [outcome for _, outcome in outcomes if outcome.outcome is Outcome.PLACED]
    assert len(placed) >= 7, [(round(turn), outcome.reason) for turn, outcome in outcomes]
    for turn, outcome in outcomes:
        if outcome.outcome is Outcome.PLACED:
            assert outcome.gauge_inside and outcome.gauge_placement_error_mm < 0.3, (turn, outcome.reason)
        else:  # refused before the pick, saying what to do
            assert outcome.outcome is Outcome.FAULT and "refused before" in outcome.reason, (turn, outcome.reason)
            assert "present the part nearer its taught place" in outcome.reason
