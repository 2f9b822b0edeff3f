"""The cell on the production line: the OPC UA server and the metrics endpoint of a real
controller process on the virtual cell, its log in JSON, and `vservo runs` afterwards.

Real processes: `vservo virtual-cell` (the JRC emulator on a pseudo-terminal, the camera
stream, the part fixture, which plays the line's conveyor here), `vservo controller` with
the cell file's [line.opcua] and [line.metrics]; asyncua's own client plays the MES, an
HTTP GET plays Prometheus.
"""

from __future__ import annotations

import asyncio
import csv
import io
import json
import math
import os
import subprocess
import sys
import tempfile
import tomllib
import urllib.request
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.ua.uaerrors import BadInvalidArgument, BadInvalidState, BadUserAccessDenied
from prometheus_client.parser import text_string_to_metric_families

from tests.virtual_cell_process import ROOT, VirtualCellProcess
from vservo.core.cell.cell_file import dumps_cell
from vservo.core.production.opcua_server import NAMESPACE
from vservo.core.production.protocol import KEY_ENVIRONMENT, new_key

USER, PASSWORD = "mes", "line-4-secret"
RUNS = 3
RUN_TIMEOUT_S = 300.0


class ControllerProcess:
    """`vservo controller` on a cell file, its log (JSON lines) in a file, its addresses from its first line."""

    def __init__(self, cell_file: Path, data: Path) -> None:
        self.log_file = tempfile.TemporaryFile("w+")
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "vservo.app.cli",
                "--cell",
                str(cell_file),
                "controller",
                "--data",
                str(data),
                "--seed",
                "3",
                "--cycle-period",
                "0",
                "--log-level",
                "info",
                "--log-format",
                "json",
            ],
            stdout=subprocess.PIPE,
            stderr=self.log_file,
            text=True,
            cwd=ROOT,
            env={**os.environ, KEY_ENVIRONMENT: new_key().hex()},
        )
        line = self.process.stdout.readline()
        if not line:
            raise AssertionError(f"the controller did not start: {self.log()[-3000:]}")
        self.addresses = json.loads(line)["controller"]

    def log(self) -> str:
        self.log_file.seek(0)
        return self.log_file.read()

    def stop(self) -> int:
        self.process.terminate()
        try:
            return self.process.wait(timeout=60)
        finally:
            self.process.stdout.close()


@pytest.fixture
def line_cell(tmp_path):
    """The virtual cell, and a controller process on its cell file with an OPC UA server
    (one user, anonymous read-only) and a metrics endpoint, both on free loopback ports."""
    cell = VirtualCellProcess("--seed", "3")
    controller = None
    try:
        tables = tomllib.loads(Path(cell.addresses["cell_file"]).read_text())
        tables["line"] = {
            "opcua": {"enabled": True, "port": 0, "users": {USER: {"password": PASSWORD}}},
            "metrics": {"enabled": True, "port": 0},
        }
        cell_file = tmp_path / "cell.toml"
        cell_file.write_text(dumps_cell(tables))
        controller = ControllerProcess(cell_file, tmp_path / "data")
        yield cell, controller, tmp_path / "data"
    finally:
        if controller is not None and controller.process.poll() is None:
            controller.stop()
        cell.stop()


def present_part(fixture_url: str, seed: int) -> None:
    """The line's conveyor: a new part on the table (the virtual cell's fixture)."""
    request = urllib.request.Request(
        fixture_url + "/part", data=json.dumps({"seed": seed}).encode(), headers={"Content-Type": "application/json"}
    )
    with urllib.request.urlopen(request, timeout=10) as response:
        assert response.status == 200


def scrape(url: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """Every sample of the metrics endpoint by name and labels."""
    with urllib.request.urlopen(url, timeout=10) as response:
        text = response.read().decode()
    return {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
    }


async def read(client: Client, namespace: int, name: str):
    return await client.get_node(ua.NodeId(name, namespace)).read_value()


async def wait_for_value(client: Client, namespace: int, name: str, value: object, timeout_s: float = 10.0) -> None:
    """Poll until the variable holds ``value`` (the server follows the controller's state within its period)."""
    deadline = asyncio.get_running_loop().time() + timeout_s
    while (seen := await read(client, namespace, name)) != value:
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError(f"{name} is {seen!r}, not {value!r}, after {timeout_s} s")
        await asyncio.sleep(0.05)


async def wait_for_run_end(client: Client, namespace: int, run_id: int, metrics_url: str, during: list) -> None:
    """Poll until Cell.LastRun says run ``run_id`` ended; the metrics scraped while it ran go into ``during``."""
    deadline = asyncio.get_running_loop().time() + RUN_TIMEOUT_S
    while await read(client, namespace, "Cell.LastRun.RunId") != run_id:
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError(f"run {run_id} did not end within {RUN_TIMEOUT_S} s")
        if await read(client, namespace, "Cell.CurrentRun.Active"):
            during.append(scrape(metrics_url))
        await asyncio.sleep(0.2)


async def anonymous_session(endpoint: str) -> None:
    """An anonymous client browses and reads, and is refused a write and every method."""
    async with Client(endpoint) as client:
        namespace = await client.get_namespace_index(NAMESPACE)
        names = {(await child.read_browse_name()).Name for child in await client.nodes.objects.get_children()}
        assert "Cell" in names
        assert await read(client, namespace, "Cell.Phase") in ("idle", "done")
        phase = client.get_node(ua.NodeId("Cell.Phase", namespace))
        with pytest.raises(BadUserAccessDenied):
            await phase.write_value(ua.Variant("fault", ua.VariantType.String))
        cell = client.get_node(ua.NodeId("Cell", namespace))
        for method, args in (("Start", ("demo", "anon-1")), ("Hold", ()), ("Reset", ())):
            with pytest.raises(BadUserAccessDenied):
                await cell.call_method(ua.NodeId(f"Cell.{method}", namespace), *args)
        assert await read(client, namespace, "Cell.Phase") in ("idle", "done")


async def mes_session(endpoint: str, fixture_url: str, metrics_url: str) -> tuple[list[dict], list[dict]]:
    """The MES: browse the cell, start RUNS runs by method with part IDs, read each outcome."""
    client = Client(endpoint)
    client.set_user(USER)
    client.set_password(PASSWORD)
    results, during = [], []
    async with client:
        namespace = await client.get_namespace_index(NAMESPACE)
        cell = client.get_node(ua.NodeId("Cell", namespace))
        children = {(await child.read_browse_name()).Name for child in await cell.get_children()}
        assert {"Phase", "EStopped", "Fault", "Jobs", "CurrentRun", "LastRun", "Start", "Hold", "Reset"} <= children
        assert "demo" in await read(client, namespace, "Cell.Jobs")
        with pytest.raises(BadInvalidState):  # the controller's guard: no such job
            await cell.call_method(ua.NodeId("Cell.Start", namespace), "no-such-job", "P-x")
        assert "no-such-job" in await read(client, namespace, "Cell.LastRefusal")
        with pytest.raises(BadInvalidArgument):  # the command's own check: a tab in a part ID
            await cell.call_method(ua.NodeId("Cell.Start", namespace), "demo", "tab\there")
        for index in range(RUNS):
            present_part(fixture_url, 100 + index)
            part_id = f"LINE4-{index + 1:04d}"
            run_id = await cell.call_method(ua.NodeId("Cell.Start", namespace), "demo", part_id)
            assert await read(client, namespace, "Cell.LastRefusal") == ""
            await wait_for_run_end(client, namespace, run_id, metrics_url, during)
            last = {
                name: await read(client, namespace, f"Cell.LastRun.{name}")
                for name in ("RunId", "Job", "PartId", "Outcome", "PlacementErrorMm", "CycleTimeS", "CellTimeS", "Iterations")
            }
            results.append(last)
        await cell.call_method(ua.NodeId("Cell.Hold", namespace))
        with pytest.raises(BadInvalidState):  # held: the page's guard refuses a start until Reset
            await cell.call_method(ua.NodeId("Cell.Start", namespace), "demo", "P-held")
        assert "e-stop" in await read(client, namespace, "Cell.LastRefusal")
        await wait_for_value(client, namespace, "Cell.EStopped", True)
        await cell.call_method(ua.NodeId("Cell.Reset", namespace))
        await wait_for_value(client, namespace, "Cell.Phase", "idle")
    return results, during


@pytest.mark.slow
def test_the_mes_starts_runs_over_opc_ua_and_reads_their_results_and_the_metrics_move(line_cell):
    cell, controller, data = line_cell
    endpoint, metrics_url = controller.addresses["opcua"], controller.addresses["metrics"]
    assert endpoint.startswith("opc.tcp://127.0.0.1:") and metrics_url.startswith("http://127.0.0.1:")
    before = scrape(metrics_url)
    asyncio.run(anonymous_session(endpoint))
    results, during = asyncio.run(mes_session(endpoint, cell.addresses["fixture"], metrics_url))
    after = scrape(metrics_url)

    assert [r["PartId"] for r in results] == [f"LINE4-{i:04d}" for i in (1, 2, 3)]
    for result in results:
        assert result["Job"] == "demo" and result["Outcome"] == "placed", result
        assert 0.0 <= result["PlacementErrorMm"] < 1.0, result  # the demo job's tolerance
        assert result["CycleTimeS"] > 0 and result["CellTimeS"] > 0 and result["Iterations"] > 0, result
    assert len({r["RunId"] for r in results}) == RUNS

    placed = ("vservo_runs_total", (("outcome", "placed"),))
    assert before[placed] == 0 and after[placed] == RUNS
    assert after[("vservo_cycle_time_seconds_count", ())] == RUNS
    assert after[("vservo_placement_error_mm_count", ())] == RUNS
    assert after[("vservo_cell_time_seconds_count", ())] == RUNS
    assert during, "no scrape while a run was under way"
    frames = ("vservo_camera_frames_total", ())
    cycles = ("vservo_servo_cycles_total", ())
    for counter in (frames, cycles):  # counters never go back, and move while the runs go on
        seen = [before[counter], *(sample[counter] for sample in during), after[counter]]
        assert seen == sorted(seen) and seen[0] < max(seen[1:-1]), (counter, seen)
    assert any(sample[("vservo_phase", (("phase", "servoing"),))] == 1 for sample in during)
    assert after[("vservo_phase", (("phase", "idle"),))] == 1
    # the JRC link's recoveries (the pseudo-terminal loses nothing: listed, at 0)
    assert after[("vservo_link_retries_total", (("kind", "enq_retries"),))] == 0

    assert controller.stop() == 0
    exported = subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "runs", "--data", str(data), "--csv"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert exported.returncode == 0, exported.stderr
    rows = list(csv.DictReader(io.StringIO(exported.stdout)))
    assert [(int(row["id"]), row["part_id"], row["outcome"]) for row in rows] == [
        (r["RunId"], r["PartId"], "placed") for r in results
    ]
    for row, result in zip(rows, results, strict=True):
        assert math.isclose(float(row["placement_error_mm"]), result["PlacementErrorMm"], abs_tol=1e-4)

    lines = controller.log().splitlines()
    records = [json.loads(line) for line in lines]  # every line of the log is one JSON object
    assert len(records) == len(lines) > 0
    messages = " ".join(record["message"] for record in records)
    assert "OPC UA: Start('demo', part 'LINE4-0001')" in messages
    assert {record["process"] for record in records} == {"controller"}
