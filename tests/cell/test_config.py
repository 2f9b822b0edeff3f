"""The cell configuration file: defaults of the thesis, truth overrides, errors that name the key."""

import re
import tomllib
from importlib import resources

import numpy as np
import pytest

from vservo.core.cell.config import ConfigError, StepPolicyKind, load_cell, parse_cell
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import matrix_from_pose, pose_from_mm_deg


def default_data() -> dict:
    return tomllib.loads(resources.files("vservo.static").joinpath("cell.toml").read_text())


def test_default_cell_holds_the_thesis_values():
    cell = load_cell()
    intrinsics = cell.nominal.camera.intrinsics
    assert intrinsics.fx == pytest.approx(6.0 / 0.0074) and intrinsics.fy == pytest.approx(6.0 / 0.0074)
    assert (intrinsics.u0, intrinsics.v0, intrinsics.width, intrinsics.height) == (320, 240, 640, 480)
    assert np.allclose(cell.nominal.laser.cMl, LaserPointer.in_plane(0.030, np.radians(80.0)).cMl)
    assert np.allclose(cell.nominal.eMc, np.eye(4))
    assert cell.motion.divide_factor == 50 and cell.motion.sampling_period_s == 2.0
    # The shipped cell servos with the fast policy; a file that names none, the thesis's.
    assert cell.motion.policy is StepPolicyKind.FAST
    data = default_data()
    del data["motion"]["policy"], data["motion"]["fast"], data["motion"]["move_speed_mm_s"]
    motion = parse_cell(data).motion
    assert motion.policy is StepPolicyKind.THESIS
    assert (motion.fast.max_step_m, motion.fast.speed_m_s) == (pytest.approx(0.04), pytest.approx(0.1))
    assert motion.move_speed_m_s == pytest.approx(0.05)
    # The fast policy's limits are held against [safety] only where it is the policy.
    data["safety"].update(max_step_mm=10.0)
    assert parse_cell(data).motion.fast.max_step_m == pytest.approx(0.04)
    data["motion"]["policy"] = "fast"
    with pytest.raises(ConfigError, match=r"motion.fast.max_step_mm = 40.0: exceeds \[safety\] max_step_mm = 10"):
        parse_cell(data)
    assert cell.arm == "upj" and cell.home_q.shape == (6,)
    assert cell.simulation.scene.cube.side_m == pytest.approx(0.020)


def test_default_cell_holds_the_controllers_factory_line_settings_and_safety_limits():
    cell = load_cell()
    line = cell.jrc
    assert cell.robot_backend == "sim"
    assert (line.baud, line.parity, line.data_bits, line.stop_bits, line.rtscts) == (9600, "even", 8, 1, True)
    assert (line.timer_a_s, line.timer_b_s, line.retry_1, line.retry_2) == (3.0, 20.0, 10, 3)
    # 8E1: start, 8 data, parity, stop = 11 bits a byte, about 870 bytes/s at 9600 baud.
    assert line.bits_per_character == 11 and line.wire_time_s(870) == pytest.approx(0.997, abs=1e-3)
    assert cell.safety.max_step_m == pytest.approx(0.05) and cell.safety.max_speed_m_s == pytest.approx(0.25)
    assert np.all(cell.safety.workspace_min_m < cell.safety.workspace_max_m)


def test_without_overrides_the_truth_equals_the_nominal_cell():
    cell = load_cell()
    assert cell.simulation.truth.camera == cell.nominal.camera
    assert np.array_equal(cell.simulation.truth.eMc, cell.nominal.eMc)
    assert np.array_equal(cell.simulation.truth.laser.cMl, cell.nominal.laser.cMl)


def test_truth_overrides_change_the_truth_only():
    """Truth overrides (the tables of Table 5-3's robustness cell) change the truth only."""
    data = default_data()
    data["camera"].update(focal_length_mm=7.2, principal_point_px=[384.0, 288.0])
    data["laser"]["cMl"] = [30.0, 10.0, 10.0, 0.0, -12.0, 2.0]
    data["simulation"]["truth"] = {
        "camera": {"focal_length_mm": 6.0, "principal_point_px": [320.0, 240.0]},
        "hand_eye": {"eMc": [-20.0, 20.0, 20.0, 5.0, 5.0, 5.0]},
        "laser": {"cMl": [30.0, 0.0, 0.0, 0.0, -10.0, 0.0]},
    }
    cell = parse_cell(data, "robustness")
    nominal, truth = cell.nominal, cell.simulation.truth
    assert nominal.camera.intrinsics.fx == pytest.approx(7.2 / 0.0074)
    assert truth.camera.intrinsics.fx == pytest.approx(6.0 / 0.0074)
    assert (truth.camera.intrinsics.u0, truth.camera.intrinsics.v0) == (320.0, 240.0)
    assert (nominal.camera.intrinsics.u0, nominal.camera.intrinsics.v0) == (384.0, 288.0)
    assert np.allclose(nominal.eMc, np.eye(4))
    assert np.allclose(truth.eMc, matrix_from_pose(pose_from_mm_deg([-20, 20, 20, 5, 5, 5])))
    assert np.allclose(truth.laser.cMl, matrix_from_pose(pose_from_mm_deg([30, 0, 0, 0, -10, 0])))
    assert np.allclose(nominal.laser.cMl, matrix_from_pose(pose_from_mm_deg([30, 10, 10, 0, -12, 2])))
    # The vacuum cup was not overridden: the truth inherits it.
    assert np.array_equal(truth.eMv, nominal.eMv)


@pytest.mark.parametrize(
    ("edit", "names"),
    [
        (lambda d: d["camera"].update(focal_length_mm=-6.0), ["camera.focal_length_mm", "-6.0", "positive"]),
        (lambda d: d["camera"].update(focal_length_mm="six"), ["camera.focal_length_mm", "'six'"]),
        (lambda d: d["camera"].update(focal_length_mm=float("nan")), ["camera.focal_length_mm", "nan", "finite"]),
        (lambda d: d["camera"].update(pixel_size_mm=[0.0074, 0.0]), ["camera.pixel_size_mm", "positive"]),
        (lambda d: d["camera"].update(image_size_px=[640.5, 480]), ["camera.image_size_px", "640.5"]),
        (lambda d: d["camera"].update(distortion=[0.1, 0.0]), ["camera.distortion", "5 finite numbers"]),
        (lambda d: d["hand_eye"].update(eMc=[0, 0, 0]), ["hand_eye.eMc", "6 finite numbers"]),
        (lambda d: d["laser"].update(cMl=[30, 0, 0, 0, True, 0]), ["laser.cMl"]),
        (lambda d: d["robot"].update(arm="kuka"), ["robot.arm", "'kuka'", "upj, ur5"]),
        (lambda d: d["robot"].pop("home_joints_deg"), ["missing key robot.home_joints_deg"]),
        (lambda d: d["camera"].update(focal_lenght_mm=6.0), ["unknown key camera.focal_lenght_mm"]),
        (lambda d: d.update(cameras={}), ["unknown key cameras"]),
        (lambda d: d["motion"].update(mode="teleport"), ["motion.mode", "position_steps, velocity"]),
        (lambda d: d["motion"].update(divide_factor=0.5), ["motion.divide_factor", "at least 1"]),
        (lambda d: d["motion"].update(policy="quick"), ["motion.policy", "'quick'", "thesis, fast"]),
        (
            lambda d: d["motion"]["fast"].update(max_step_mm=60.0),
            ["motion.fast.max_step_mm = 60.0", "exceeds [safety] max_step_mm = 50"],
        ),
        (lambda d: d["motion"]["fast"].update(max_step_deg=0.0), ["motion.fast.max_step_deg", "positive"]),
        (
            lambda d: d["safety"].update(max_speed_mm_s=80.0),
            ["motion.fast.speed_mm_s = 100.0", "exceeds [safety] max_speed_mm_s = 80"],
        ),
        (lambda d: d["motion"]["fast"].update(gain=0.5), ["unknown key motion.fast.gain"]),
        (lambda d: d["motion"].update(move_speed_mm_s=0.0), ["motion.move_speed_mm_s = 0.0", "positive"]),
        (lambda d: d["simulation"].update(pixel_noise_px=-1), ["simulation.pixel_noise_px", ">= 0"]),
        (lambda d: d["simulation"].update(seed=1.5), ["simulation.seed", "integer"]),
        (lambda d: d["simulation"]["scene"].pop("object_pose"), ["simulation.scene.object_pose"]),
        (
            lambda d: d["simulation"].update(truth={"camera": {"focal_length_mm": 0}}),
            ["[simulation.truth]", "camera.focal_length_mm", "positive"],
        ),
        (lambda d: d["simulation"].update(truth={"lens": {}}), ["unknown key simulation.truth.lens"]),
        (lambda d: d.update(camera=3), ["camera must be a table"]),
        (lambda d: d["robot"].update(backend="kuka-rsi"), ["robot.backend", "'kuka-rsi'", "sim, jrc"]),
        (lambda d: d["jrc"].update(baud=9601), ["jrc.baud", "9601", "150, 300, 600, 1200, 2400, 4800, 9600, 19200"]),
        (lambda d: d["jrc"].update(parity="mark"), ["jrc.parity", "'mark'", "even, odd, none"]),
        (lambda d: d["jrc"].update(data_bits=9), ["jrc.data_bits", "9", "7, 8"]),
        (lambda d: d["jrc"].update(stop_bits=1.5), ["jrc.stop_bits", "1.5", "integer"]),
        (lambda d: d["jrc"].update(rtscts="yes"), ["jrc.rtscts", "'yes'", "true or false"]),
        (lambda d: d["jrc"].update(port=""), ["jrc.port", "non-empty string"]),
        (lambda d: d["jrc"].update(timer_a_s=0), ["jrc.timer_a_s", "positive"]),
        (lambda d: d["jrc"].update(retry_2=-1), ["jrc.retry_2", "-1", ">= 0"]),
        (lambda d: d["jrc"].update(retries=3), ["unknown key jrc.retries"]),
        (
            lambda d: d["safety"].update(workspace_max_mm=[-700.0, 400.0, 450.0]),
            ["safety.workspace_max_mm", "[-700.0, 400.0, 450.0]", "must exceed workspace_min_mm"],
        ),
        (lambda d: d["safety"].update(max_step_mm=float("inf")), ["safety.max_step_mm", "finite"]),
        (lambda d: d["safety"].update(watchdog_s=-2.0), ["safety.watchdog_s", "-2.0", "more than 0"]),
        (lambda d: d["safety"].update(watchdog_s=1e300), ["safety.watchdog_s", "1e+300", "at most 600 s"]),
        (lambda d: d["safety"].update(watchdog_s=float("nan")), ["safety.watchdog_s", "nan", "finite"]),
        (
            lambda d: d["robot"].update(home_joints_deg=[0.0, 500.0, 150.0, 0.0, -75.0, 0.0]),
            ["robot.home_joints_deg", "500.0", "beyond the upj's joint limits", "[-85.0, 90.0]"],
        ),
        (
            lambda d: d["robot"].update(home_joints_deg=[0.0, 45.0, 150.0]),
            ["robot.home_joints_deg", "3 values, the upj arm has 6 joints"],
        ),
        (
            lambda d: d["camera"].update(image_size_px=[1e6, 1e6]),
            ["camera.image_size_px", "[1000000.0, 1000000.0]", "from 1 to 20000"],
        ),
        (
            lambda d: d["camera"].update(source={"kind": "webcam"}),
            ["camera.source.kind", "'webcam'", "simulated, capture, folder"],
        ),
        (lambda d: d["camera"].update(source={"kind": "capture"}), ["missing key camera.source.device"]),
        (lambda d: d["camera"].update(source={"kind": "capture", "device": -1}), ["camera.source.device", "-1"]),
        (
            lambda d: d["camera"].update(source={"kind": "capture", "device": 0, "reconnect_attempts": -2}),
            ["camera.source.reconnect_attempts", "-2", ">= 0"],
        ),
        (
            lambda d: d["camera"].update(source={"kind": "capture", "device": 0, "buffer_frames": -1}),
            ["camera.source.buffer_frames", "-1", ">= 0"],
        ),
        (
            lambda d: d["camera"].update(source={"kind": "capture", "device": 0, "exposure_latency_s": -0.1}),
            ["camera.source.exposure_latency_s", "-0.1", ">= 0"],
        ),
        (
            lambda d: d["camera"].update(source={"kind": "folder", "path": "frames", "device": 0}),
            ["unknown key camera.source.device"],
        ),
        (lambda d: d["simulation"].update(truth={"camera": {"source": {"kind": "capture"}}}), ["unknown key camera.source"]),
        (
            lambda d: d["vacuum"].update(device="suction-cup"),
            ["vacuum.device", "'suction-cup'", "simulated, jrc_io, ur_io, none"],
        ),
        (
            lambda d: (d["robot"].update(backend="jrc"), d["vacuum"].update(device="jrc_io", suction_output=27010)),
            ["missing key vacuum.grip_input"],
        ),
        (
            lambda d: (
                d["robot"].update(backend="jrc"),
                d["vacuum"].update(device="jrc_io", suction_output=27018, grip_input=20),
            ),
            ["vacuum.suction_output", "27018", "bit, is 0..7"],
        ),
        (
            lambda d: d["vacuum"].update(device="jrc_io", suction_output=27010, grip_input=20),
            ["vacuum.device = 'jrc_io'", "robot.backend", "'sim'"],
        ),
        (lambda d: d["camera"].update(source={"kind": "capture", "device": 0}), ["robot.backend = 'sim'", "'capture'", "jrc"]),
        (
            lambda d: (d["robot"].update(backend="jrc"), d["camera"].update(source={"kind": "folder", "path": "f"})),
            ["vacuum.device = 'simulated'", "'folder'", "jrc_io"],
        ),
    ],
)
def test_a_bad_value_is_reported_with_its_key_and_value(edit, names):
    data = default_data()
    edit(data)
    with pytest.raises(ConfigError) as error:
        parse_cell(data, "bad.toml")
    message = str(error.value)
    assert message.startswith("bad.toml")
    for name in names:
        assert name in message, (name, message)


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="cell file not found: .*nowhere.toml"):
        load_cell(tmp_path / "nowhere.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("[camera\nfocal_length_mm = 6\n")
    with pytest.raises(ConfigError, match=r"broken.toml: not valid TOML"):
        load_cell(broken)
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"seed\xaa\xff\x00")
    with pytest.raises(ConfigError, match=r"binary.toml: not a text file \(byte 4 is not UTF-8\)"):
        load_cell(binary)


def test_a_cell_file_on_disk_round_trips(tmp_path):
    text = resources.files("vservo.static").joinpath("cell.toml").read_text()
    path = tmp_path / "my_cell.toml"
    path.write_text(text.replace("focal_length_mm = 6.0", "focal_length_mm = 6.02"))
    cell = load_cell(path)
    assert cell.source == str(path)
    assert cell.nominal.camera.intrinsics.fx == pytest.approx(6.02 / 0.0074)


def test_a_real_cell_names_its_camera_and_its_vacuum_on_the_jrcs_io(tmp_path):
    """[camera.source] and the [vacuum] device: a relative folder is read from the cell file's folder."""
    text = resources.files("vservo.static").joinpath("cell.toml").read_text()
    for key, value in (
        ("backend", '"jrc"'),
        ("device", '"jrc_io"\nsuction_output = 27013\ngrip_input = 20'),
        ("kind", '"folder"\npath = "frames"'),
    ):
        text, count = re.subn(rf"^{key} = .*$", f"{key} = {value}", text, flags=re.MULTILINE)
        assert count == 1, key
    path = tmp_path / "real.toml"
    path.write_text(text)
    cell = load_cell(path)
    assert cell.real and cell.camera_source.kind == "folder" and cell.camera_source.path == tmp_path / "frames"
    assert (cell.vacuum_device.device, cell.vacuum_device.suction_output, cell.vacuum_device.grip_input) == ("jrc_io", 27013, 20)
    # The wiring keys are no part of the model: the nominal and true cells are as before.
    assert np.allclose(cell.nominal.eMv, load_cell().nominal.eMv)
    capture = parse_cell(
        {
            **default_data(),
            "robot": {**default_data()["robot"], "backend": "jrc"},
            "vacuum": {"device": "none"},
            "camera": {
                "source": {
                    "kind": "capture",
                    "device": "rtsp://cell-camera/stream",
                    "reconnect_attempts": 5,
                    "reconnect_delay_s": 1.0,
                    "exposure_latency_s": 0.12,
                    "buffer_frames": 4,
                }
            },
        },
        "capture.toml",
    )
    assert capture.camera_source.device == "rtsp://cell-camera/stream" and capture.camera_source.reconnect_attempts == 5
    assert capture.camera_source.exposure_latency_s == 0.12 and capture.camera_source.buffer_frames == 4
    assert capture.vacuum_device.device == "none"


def test_the_shipped_cell_is_the_simulated_one():
    cell = load_cell()
    assert not cell.real and cell.camera_source.kind == "simulated" and cell.vacuum_device.device == "simulated"


@pytest.mark.parametrize(
    ("table", "key", "value", "words"),
    [
        ("jrc", "timer_a_s", 1e300, "must be positive and at most 60 s"),
        ("jrc", "timer_b_s", 1e9, "must be positive and at most 600 s"),
        ("jrc", "retry_1", 10**12, "must be a whole number >= 0 and at most 255"),
        ("motion", "sampling_period_s", 1e12, "must be positive and at most 60 s"),
        ("motion", "move_speed_mm_s", 1e9, "must be positive and at most 5000 mm/s"),
        ("motion", "divide_factor", 1e15, "must be at least 1 and at most 10000"),
        ("safety", "max_step_mm", 1e9, "must be positive and at most 1000 mm"),
        ("safety", "max_speed_mm_s", 1e9, "must be positive and at most 5000 mm/s"),
        ("camera", "focal_length_mm", 1e12, "must be positive and at most 1000 mm"),
        ("simulation", "seed", -1, "must be a whole number >= 0 and at most 4294967295"),
        ("simulation", "pixel_noise_px", 1e9, "must be >= 0 and at most 100 px"),
    ],
)
def test_a_number_beyond_the_products_range_is_refused_naming_the_key_and_the_range(table, key, value, words):
    """Keys that took any positive number (a timer of 10^300 s waited for ever) take only the product's range."""
    data = default_data()
    data[table][key] = value
    with pytest.raises(ConfigError) as error:
        parse_cell(data, "big.toml")
    assert str(error.value) == f"big.toml: {table}.{key} = {value!r}: {words}"
