"""docs/connecting-your-cell.md cannot rot: its cell files load, and what it says of them holds.

The page's first ```toml block is a whole real cell file; each later block is a set of
tables that replace the same-named tables of a copy of it, as the page tells the
integrator to do (the dry run's [camera.source], the Ethernet controller's [jrc]).
"""

import re
from pathlib import Path

import pytest

from vservo.core.cell.config import HostTransport, load_cell
from vservo.core.production.cell_controller import JOG_SPEED_M_S
from vservo.core.robot.jrc import JrcBackend
from vservo.core.robot.safety import SafetyLayer, TooFast

PAGE = Path(__file__).resolve().parents[2] / "docs" / "connecting-your-cell.md"
HEADER = re.compile(r"^\[[^\]]+\]", re.MULTILINE)


def toml_blocks() -> list[str]:
    return re.findall(r"^```toml\n(.*?)^```", PAGE.read_text(), re.MULTILINE | re.DOTALL)


def replace_tables(base: str, tables: str) -> str:
    """``base`` with every table that ``tables`` names replaced by its version there."""
    for name in HEADER.findall(tables):
        start = base.index(f"\n{name}\n") + 1
        following = HEADER.search(base, start + len(name))
        base = base[:start] + (base[following.start() :] if following else "")
    return base + "\n" + tables


def test_the_example_is_a_real_cell_on_the_jrc_with_its_cup_on_the_jrc_io(tmp_path):
    example, *_ = toml_blocks()
    (tmp_path / "mycell.toml").write_text(example)
    config = load_cell(tmp_path / "mycell.toml")
    assert config.real and config.camera_source.kind == "capture"
    assert config.robot_backend == "jrc" and config.vacuum_device.device == "jrc_io"
    # The I/O check of section 2 switches the example's own addresses.
    vacuum = config.vacuum_device
    assert f"JrcVacuum(jrc, {vacuum.suction_output}, {vacuum.grip_input})" in PAGE.read_text()


def test_the_examples_first_jog_limits_let_a_jog_through_and_refuse_a_runs_speed(tmp_path):
    """Section 5: at home, a jog's speed is allowed and the servo steps' [motion] speed refused."""
    example, *_ = toml_blocks()
    (tmp_path / "mycell.toml").write_text(example)
    config = load_cell(tmp_path / "mycell.toml")
    safety = SafetyLayer.from_config(JrcBackend(config.jrc), config)  # never connected: nothing is sent
    bMe_home = safety.arm.fk(config.home_q)
    safety.check_target(bMe_home, JOG_SPEED_M_S, bMe_now=bMe_home)
    with pytest.raises(TooFast):
        safety.check_target(bMe_home, config.motion.speed_m_s, bMe_now=bMe_home)


def test_the_dry_run_reads_the_image_folder_beside_the_cell_file(tmp_path):
    example, *fragments = toml_blocks()
    fragments = [fragment for fragment in fragments if "[camera.source]" in fragment]
    assert fragments, "the page shows the dry run's [camera.source]"
    for index, fragment in enumerate(fragments):
        cell_file = tmp_path / f"dry{index}.toml"
        cell_file.write_text(replace_tables(example, fragment))
        config = load_cell(cell_file)
        assert config.real and config.camera_source.kind == "folder"
        assert config.camera_source.path == tmp_path / "frames"


def test_the_ethernet_controllers_jrc_makes_the_example_a_cell_on_its_ethernet_server(tmp_path):
    """Section 8: the example with its [jrc] replaced loads as a real cell on the Ethernet
    server, and the check that it answers is built on the link it names (not connected)."""
    example, *fragments = toml_blocks()
    (ethernet,) = [fragment for fragment in fragments if "[jrc]" in fragment]
    cell_file = tmp_path / "mycell.toml"
    cell_file.write_text(replace_tables(example, ethernet))
    config = load_cell(cell_file)
    assert config.real and config.jrc.transport is HostTransport.ETHERNET
    assert config.jrc.address == "192.168.255.1:80" and JrcBackend(config.jrc).port == config.jrc.address
    words = " ".join(PAGE.read_text().split())
    assert f"cannot connect to the Ethernet server at {config.jrc.address}" in words  # the error, as the link words it
