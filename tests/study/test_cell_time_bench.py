"""The demo job's cell time through the JRC link at 9600 baud: the same on every run of a
seed, within 15 % of the floor of its moves, one move per taught segment."""

import pytest

from vservo.core.cell.config import load_cell
from vservo.core.cell.kinematics import ArmKinematics
from vservo.core.geometry.spatial import pose_error
from vservo.core.production.jobs import read_job_file
from vservo.core.production.storage import shipped_job_path
from vservo.core.sim.plant import ROTATION_SPEED_RAD_S
from vservo.core.study.cell_time_bench import bench_cell_time
from vservo.robot_models.loader import load_arm

pytestmark = pytest.mark.usefixtures("no_leaked_threads")


def test_the_demo_through_the_jrc_reads_the_same_cell_time_on_every_run_within_the_floor_of_its_moves(tmp_path):
    config = load_cell()
    first = bench_cell_time(config, "demo", seed=1, data=tmp_path / "first")
    second = bench_cell_time(config, "demo", seed=1, data=tmp_path / "second")
    assert first["outcome"] == second["outcome"] == "placed"
    assert first["baud"] == 9600
    # Deterministic: the same exchanges, the same cell time, phase by phase.
    assert first["cell_time_s"] == second["cell_time_s"] and first["by_phase"] == second["by_phase"]
    assert first["cell_time_s"] <= 1.15 * first["floor_s"]
    phases = first["by_phase"]
    assert list(phases) == ["start", "servo", "pick", "place", "check"]
    assert sum(p["cell_time_s"] for p in phases.values()) == pytest.approx(first["cell_time_s"], abs=0.005)
    # One move per taught segment (start; down, up to the pick; over, down, up to the place;
    # the check), one pose read in the whole run.
    assert [phases[name]["moves"] for name in ("start", "pick", "place", "check")] == [1, 3, 3, 1]
    assert first["pose_reads"] == 1
    # The start move's motion by the emulator's motion model, worked out here: from the
    # home pose to the job's start pose, the translation at the taught speed or the
    # rotation at the JRC's rate, whichever takes longer.
    home_bMe = ArmKinematics(load_arm(config.arm), config.nominal.mount).fk(config.home_q)
    translation, rotation = pose_error(home_bMe, read_job_file(shipped_job_path("demo")).start_bMe)
    expected = max(translation / config.motion.move_speed_m_s, rotation / ROTATION_SPEED_RAD_S)
    assert phases["start"]["motion_s"] == pytest.approx(expected, abs=0.002)
