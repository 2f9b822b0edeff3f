"""--log-format json on the long-running commands: every line of standard error is one JSON
object, the command's own announcements included; --log-level sets what is written."""

import json
import subprocess
import sys

import pytest

from tests.polling import wait_until
from tests.virtual_cell_process import ROOT, VirtualCellProcess


def json_lines(text: str) -> list[dict]:
    lines = text.splitlines()
    records = [json.loads(line) for line in lines]  # fails on any line that is no JSON
    assert all(isinstance(record, dict) for record in records)
    return records


@pytest.mark.slow
def test_vservo_run_logs_json_lines_at_the_level_asked(tmp_path):
    common = [sys.executable, "-m", "vservo.app.cli", "run", "--job", "demo", "--data", str(tmp_path), "--seed", "2", "--json"]
    run = subprocess.run(
        [*common, "--log-format", "json", "--log-level", "info"], capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout)["outcome"] == "placed"  # standard output stays the result
    records = json_lines(run.stderr)
    assert records and {record["level"] for record in records} >= {"info"}
    assert {record["process"] for record in records} == {"run"}
    quiet = subprocess.run(
        [*common, "--log-format", "json", "--log-level", "error"], capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert quiet.returncode == 0 and all(record["level"] in ("error", "critical") for record in json_lines(quiet.stderr))


def test_the_virtual_cell_announces_itself_in_json():
    cell = VirtualCellProcess("--seed", "3", "--log-format", "json")
    try:
        wait_until(lambda: "virtual cell from" in cell.log(), "the virtual cell's announcement")
        records = json_lines(cell.log())
    finally:
        assert cell.stop() == 0
    assert any(record["message"].startswith("virtual cell from") for record in records), records
