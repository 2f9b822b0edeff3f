"""The vservo command line: --help, info --json, demo, and one-line errors."""

import json
import subprocess
import sys
from importlib import resources

import numpy as np
import pytest

from tests.jrc_fixtures import short_timer_cell
from vservo.app.cli import main
from vservo.core.cell.config import load_cell
from vservo.core.cell.kinematics import ArmKinematics
from vservo.core.geometry.spatial import pose_error
from vservo.core.robot.jrc import JrcBackend
from vservo.core.sim.plant import IK_TOLERANCE_M
from vservo.robot_models.loader import load_arm
from vservo.robot_models.upj_dh import UPJ_DH


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vservo.app.cli", *args], capture_output=True, text=True, timeout=120)


def shipped_cell() -> str:
    return resources.files("vservo.static").joinpath("cell.toml").read_text()


def test_help_lists_every_command():
    result = run("--help")
    assert result.returncode == 0
    for command in ("info", "demo"):
        assert command in result.stdout


def test_info_json_describes_robot_camera_and_laser(capsys):
    assert main(["info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["robot"]["name"] == "upj" and info["robot"]["dof"] == 6
    limits = np.radians(info["robot"]["joint_limits_deg"])
    assert np.allclose(limits, [[link.lower, link.upper] for link in UPJ_DH])
    assert info["camera"]["fx_px"] == pytest.approx(6.0 / 0.0074, abs=1e-3)
    assert info["camera"]["fy_px"] == pytest.approx(6.0 / 0.0074, abs=1e-3)
    assert info["camera"]["image_size_px"] == [640, 480]
    assert info["camera"]["principal_point_px"] == [320.0, 240.0]
    assert info["laser"]["baseline_mm"] == pytest.approx(30.0)
    assert info["laser"]["alpha_deg"] == pytest.approx(80.0)


def test_info_follows_the_cell_file(tmp_path, capsys):
    cell = tmp_path / "ur5.toml"
    text = shipped_cell().replace('arm = "upj"', 'arm = "ur5"')
    cell.write_text(text.replace("focal_length_mm = 6.0", "focal_length_mm = 7.2"))
    assert main(["--cell", str(cell), "info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["robot"]["name"] == "ur5" and info["robot"]["dof"] == 6
    assert info["camera"]["fx_px"] == pytest.approx(7.2 / 0.0074, abs=1e-3)


def test_a_bad_cell_file_gives_one_line_and_a_non_zero_exit(tmp_path):
    cell = tmp_path / "bad.toml"
    cell.write_text(shipped_cell().replace("focal_length_mm = 6.0", "focal_length_mm = -6.0"))
    result = run("--cell", str(cell), "info", "--json")
    assert result.returncode == 2
    assert result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1
    assert "camera.focal_length_mm = -6.0" in lines[0] and "bad.toml" in lines[0]

    missing = run("--cell", str(tmp_path / "none.toml"), "info")
    assert missing.returncode == 2 and "cell file not found" in missing.stderr


def test_unknown_command_is_refused():
    result = run("teleport")
    assert result.returncode != 0 and "invalid choice" in result.stderr


def test_demo_sees_the_thesis_laser_spot_and_measures_its_depth(capsys):
    assert main(["demo", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    home, teach, steps = report["steps"]
    assert home["corners_seen"] == 4
    assert teach["laser_spot_px"] == pytest.approx([327.2, 240.0], abs=0.1)
    assert teach["laser_depth_mm"] == pytest.approx(teach["true_depth_of_cube_face_mm"], abs=1e-3)
    # The four corners form the 100 px square of Table 5-2 around the principal point.
    corners = np.array(teach["corners_px"])
    assert np.allclose(np.ptp(corners, axis=0), [100.1, 100.1], atol=0.5)
    assert steps["elapsed_s"] == pytest.approx(10.0)
    # The robot controller's IK stops at 0.1 um (vservo.core.sim.plant.IK_TOLERANCE_M).
    assert steps["deviation_from_last_target_mm"] == pytest.approx(0.0, abs=IK_TOLERANCE_M * 1000.0)


def test_the_demo_steps_through_the_cells_motion_mode(tmp_path, capsys):
    cell = tmp_path / "velocity.toml"
    cell.write_text(shipped_cell().replace('mode = "position_steps"', 'mode = "velocity"'))
    assert main(["--cell", str(cell), "demo", "--json"]) == 0
    steps = json.loads(capsys.readouterr().out)["steps"][-1]
    assert steps["what"].startswith("5 velocity steps of 0.05 s")
    assert steps["elapsed_s"] == pytest.approx(5 * 0.05)
    assert steps["deviation_from_last_target_mm"] == pytest.approx(0.0, abs=IK_TOLERANCE_M * 1000.0)


def test_the_jrc_emulator_serves_a_pty_until_it_is_stopped():
    process = subprocess.Popen(
        [sys.executable, "-m", "vservo.app.cli", "jrc-emulator"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        device = process.stdout.readline().strip()
        assert device.startswith("/dev/")
        robot = JrcBackend(short_timer_cell().jrc, device)
        robot.connect()
        bMe = robot.read_pose()
        robot.close()
    finally:
        process.terminate()
        _, stderr = process.communicate(timeout=30)
    config = load_cell()
    home = ArmKinematics(load_arm(config.arm), config.nominal.mount).fk(config.home_q)
    translation, rotation = pose_error(bMe, home)
    assert translation < 1e-6 and rotation < np.radians(0.006)
    assert process.returncode == 0 and "served 2 exchanges, 0 moves" in stderr


def test_bench_jrc_sets_round_trips_against_the_wire_time(capsys):
    assert main(["bench", "jrc", "--samples", "3", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["line"].startswith("9600 8E1")
    for mode in ("pty", "paced_at_baud"):
        for command in ("RPOSC", "MOVL"):
            trips = result[mode][command]
            assert trips["n"] == 3 and trips["bytes"] > 20
            assert trips["wire_ms"] == pytest.approx(trips["bytes"] * 11 / 9600 * 1000, abs=1e-3)


def test_bench_jrc_soak_reports_its_figures(capsys):
    assert main(["bench", "jrc", "--soak", "10", "--fault-rate", "0", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["moves"] == 10 and result["faults_injected_total"] == 0
    assert result["commands_accepted_twice"] == 0 and result["final_pose_error_mm"] < 0.01


def test_the_jrc_commands_refuse_bad_arguments_in_one_line():
    rate = run("jrc-emulator", "--fault-rate", "2")
    assert rate.returncode == 2 and "expected a number from 0 to 1, got '2'" in rate.stderr
    port = run("jrc-emulator", "--port", "/dev/nonexistent-jrc")
    assert port.returncode == 2 and len(port.stderr.strip().splitlines()) == 1
    assert port.stderr.startswith("vservo jrc-emulator: error: cannot open the serial port /dev/nonexistent-jrc")


@pytest.mark.parametrize(
    "command",
    [("run", "--job", "demo"), ("montecarlo", "--n", "2"), ("calibrate", "collect"), ("bench", "jrc"), ("virtual-cell",)],
)
def test_a_negative_seed_is_refused_naming_the_option(command):
    refused = run(*command, "--seed", "-5")
    assert refused.returncode == 2
    assert refused.stderr.strip().endswith("error: argument --seed: expected a non-negative integer, got '-5'"), refused.stderr


@pytest.mark.slow
def test_the_cell_option_goes_before_or_after_the_command():
    for args in (
        ("--cell", "/nowhere/cell.toml", "info"),
        ("info", "--cell", "/nowhere/cell.toml"),
        ("calibrate", "--cell", "/nowhere/cell.toml", "track"),
        ("calibrate", "track", "--cell", "/nowhere/cell.toml"),
    ):
        result = run(*args)
        assert result.returncode == 2 and "cell file not found: /nowhere/cell.toml" in result.stderr


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (("serve", "--port", "70000"), "argument --port: expected a whole number from 1 to 65535, got '70000'"),
        (("serve", "--cycle-period", "nan"), "argument --cycle-period: expected a number from 0 to 10 s, got 'nan'"),
        (("controller", "--cycle-period", "1e300"), "argument --cycle-period: expected a number from 0 to 10 s, got '1e300'"),
        (("controller", "--port", "-1"), "argument --port: expected a whole number from 0 to 65535, got '-1'"),
        (("detect", "x.png", "--spot-threshold", "300"), "argument --spot-threshold: expected a whole number from 0 to 255"),
        (("virtual-cell", "--camera-port", "99999"), "argument --camera-port: expected a whole number from 0 to 65535"),
        (("reproduce", "--out", "x", "--montecarlo", "10000000"), "argument --montecarlo: expected a whole number from 0"),
        (("simulate", "--dt", "inf"), "argument --dt: expected a positive float, got 'inf'"),
        (("bench", "browsers", "--clients", "0"), "argument --clients: expected a whole number from 1 to 10000, got '0'"),
    ],
)
def test_a_number_option_beyond_its_range_is_refused_in_one_line(args, words):
    refused = run(*args)
    assert refused.returncode == 2, refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1 and words in refused.stderr, refused.stderr
