"""[line.plc] in the cell file: every key checked on load, each error one line naming the
key, the value and what it must be."""

from __future__ import annotations

import copy

import pytest

from tests.cell.test_config import default_data
from vservo.core.cell.config import ConfigError, PlcTransport, parse_cell

MODBUS = {
    "transport": "modbus",
    "inputs": {"start": 0, "part_present": 1, "reset": 2, "job_bits": [8, 9]},
    "outputs": {"ready": 0, "busy": 1, "done": 2, "ok": 3, "not_ok": 4, "fault": 5},
    "jobs": {"1": "demo", "3": "other"},
}
JRC_IO = {
    "transport": "jrc_io",
    "inputs": {"start": 30, "part_present": 31, "reset": 32, "job_bits": [40]},
    "outputs": {"ready": 27020, "busy": 27021, "done": 27022, "ok": 27023, "not_ok": 27024, "fault": 27025},
    "jobs": {"1": "demo"},
}


def cell_with(plc: dict, backend: str = "sim", **vacuum):
    data = default_data()
    data["robot"]["backend"] = backend
    data["vacuum"].update(vacuum)
    data["line"] = {"plc": plc}
    return parse_cell(data, "line.toml")


def changed(base: dict, path: str, value) -> dict:
    plc = copy.deepcopy(base)
    *tables, key = path.split(".")
    target = plc
    for table in tables:
        target = target[table]
    if value is None:
        del target[key]
    else:
        target[key] = value
    return plc


def test_a_cell_without_line_has_no_plc_and_the_defaults_of_a_modbus_plc():
    assert parse_cell(default_data(), "cell").plc is None
    plc = cell_with(MODBUS).plc
    assert plc.transport is PlcTransport.MODBUS and (plc.host, plc.port, plc.poll_period_s) == ("127.0.0.1", 5020, 0.05)
    assert plc.jobs == ((1, "demo"), (3, "other")) and plc.job_name(3) == "other" and plc.job_name(2) is None
    assert plc.inputs.addresses() == (0, 1, 2, 8, 9) and plc.part_id_register is None
    on_jrc = cell_with(JRC_IO, backend="jrc").plc
    assert on_jrc.transport is PlcTransport.JRC_IO and on_jrc.outputs.addresses()[0] == 27020


@pytest.mark.parametrize(
    "base, path, value, message",
    [
        (MODBUS, "transport", "profinet", r"line.toml: line.plc.transport = 'profinet': must be one of modbus, jrc_io"),
        (MODBUS, "port", 70000, r"line.plc.port = 70000: a TCP port, 0 \(any free one\) to 65535"),
        (MODBUS, "poll_period_s", 0.0, r"line.plc.poll_period_s = 0.0: must be 0.005 to 5 s"),
        (MODBUS, "inputs.start", 65536, r"line.plc.inputs.start = 65536: must be a Modbus address, 0 to 65535"),
        (MODBUS, "inputs.reset", True, r"line.plc.inputs.reset = True: must be an integer"),
        (MODBUS, "inputs.part_present", None, r"line.toml: missing key line.plc.inputs.part_present"),
        (MODBUS, "inputs.job_bits", [], r"line.plc.inputs.job_bits = \[\]: must be a list of 1 to 16 addresses"),
        (MODBUS, "inputs.job_bits", [8, 1], r"line.plc.inputs.job_bits\[1\] = 1: is also line.plc.inputs.part_present"),
        (MODBUS, "outputs.fault", 0, r"line.plc.outputs.fault = 0: is also line.plc.outputs.ready"),
        (MODBUS, "outputs.alarm", 7, r"unknown key line.plc.outputs.alarm"),
        (MODBUS, "jobs", {}, r"line.plc.jobs is empty: give each job number its job"),
        (MODBUS, "jobs.4", "demo", r"line.plc.jobs.4 = 'demo': the key must be a job number, 0 to 3 \(2 job bits\)"),
        (MODBUS, "jobs.x", "demo", r"line.plc.jobs.x = 'demo': the key must be a job number"),
        (MODBUS, "jobs.1", "", r"line.plc.jobs.1 = '': must be a non-empty string"),
        (MODBUS, "part_id_registers", 33, r"line.plc.part_id_registers = 33: must be 1 to 32"),
        (MODBUS, "part_id_register", 65530, r"line.plc.part_id_register = 65530: must be 0 to 65526"),
        (JRC_IO, "inputs.start", 38, r"line.plc.inputs.start = 38: must be a byte.bit I/O address"),
        (JRC_IO, "port", 5020, r"line.plc.port = 5020: has no meaning with transport = \"jrc_io\""),
    ],
)
def test_a_bad_key_is_one_line_naming_it_and_its_range(base, path, value, message):
    with pytest.raises(ConfigError, match=message) as error:
        cell_with(changed(base, path, value), backend="jrc" if base is JRC_IO else "sim")
    assert "\n" not in str(error.value)


def test_the_plc_on_the_jrcs_io_needs_the_jrc_and_lines_of_its_own():
    with pytest.raises(ConfigError, match=r'line.plc.transport = "jrc_io": the PLC on the JRC.s I/O needs robot.backend = "jrc"'):
        cell_with(JRC_IO)
    with pytest.raises(ConfigError, match=r"line.plc.outputs.ready = 27020: it is vacuum.suction_output"):
        cell_with(JRC_IO, backend="jrc", device="jrc_io", suction_output=27020, grip_input=20)
    with pytest.raises(ConfigError, match=r"line.plc.inputs.start = 30: it is vacuum.grip_input"):
        cell_with(JRC_IO, backend="jrc", device="jrc_io", suction_output=27010, grip_input=30)
    with pytest.raises(ConfigError, match=r"line.plc.inputs.reset = 27021: it is also a \[line.plc.outputs\] address"):
        cell_with(changed(JRC_IO, "inputs.reset", 27021), backend="jrc")
