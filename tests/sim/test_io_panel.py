"""The virtual cell's I/O panel: the lines a PLC on the JRC's I/O is wired to. The PLC's
signals reach the host through IOREAD over the real link; what the host writes to the
PLC's network inputs comes out on the panel; other lines stay unwired."""

from __future__ import annotations

import json

import pytest

from tests.cell.test_config import default_data
from tests.cell.test_plc_config import JRC_IO
from tests.sim.test_virtual_cell import fixture_request
from vservo.core.robot.jrc import JrcBackend, JrcCommandError
from vservo.core.sim.virtual_cell import VirtualCell


@pytest.fixture
def panel_cell():
    data = default_data()
    assert data["robot"]["backend"] == "sim"  # the virtual cell's robot is its JRC whatever the file says
    data["line"] = {"plc": JRC_IO}
    with VirtualCell(data, "panel cell", seed=3) as virtual:
        jrc = JrcBackend(virtual.emulator.line, virtual.jrc_port)
        jrc.connect()
        try:
            yield virtual, jrc
        finally:
            jrc.close()


def test_the_plcs_signals_reach_the_host_and_the_hosts_reach_the_plc(panel_cell):
    virtual, jrc = panel_cell
    url = f"{virtual.fixture.url}/io"
    status, panel = fixture_request(url, "POST", json.dumps({"inputs": {"30": True, "40": True}}).encode())
    assert status == 200 and panel["inputs"] == {"30": True, "31": False, "32": False, "40": True}
    assert jrc.read_signal(30) and not jrc.read_signal(31) and jrc.read_signal(40)
    jrc.write_signals({27021: True, 27024: True})
    status, panel = fixture_request(url)
    assert status == 200 and [a for a, on in panel["outputs"].items() if on] == ["27021", "27024"]
    jrc.write_signal(27021, False)
    assert [a for a, on in fixture_request(url)[1]["outputs"].items() if on] == ["27024"]


@pytest.mark.parametrize(
    "body, words",
    [
        ({"inputs": {"33": True}}, "input 33 is not wired to the PLC: its inputs are 30, 31, 32, 40"),
        ({"inputs": {"30": 1}}, 'the body is {"inputs": {"<byte.bit address>": true|false, ...}}'),
        ({"lines": {}}, 'the body is {"inputs"'),
    ],
)
def test_the_panel_refuses_an_unwired_line_or_a_bad_body_and_changes_nothing(panel_cell, body, words):
    virtual, jrc = panel_cell
    status, reply = fixture_request(f"{virtual.fixture.url}/io", "POST", json.dumps(body).encode())
    assert status == 400 and words in reply["error"], reply
    assert not any(fixture_request(f"{virtual.fixture.url}/io")[1]["inputs"].values())


def test_the_jrc_still_refuses_writes_to_lines_nothing_is_wired_to(panel_cell):
    _, jrc = panel_cell
    with pytest.raises(JrcCommandError, match="2110"):
        jrc.write_signal(27030, True)
