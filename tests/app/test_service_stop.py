"""The service's stop, as deploy/vservo.service does it: SIGINT to every process of the
service at once (KillMode=control-group) in the middle of a run. The controller holds the
arm, the run ends on record as e-stopped, both processes exit; the log, in JSON, parses
line by line. A real `vservo serve` with its controller process; the run is started the way
the line starts one, by the OPC UA server's Start."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

import pytest
from asyncua import Client, ua

from tests.virtual_cell_process import ROOT
from vservo.app.browser import free_port
from vservo.core.cell.config import write_thesis_policy_cell
from vservo.core.production.opcua_server import NAMESPACE
from vservo.core.production.storage import Store

USER, PASSWORD = "mes", "line-4-secret"


async def start_a_run(endpoint: str, timeout_s: float = 120.0) -> int:
    """Connect as the MES (retrying while the service starts), Start a run, wait until it moves the arm."""
    deadline = time.monotonic() + timeout_s
    while True:
        client = Client(endpoint)
        client.set_user(USER)
        client.set_password(PASSWORD)
        try:
            await client.connect()
            break
        except (OSError, asyncio.TimeoutError):
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.5)
    try:
        namespace = await client.get_namespace_index(NAMESPACE)
        cell = client.get_node(ua.NodeId("Cell", namespace))
        run_id = await cell.call_method(ua.NodeId("Cell.Start", namespace), "demo", "P-STOP-1")
        busy = client.get_node(ua.NodeId("Cell.Busy", namespace))
        iteration = client.get_node(ua.NodeId("Cell.CurrentRun.Iteration", namespace))
        while not (await busy.read_value() and await iteration.read_value() >= 3):
            assert time.monotonic() < deadline, "the run did not get under way"
            await asyncio.sleep(0.1)
        return run_id
    finally:
        await client.disconnect()


@pytest.mark.slow
def test_sigint_to_the_service_holds_the_arm_ends_the_run_on_record_and_logs_json(tmp_path):
    cell_file = write_thesis_policy_cell(tmp_path)  # the thesis's steps: a run long enough to stop in its middle
    opcua_port = free_port()
    with cell_file.open("a") as text:
        text.write(f'\n[line.opcua]\nenabled = true\nport = {opcua_port}\n\n[line.opcua.users.{USER}]\npassword = "{PASSWORD}"\n')
    data = tmp_path / "data"
    log = tempfile.TemporaryFile("w+")
    service = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "vservo.app.cli",
            "--cell",
            str(cell_file),
            "serve",
            "--port",
            str(free_port()),
            "--data",
            str(data),
            "--seed",
            "3",
            "--log-format",
            "json",
            "--log-level",
            "info",
        ],
        stdout=subprocess.DEVNULL,
        stderr=log,
        cwd=ROOT,
        start_new_session=True,  # its own process group, as the service's control group
        env={**os.environ, "VSERVO_OPERATOR_TOKEN": "a-token-for-the-test-only"},
    )
    try:
        run_id = asyncio.run(start_a_run(f"opc.tcp://127.0.0.1:{opcua_port}/vservo/"))
        os.killpg(service.pid, signal.SIGINT)  # systemctl stop: KillSignal=SIGINT to the whole group
        code = service.wait(timeout=45)  # within the unit's TimeoutStopSec
        log.seek(0)
        assert code == 0, log.read()[-4000:]
    finally:
        if service.poll() is None:
            os.killpg(service.pid, signal.SIGKILL)
            service.wait()
    with pytest.raises(ProcessLookupError):  # the controller process is gone too
        os.killpg(service.pid, 0)

    store = Store(data)
    try:
        (run,) = [record for record in store.list_runs() if record.id == run_id]
    finally:
        store.close()
    assert run.outcome is not None and run.outcome.value == "e-stopped", (run.outcome, run.reason)
    assert run.part_id == "P-STOP-1" and "the controller process is stopping" in (run.reason or ""), run.reason

    log.seek(0)
    lines = log.read().splitlines()
    records = [json.loads(line) for line in lines]
    assert records and {record["process"] for record in records} == {"serve", "controller"}
    held = [r for r in records if r["process"] == "controller" and r["message"].endswith("stopping: robot held")]
    assert held, "the controller did not log the robot held"
