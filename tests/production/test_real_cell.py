"""A real cell: the controller builds its rig from the cell file, and on a real cell it
never loads the simulator.

The "real" cell here is a JRC emulator on a pseudo-terminal, started by the test, and an
image folder for a camera: to the controller process they are a serial device and a
camera source like any other. The simulator runs in the test process only (it moves the
emulated arm, holds the part and rendered the frames).
"""

import json
import re
import subprocess
import sys
from importlib import resources
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.jrc_fixtures import TEST_LINE, TIME_SCALE
from vservo.core.cell.config import ConfigError, VacuumDeviceConfig, load_cell
from vservo.core.geometry.spatial import inverse
from vservo.core.perception.camera_source import CameraSourceError
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.storage import Store
from vservo.core.robot.jrc import JrcBackend
from vservo.core.robot.jrc_vacuum import JrcVacuum
from vservo.core.robot.safety import SafetyLayer
from vservo.core.sim.camera import SimulatedCamera
from vservo.core.sim.jrc_emulator import JrcEmulator
from vservo.core.sim.plant import SimulatedCell

SIM_FOLDER = Path(resources.files("vservo.core.sim"))
# Every module of the simulator. The sim folder's cli.py only registers `vservo
# jrc-emulator` on the command line's parser (it imports nothing of the simulator), so
# it and the package's empty __init__ are loaded by every `vservo` command.
SIMULATOR_MODULES = {f"vservo.core.sim.{path.stem}" for path in SIM_FOLDER.glob("*.py")} - {
    "vservo.core.sim.__init__",
    "vservo.core.sim.cli",
}
VACUUM_IO = '"jrc_io"\nsuction_output = 27013\ngrip_input = 20'


def real_cell_text(port: str, camera_source: str, vacuum: str = VACUUM_IO) -> str:
    """The shipped cell as a real one: the JRC on ``port``, the camera source (the value of
    [camera.source] kind and its keys) and the vacuum device (likewise) given."""
    text = resources.files("vservo.static").joinpath("cell.toml").read_text()
    # The vacuum's device before the camera's kind, which may bring a capture's own device key.
    keys = {
        "backend": '"jrc"',
        "port": f'"{port}"',
        "sampling_period_s": "0.05",
        "device": vacuum,
        "kind": camera_source,
        **{key: str(value) for key, value in TEST_LINE.items()},
    }
    for key, value in keys.items():
        text, count = re.subn(rf"^{key} = .*$", f"{key} = {value}", text, flags=re.MULTILINE)
        assert count == 1, key
    return text


def loaded_modules(importtime_log: str) -> set[str]:
    """The modules a process imported, from its ``python -X importtime`` log."""
    return {
        line.rsplit("|", 1)[1].strip() for line in importtime_log.splitlines() if line.startswith("import time:") and "|" in line
    } - {"package"}


@pytest.mark.usefixtures("no_leaked_threads")
def test_a_real_cell_assembles_through_the_jrc_and_an_image_folder_without_loading_the_simulator(tmp_path):
    """`vservo run` on a real cell file: the JRC (an emulator on a pty) moves the arm, the
    camera is an image folder, the cup is on the JRC's I/O; the run places the part, its
    placement measured by the camera from the check pose (the folder's frame shows the part
    as taught) and no gauge figure (a real cell has none), and its process imported no module of
    the simulator (``python -X importtime`` lists every module a process imports)."""
    store = Store(tmp_path / "data")
    demo = store.load_job("demo")
    store.close()
    shipped = load_cell()
    # The part lies where, seen from the job's start pose, it looks as it did when taught:
    # the servo converges at once on the folder's still frames and the cup meets the part.
    bMo = demo.start_bMe @ inverse(demo.taught_bMe) @ shipped.simulation.scene.cube.bMo
    cell, view = SimulatedCell(shipped), SimulatedCell(shipped)  # the emulated arm's plant; the frames' twin
    frames = tmp_path / "frames"
    frames.mkdir()
    for plant in (cell, view):
        plant.place_cube(bMo)
    view.move_joints(view.jrc_ik(demo.start_bMe), 1.0, settle=True)
    image = SimulatedCamera(view).read().image
    for i in range(20):
        cv2.imwrite(str(frames / f"{i:04d}.png"), image)
    # This cell's ladder line and pressure switch, as the cell file below wires them.
    wiring = VacuumDeviceConfig("jrc_io", suction_output=27013, grip_input=20)
    with JrcEmulator(cell, shipped.jrc, time_scale=TIME_SCALE, vacuum=wiring) as emulator:
        cell_file = tmp_path / "real-cell.toml"
        # The cell's model is its own (the frames' twin plays it), as a commissioned cell's is.
        declared = '\n[commissioning]\nprovenance = { declared = "the emulated arm and the frames play this model" }\n'
        cell_file.write_text(real_cell_text(emulator.device, '"folder"\npath = "frames"') + declared)
        config = load_cell(cell_file)
        assert config.vacuum_device == wiring
        run = subprocess.run(
            [
                sys.executable,
                "-X",
                "importtime",
                "-m",
                "vservo.app.cli",
                "--cell",
                str(cell_file),
                "run",
                "--job",
                "demo",
                "--data",
                str(tmp_path / "data"),
                "--json",
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
    errors = "\n".join(line for line in run.stderr.splitlines() if not line.startswith("import time:"))
    assert run.returncode == 0, (run.stdout, errors)
    summary = json.loads(run.stdout)
    assert summary["outcome"] == "placed", summary
    assert summary["gauge_placement_error_mm"] is None and summary["gauge_inside"] is None
    assert summary["placement_error_mm"] < 1.0 and "seen" in summary["reason"]
    assert not cell.holding_part and any(move.startswith("MOVL") for move in emulator.executed)
    modules = loaded_modules(run.stderr)
    assert "vservo.core.production.cell_rig" in modules and "vservo.core.robot.jrc_vacuum" in modules
    assert not modules & SIMULATOR_MODULES, sorted(modules & SIMULATOR_MODULES)


def test_the_simulated_cell_file_still_builds_the_simulated_rig():
    rig = build_rig(load_cell(), seed=1)
    try:
        assert rig.cell is not None and rig.present_part is not None and rig.measure_placement() is not None
    finally:
        rig.close()


def test_a_real_cell_file_chooses_the_jrc_behind_the_safety_layer_and_the_cup_on_its_io(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "0000.png"), np.zeros((480, 640), np.uint8))
    cell_file = tmp_path / "cell.toml"
    cell_file.write_text(real_cell_text("/dev/ttyUSB3", '"folder"\npath = "frames"'))
    rig = build_rig(load_cell(cell_file))  # nothing is opened but the camera: the port waits for connect()
    try:
        assert isinstance(rig.robot, SafetyLayer) and isinstance(rig.robot.robot, JrcBackend)
        assert rig.robot.robot.port == "/dev/ttyUSB3" and rig.robot.name == "jrc"
        assert isinstance(rig.gripper, JrcVacuum)
        assert (rig.gripper.suction_output, rig.gripper.grip_input) == (27013, 20)
        assert rig.measure_placement() is None  # no gauge on a real cell
    finally:
        rig.close()


def test_a_real_cells_camera_is_checked_when_the_rig_is_built(tmp_path):
    """A folder of frames of another size than the intrinsics', a capture that cannot be
    opened, and a simulator's backend asked of a real cell: each an error naming it."""
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "0000.png"), np.zeros((600, 800), np.uint8))
    cell_file = tmp_path / "cell.toml"
    cell_file.write_text(real_cell_text("/dev/null", '"folder"\npath = "frames"', vacuum='"none"'))
    with pytest.raises(ConfigError, match=r"0000.png' is 800x600, the camera's image_size_px is 640x480"):
        build_rig(load_cell(cell_file))
    with pytest.raises(ConfigError, match="not by the 'sim' backend"):
        build_rig(load_cell(cell_file), backend="sim")
    cell_file.write_text(real_cell_text("/dev/null", f'"capture"\ndevice = "{tmp_path / "none.avi"}"', vacuum='"none"'))
    with pytest.raises(CameraSourceError, match="none.avi.*no such file"):
        build_rig(load_cell(cell_file))
