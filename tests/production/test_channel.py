"""The controller's channel: only a holder of the key gets in; commands, state and frames flow."""

from __future__ import annotations

import inspect
import json
import logging
import socket
import threading

import cv2
import numpy as np
import pytest

from tests.jrc_fixtures import with_the_thesis_policy
from vservo.core.cell.config import load_cell
from vservo.core.production.assembly import Outcome
from vservo.core.production.cell_controller import CellController
from vservo.core.production.channel import APP_GONE, HANDSHAKE_DEADLINE_S, ControllerServer
from vservo.core.production.protocol import (
    COMMANDS,
    KEY_ENVIRONMENT,
    BeginTeach,
    ChannelError,
    CommandRefused,
    ControllerClient,
    EnterManual,
    Estop,
    GetJob,
    GoHome,
    Jog,
    LeaveManual,
    ListJobs,
    ListRuns,
    MoveJoint,
    MoveTo,
    Phase,
    PresentPart,
    Query,
    Reset,
    SaveJob,
    SetSettings,
    SetStartPose,
    Start,
    Suction,
    new_key,
)
from vservo.core.production.protocol.catalogue import Refusal
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.production.storage import Store
from vservo.core.robot.backend import RobotError
from vservo.core.robot.safety import SafetyLayer
from vservo.core.sim.backend import SimulatedBackend


@pytest.fixture
def served(tmp_path):
    store = Store(tmp_path)
    controller = CellController(simulated_rig(load_cell(), seed=2), store, seed=2)
    key = new_key()
    server = ControllerServer(controller, key)
    yield controller, server, key
    server.close()
    controller.close()
    store.close()


def test_a_client_without_the_key_is_refused(served):
    controller, server, _ = served
    with pytest.raises(ChannelError, match="cannot connect"):
        ControllerClient(server.address, b"wrong key")
    assert server.subscribers == []


def test_commands_state_and_frames_flow(served):
    controller, server, key = served
    frames: list[tuple[dict, bytes]] = []
    got_frame = threading.Event()

    def on_frame(meta, jpeg):
        frames.append((meta, jpeg))
        got_frame.set()

    client = ControllerClient(server.address, key, on_frame=on_frame)
    try:
        assert client.state.phase is Phase.IDLE
        assert got_frame.wait(10.0)  # the live view starts with a subscriber
        meta, jpeg = frames[-1]
        image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
        assert image.shape == (480, 640)
        assert meta.corners_px.shape == (4, 2)

        z = controller.rig.robot.read_pose()[2, 3]
        refused = client.call(Jog(translation_m=(0, 0, 0.01)))  # jogs only while teaching or in manual mode
        assert not refused.ok and refused.kind is Refusal.NOT_MANUAL
        assert client.call(EnterManual()).ok
        assert client.call(Jog(translation_m=(0, 0, 0.01))).ok
        assert controller.rig.robot.read_pose()[2, 3] == pytest.approx(z + 0.01, abs=1e-6)
        _raw_command(client, 900, "jog", {"translation_m": [0, float("nan"), 0]})
        refused = _reply(client, 900)
        assert not refused["ok"] and "translation_m must be 3 numbers, each from -0.02 to 0.02 m" in refused["error"]
        _raw_command(client, 901, "fly", {})
        unknown = _reply(client, 901)
        assert not unknown["ok"] and "unknown command 'fly'" in unknown["error"]
        assert [job.name for job in client.call(ListJobs()).result] == ["demo"]

        assert client.call(Estop()).ok
        assert controller.rig.robot.status().held
        assert "e-stop" in client.call(Jog(translation_m=(0, 0, 0.01))).error
        assert client.call(Reset()).ok
    finally:
        client.close()


def test_the_app_going_away_leaves_the_controller_serving(served):
    controller, server, key = served
    client = ControllerClient(server.address, key)
    client.close()
    again = ControllerClient(server.address, key)
    try:
        assert again.call(ListRuns()).ok
    finally:
        again.close()


def test_the_controller_runs_as_its_own_process(tmp_path):
    import json
    import os
    import subprocess
    import sys

    key = new_key()
    env = {**os.environ, KEY_ENVIRONMENT: key.hex()}
    process = subprocess.Popen(
        [sys.executable, "-m", "vservo.app.cli", "controller", "--data", str(tmp_path)],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        address = json.loads(process.stdout.readline())["controller"]
        client = ControllerClient((address["host"], address["port"]), key)
        assert client.call(ListJobs()).result[0].name == "demo"
        client.close()
    finally:
        process.terminate()
        assert process.wait(30) == 0  # a clean stop on SIGTERM
    refused = subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "controller"],
        capture_output=True,
        text=True,
        env={k: v for k, v in os.environ.items() if k != KEY_ENVIRONMENT},
    )
    assert refused.returncode == 2 and KEY_ENVIRONMENT in refused.stderr


# A stand-in for `vservo serve`: it starts the controller as serve does, prints its pid,
# and waits to be killed.
_STARTER = """
import sys, time
from pathlib import Path
from vservo.app.controller_process import ControllerProcess
controller = ControllerProcess.start(backend="sim", data=Path(sys.argv[1]), seed=2, cycle_period_s=0.05)
print(controller.process.pid, flush=True)
time.sleep(600)
"""


def _running(pid: int) -> bool:
    """Whether the process exists and has not exited (an unreaped zombie has)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_a_controller_whose_app_is_killed_outright_stops_by_itself(tmp_path):
    # SIGKILL runs no handler in the app: the orphaned controller notices its parent is
    # gone, holds the robot and exits, freeing the cell (a real JRC's serial port).
    import os
    import signal
    import subprocess
    import sys
    import time

    log = tmp_path / "controller.stderr"
    with open(log, "w") as stderr:
        starter = subprocess.Popen(
            [sys.executable, "-c", _STARTER, str(tmp_path)], stdout=subprocess.PIPE, stderr=stderr, text=True
        )
    controller_pid = int(starter.stdout.readline())
    assert _running(controller_pid)
    starter.send_signal(signal.SIGKILL)
    starter.wait()
    starter.stdout.close()
    deadline = time.monotonic() + 60.0  # a liveness bound, not a timing: it polls every 0.5 s
    while _running(controller_pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    orphaned = _running(controller_pid)
    if orphaned:
        os.kill(controller_pid, signal.SIGKILL)  # leave no stray process behind a failure
    assert not orphaned, "the orphaned controller is still running"
    assert "is gone: holding the robot and stopping" in log.read_text()


class SlowMotionBackend(SimulatedBackend):
    """The simulated robot with moves that take time, as a real arm's do: wait_motion
    returns when the test lets the move finish, or at once when the robot is held."""

    def __init__(self, cell) -> None:
        super().__init__(cell)
        self.moving = threading.Event()
        self.finish = threading.Event()

    def wait_motion(self, timeout_s: float | None = None) -> bool:
        self.moving.set()
        while not self.finish.wait(0.01):
            if self.status().held:
                return False
        return super().wait_motion(timeout_s)


@pytest.fixture
def slow_served(tmp_path):
    store = Store(tmp_path)
    rig = simulated_rig(load_cell(), seed=2)
    slow = SlowMotionBackend(rig.cell)
    rig.robot = SafetyLayer.from_config(slow, rig.config)
    controller = CellController(rig, store, seed=2)
    key = new_key()
    server = ControllerServer(controller, key)
    yield controller, server, key
    slow.finish.set()
    server.close()
    controller.close()
    store.close()


def _jog_in_background(client: ControllerClient) -> tuple[threading.Thread, list]:
    replies: list = []
    assert client.call(EnterManual()).ok

    def jog() -> None:
        try:
            replies.append(client.call(Jog(translation_m=(0, 0, 0.01))))
        except ChannelError as exc:  # the app closed its end meanwhile
            replies.append(exc)

    thread = threading.Thread(target=jog)
    thread.start()
    return thread, replies


def test_estop_is_carried_out_while_a_long_move_of_the_same_app_runs(slow_served):
    controller, server, key = slow_served
    client = ControllerClient(server.address, key)
    try:
        jog, replies = _jog_in_background(client)
        assert controller.rig.robot.robot.moving.wait(10.0)
        assert client.call(Estop(), timeout_s=10.0).ok  # the move was never let finish: estop did not queue behind it
        assert controller.rig.robot.status().held
        jog.join(10.0)
        assert replies and not replies[0].ok and "the move was stopped" in replies[0].error
    finally:
        client.close()


def test_the_last_app_leaving_during_a_jog_holds_the_robot(slow_served):
    controller, server, key = slow_served
    client = ControllerClient(server.address, key)
    jog, replies = _jog_in_background(client)
    assert controller.rig.robot.robot.moving.wait(10.0)
    client.close()
    jog.join(10.0)
    assert isinstance(replies[0], ChannelError)
    pause = threading.Event()
    for _ in range(200):  # the controller hears of the disconnect on its own thread
        if controller.state.phase == "e-stopped":
            break
        pause.wait(0.05)
    assert controller.state.phase == "e-stopped"
    assert controller.rig.robot.status().held
    assert APP_GONE in controller.state.detail


def test_the_last_app_leaving_during_a_run_holds_the_robot_and_the_run_says_why(tmp_path):
    store = Store(tmp_path)
    # The thesis's step policy: a run long enough to leave in the middle of.
    controller = CellController(simulated_rig(with_the_thesis_policy(load_cell()), seed=2), store, seed=2, cycle_period_s=0.05)
    key = new_key()
    server = ControllerServer(controller, key)
    try:
        watcher = ControllerClient(server.address, key)
        operator = ControllerClient(server.address, key)
        run_id = operator.call(Start("demo")).result
        operator.close()  # another app is still connected: the run goes on
        assert controller.running
        watcher.close()  # the last one: the robot is held
        controller.wait(30.0)
        assert controller.state.phase == "e-stopped"
        assert controller.rig.robot.status().held
        record = store.run(run_id)
        assert record.outcome is Outcome.ESTOPPED and record.reason == APP_GONE
        assert APP_GONE in controller.state.detail
    finally:
        server.close()
        controller.close()
        store.close()


def test_the_last_app_leaving_during_a_run_the_line_started_leaves_it_going(tmp_path):
    """A monitor page that watched a run the PLC or OPC UA started, then closed, does not
    stop the line: only what an app started is held when the last app goes."""
    store = Store(tmp_path)
    controller = CellController(simulated_rig(with_the_thesis_policy(load_cell()), seed=2), store, seed=2, cycle_period_s=0.05)
    key = new_key()
    server = ControllerServer(controller, key)
    try:
        watcher = ControllerClient(server.address, key)
        run_id = controller.start("demo", part_id="LINE-1", by_line=True)
        assert controller.running
        watcher.close()
        controller.wait(120.0)
        record = store.run(run_id)
        assert record.outcome is Outcome.PLACED, record.reason
        assert not controller.rig.robot.status().held
    finally:
        server.close()
        controller.close()
        store.close()


def test_the_last_app_leaving_while_idle_changes_nothing(served):
    controller, server, key = served
    ControllerClient(server.address, key).close()
    assert controller.state.phase == "idle"
    assert not controller.rig.robot.status().held


def _raw_command(client: ControllerClient, request: int, name, args) -> None:
    """A command as a buggy or hostile app could send it, past the checks of the command's dataclass."""
    with client._send_lock:
        client.connection.send_bytes(json.dumps({"type": "command", "id": request, "name": name, "args": args}).encode())


def _reply(client: ControllerClient, request: int) -> dict:
    """The reply message, as it came."""
    return client._wait_reply(request, f"request {request}", 10.0)


def test_commands_with_bad_arguments_get_an_error_and_the_connection_keeps_working(served):
    _, server, key = served
    client = ControllerClient(server.address, key)
    try:
        bad = [
            ("list_runs", [1]),
            ("list_runs", {"limit": 10**30}),
            ("list_runs", {"limit": "many"}),
            ("list_runs", {"limit": 0}),
            ("jog", {"translation_m": "up"}),
            ("set_settings", {"gain": [1]}),
            ("get_job", None),
            (["list_jobs"], {}),
            ("fly", {}),
        ]
        for request, (name, args) in enumerate(bad, start=1000):
            _raw_command(client, request, name, args)
            reply = _reply(client, request)
            assert not reply["ok"] and reply["error"], (name, args)
            assert "\n" not in reply["error"] and "internal error" not in reply["error"], reply["error"]
        _raw_command(client, 2000, "list_runs", {"limit": 10**30})
        assert "limit must be a whole number" in _reply(client, 2000)["error"]
        assert [job.name for job in client.call(ListJobs()).result] == ["demo"]
        assert client.call(ListRuns(limit=5)).ok
    finally:
        client.close()


def _connect_and_list(address, key, results: list, index: int) -> None:
    client = ControllerClient(address, key)
    try:
        results[index] = client.call(ListJobs(), timeout_s=60.0).ok
    finally:
        client.close()


def test_idle_connections_without_the_key_do_not_block_an_app(served):
    _, server, key = served
    idle = [socket.create_connection(server.address) for _ in range(5)]
    try:
        results = [False]
        app = threading.Thread(target=_connect_and_list, args=(server.address, key, results, 0), daemon=True)
        app.start()
        app.join(3.0)  # a handshake takes milliseconds; behind the idle sockets it used to wait for ever
        assert results == [True]
        # Each silent connection is dropped at the handshake's deadline.
        for connection in idle:
            connection.settimeout(HANDSHAKE_DEADLINE_S + 10.0)
            while connection.recv(4096):
                pass  # the server's challenge, then the end of the connection
    finally:
        for connection in idle:
            connection.close()


def test_300_apps_connecting_at_once_all_get_through(served):
    _, server, key = served
    results = [False] * 300
    apps = [
        threading.Thread(target=_connect_and_list, args=(server.address, key, results, i), daemon=True)
        for i in range(len(results))
    ]
    for app in apps:
        app.start()
    for app in apps:
        app.join(120.0)
    assert sum(results) == len(results)


# -- the protocol's commands, and errors, on the controller's side --------------------------------


@pytest.mark.parametrize(
    ("name", "args", "error"),
    [
        (
            "set_settings",
            {"threshold_px": 3.0, "gain": 1.0, "approach_m": 1e9},
            "approach_m must be from 0.005 to 0.2 m, got 1e+09",
        ),
        (
            "set_settings",
            {"threshold_px": 1e12, "gain": 1.0, "approach_m": 0.04},
            "threshold_px must be from 0.1 to 50 px, got 1e+12",
        ),
        (
            "move_to",
            {"bMe_target": [[1.0, 0.0, 0.0, 1e300], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.3], [0.0, 0.0, 0.0, 1.0]]},
            "bMe_target: its translation must be from -5 to 5 m each, got [1e+300, 0, 0.3]",
        ),
        (
            "move_to",
            {"bMe_target": [[1e300] * 4] * 4},
            "bMe_target: its translation must be from -5 to 5 m each, got [1e+300, 1e+300, 1e+300]",
        ),
    ],
)
def test_a_number_out_of_the_pages_range_sent_straight_over_the_channel_is_refused_naming_it(served, name, args, error):
    """Past the app's own checks (a raw message): the controller's dataclass refuses it, in one line."""
    controller, server, key = served
    client = ControllerClient(server.address, key)
    try:
        assert client.call(EnterManual()).ok and client.call(Jog()).ok  # a first readout: the flange pose below is the robot's
        assert client.call(LeaveManual()).ok
        assert controller.state.phase == "idle"
        bMe = controller.rig.robot.read_pose()
        if name == "set_settings":
            assert client.call(BeginTeach()).ok  # where settings are taken
        _raw_command(client, 1, name, args)
        reply = _reply(client, 1)
        assert not reply["ok"] and reply["error"] == error
        np.testing.assert_array_equal(controller.rig.robot.read_pose(), bMe)  # nothing moved
        assert client.call(GoHome()).ok  # and the connection goes on
    finally:
        client.close()


def test_the_same_check_refuses_it_in_the_app_before_it_is_sent():
    with pytest.raises(CommandRefused) as refused:
        SetSettings(threshold_px=3.0, gain=1.0, approach_m=1e9)
    assert str(refused.value) == "approach_m must be from 0.005 to 0.2 m, got 1e+09"
    with pytest.raises(CommandRefused, match=r"^threshold_px must be from 0\.1 to 50 px, got 1e\+12$"):
        SetSettings(threshold_px=1e12, gain=1.0, approach_m=0.04)
    with pytest.raises(CommandRefused, match=r"^bMe_target: its translation must be from -5 to 5 m each"):
        MoveTo(np.full((4, 4), 1e300))
    rotated = np.eye(4)
    rotated[:3, :3] *= 2.0  # no rotation: a scaling
    with pytest.raises(CommandRefused, match=r"^bMe_target must be a rigid pose"):
        MoveTo(rotated)


def test_a_bug_in_a_command_reaches_the_app_as_an_internal_error_and_its_traceback_is_in_the_log(served, monkeypatch, caplog):
    controller, server, key = served

    def deliberate_bug() -> None:
        raise KeyError("a deliberate bug")

    monkeypatch.setattr(controller, "set_start_pose", deliberate_bug)
    client = ControllerClient(server.address, key)
    try:
        with caplog.at_level(logging.ERROR, logger="vservo.channel"):
            reply = client.call(SetStartPose())
        assert not reply.ok
        assert reply.error == "set_start_pose: internal error (its traceback is in the controller's log)"
        (record,) = [r for r in caplog.records if r.name == "vservo.channel" and r.exc_info]
        assert record.exc_info[0] is KeyError
        assert "Traceback (most recent call last)" in caplog.text and "KeyError: 'a deliberate bug'" in caplog.text
        assert "deliberate_bug" in caplog.text  # the frame that raised it
        assert client.call(ListJobs()).ok  # the connection goes on
    finally:
        client.close()


def test_an_error_vservo_raises_on_purpose_is_a_refusal_with_its_message_and_no_traceback(served, monkeypatch, caplog):
    controller, server, key = served

    def lost_link() -> None:
        raise RobotError("the JRC does not answer")

    monkeypatch.setattr(controller, "set_start_pose", lost_link)
    client = ControllerClient(server.address, key)
    try:
        with caplog.at_level(logging.DEBUG, logger="vservo.channel"):
            reply = client.call(SetStartPose())
        assert not reply.ok and reply.error == "the JRC does not answer"
        assert not [r for r in caplog.records if r.exc_info]
    finally:
        client.close()


def test_every_command_is_a_controller_method_that_takes_its_fields():
    """One spelling: the command's name on the channel is the controller's method, its fields the method's arguments."""
    samples = {
        MoveTo: MoveTo(np.eye(4)),
        MoveJoint: MoveJoint(np.eye(4)),
        Suction: Suction(True),
        SetSettings: SetSettings(3.0, 1.0, 0.04),
        SaveJob: SaveJob("bolt"),
        Start: Start("demo"),
        GetJob: GetJob("demo"),
    }
    for kind in COMMANDS.values():
        command = samples.get(kind) or kind()
        if isinstance(command, Query):
            continue  # answered from the store
        method = getattr(CellController, command.command_name)
        inspect.signature(method).bind(None, **command.arguments())


def test_the_protocol_imports_nothing_of_the_controller_and_nothing_heavy():
    import subprocess
    import sys

    loaded = subprocess.run(
        [sys.executable, "-c", "import sys, vservo.core.production.protocol; print(' '.join(sys.modules))"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    assert "vservo.core.production.protocol.client" in loaded  # the test reads what it should
    heavy = {"vservo.core.production.cell_controller", "vservo.core.production.channel", "cv2", "pinocchio", "torch", "viser"}
    assert not heavy & set(loaded)


def test_a_run_started_over_the_channel_records_the_parts_id_and_a_bad_one_is_refused(served):
    controller, server, key = served
    client = ControllerClient(server.address, key)
    try:
        _raw_command(client, 1, "start", {"job_name": "demo", "part_id": " padded"})
        refused = _reply(client, 1)
        assert not refused["ok"] and refused["error"].startswith("part_id must be 1 to 64 printable characters")
        assert client.call(PresentPart()).ok
        run_id = client.call(Start("demo", part_id="SN-0042")).result
        controller.wait(120.0)
        (run,) = [run for run in client.call(ListRuns(limit=5)).result if run.id == run_id]
        assert run.part_id == "SN-0042" and run.outcome is Outcome.PLACED
    finally:
        client.close()
