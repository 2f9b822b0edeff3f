"""Light monitors against the real app (the controller process and viser's server, as
`vservo serve` starts them) while it assembles: the camera frames they count are JPEGs of the
camera's size, decoded from viser's own wire format; and `vservo bench ui --monitors light
--json` gives, per number of clients, the figures docs/benchmarks.md records.

The app runs assemblies because a camera standing still sends no frames: viser sends an
image element's update only when its bytes change, and the simulated camera's image of a
still cell does not.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from tests.jrc_fixtures import thesis_policy_cell_file
from tests.polling import wait_until
from vservo.app.browser import free_port
from vservo.app.context import ServeOptions
from vservo.app.light_monitor import LightMonitor, LightMonitors, MonitorError
from vservo.app.server import start_app
from vservo.core.cell.config import load_cell
from vservo.core.production.protocol import PresentPart, Start

FRAMES = 10
DEADLINE_S = 180.0  # an assembly's servo sends a frame every few hundredths of a second


@pytest.fixture(scope="module")
def running(tmp_path_factory):
    # The thesis's step policy: an assembly long enough to send a monitor many frames.
    cell = thesis_policy_cell_file(tmp_path_factory.mktemp("cell"))
    options = ServeOptions(
        port=free_port(),
        data=tmp_path_factory.mktemp("serve-data"),
        seed=3,
        token="light-monitor-token",
        cycle_period_s=0.02,
        cell=cell,
    )
    running = start_app(options, load_cell(cell))
    yield running
    running.close()


def _assemble(running) -> None:
    """One assembly of the demo job, from a new part to its recorded end. (Not "until the phase
    is done": right after the start the state shown may still be the last run's "done".)"""
    session = running.app.session
    ended = session.view().runs_ended
    for command in (PresentPart(), Start("demo")):
        reply = running.channel.call(command)
        assert reply.ok, reply.error
    wait_until(lambda: session.view().runs_ended > ended, "the assembly's end", DEADLINE_S, poll_s=0.05)


async def _watch_an_assembly(running) -> LightMonitor:
    monitor, stop = LightMonitor(running.url), asyncio.Event()
    reading = asyncio.create_task(monitor.run(stop))
    await asyncio.wait_for(monitor.connected.wait(), DEADLINE_S)
    await asyncio.to_thread(_assemble, running)
    stop.set()
    await reading
    return monitor


@pytest.mark.slow
def test_a_light_monitor_decodes_the_camera_frames_of_the_app(running):
    monitor = asyncio.run(_watch_an_assembly(running))

    camera = monitor.camera()
    assert camera is not None, "no image element in what the server sent"
    assert len(camera.times) >= FRAMES
    assert camera.times == sorted(camera.times)
    image = cv2.imdecode(np.frombuffer(camera.last_jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None, "the camera frame is not a readable JPEG"
    intrinsics = load_cell().nominal.camera.intrinsics
    assert image.shape[:2] == (intrinsics.height, intrinsics.width)
    assert monitor.messages > len(camera.times)  # the page's other messages were decoded too


@pytest.mark.slow
def test_light_monitors_in_their_own_process_each_receive_the_frames(running):
    with LightMonitors(running.url, 3) as monitors:
        _assemble(running)
        frames = monitors.frames()
    assert len(frames) == 3
    assert all(len(times) >= FRAMES for times in frames)


def test_light_monitors_of_no_server_say_so():
    with pytest.raises(MonitorError, match="light monitor of http://127.0.0.1:9 stopped"):
        LightMonitors("http://127.0.0.1:9", 1)


@pytest.mark.slow
def test_bench_ui_light_json_has_the_figures_per_client_count():
    command = [
        sys.executable,
        "-m",
        "vservo.app.cli",
        "bench",
        "ui",
        "--monitors",
        "light",
        "--light-clients",
        "2",
        "--runs",
        "1",
        "--json",
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout)

    assert "browsers" not in result  # light only: no Chromium
    assert set(result["light_clients"]) == {"2"}
    two = result["light_clients"]["2"]
    for key in (
        "fps_median",
        "fps_min",
        "loop_hz_median",
        "loop_hz_no_clients_median",
        "loop_change_pct",
        "serve_cpu_pct_median",
        "controller_cpu_pct_median",
        "clients_cpu_pct_median",
        "no_clients_serve_cpu_pct_median",
        "no_clients_controller_cpu_pct_median",
    ):
        assert two[key] is not None, key
    (watched,), (alone,) = two["runs"], two["runs_no_clients"]
    assert len(watched["fps_per_client"]) == 2 and all(fps > 0 for fps in watched["fps_per_client"])
    assert alone["fps_per_client"] == []
    assert watched["servo_cycles"] > 0 and alone["servo_cycles"] > 0
    assert watched["cpu_pct"]["controller"] > 0 and alone["cpu_pct"]["controller"] > 0
