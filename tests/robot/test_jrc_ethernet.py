"""The host commands over TCP: the Ethernet server's framing against a controller scripted
line by line on a real loopback socket, its failures (a refused connection, a dropped
one, a silent peer, a refused command), the emulator's server with its faults, and the
cell file's [jrc] for Ethernet. The command set itself, and the soak, run over both
links in tests/robot/test_jrc_link.py."""

import socket
import threading
from dataclasses import replace

import pytest

from tests.cell.test_config import default_data
from tests.jrc_fixtures import ETHERNET_TIMER_A_S, TEST_LINE, TIME_SCALE, jrc_link, short_timer_cell
from vservo.core.cell.config import ConfigError, HostTransport, parse_cell
from vservo.core.geometry.spatial import pose_error, transform
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.robot.backend import RobotError
from vservo.core.robot.ethernet_link import EthernetLink, keep_alive_of
from vservo.core.robot.host_link import CommandNotOffered, LinkError
from vservo.core.robot.jrc import JrcBackend, JrcNotReady
from vservo.core.sim.jrc_emulator import FaultPlan, JrcEmulator
from vservo.core.sim.plant import SimulatedCell

pytestmark = pytest.mark.usefixtures("no_leaked_threads")
ETHERNET = HostTransport.ETHERNET


@pytest.fixture(scope="module")
def config():
    return short_timer_cell()


# -- the framing against a scripted controller -----------------------------------------


class ScriptedServer:
    """The controller's end of a loopback TCP port, driven line by line by the test (no
    emulator code): ``accept`` a connection, ``expect`` what the host sends, ``send``."""

    def __init__(self) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.address = self.listener.getsockname()[:2]
        self.connection: socket.socket | None = None

    def accept(self, timeout_s: float = 10.0) -> None:
        self.listener.settimeout(timeout_s)
        self.connection, _ = self.listener.accept()
        self.connection.settimeout(timeout_s)

    def expect(self, expected: bytes) -> None:
        data = b""
        while len(data) < len(expected):
            chunk = self.connection.recv(len(expected) - len(data))
            assert chunk, f"the host closed the connection after {data!r}, expected {expected!r}"
            data += chunk
        assert data == expected

    def send(self, data: bytes) -> None:
        self.connection.sendall(data)

    def start_session(self) -> None:
        self.accept()
        self.expect(b"CONNECT Robot_access Keep-Alive:-1\r\n")
        self.send(b"OK: DX Information Server( Ver. test) Keep-Alive:-1.\r\n")

    def closed_by_host(self) -> bool:
        return self.connection.recv(1) == b""

    def close(self) -> None:
        if self.connection is not None:
            self.connection.close()
        self.listener.close()


@pytest.fixture
def server():
    scripted = ScriptedServer()
    yield scripted
    scripted.close()


def in_thread(call):
    """Run ``call()`` in a thread: (the thread, a dict that gets its result or its exception)."""
    result = {}

    def run():
        try:
            result["value"] = call()
        except RobotError as exc:
            result["value"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    return thread, result


def scripted_host(server: ScriptedServer, config) -> JrcBackend:
    """A host of ``server``, with a timer A the test's own thread answers within on a loaded machine."""
    return JrcBackend(replace(config.jrc.on_ethernet(*server.address), timer_a_s=5.0, timer_b_s=5.0))


def test_commands_go_as_the_ethernet_server_function_draws_them(server, config):
    """A data answer ends with CR, a status with CR LF; a command without operands sends
    none and is answered at once; an error answer carries its code."""
    robot = scripted_host(server, config)

    def session():
        robot.open()
        try:
            pose = robot.command("RPOSC 0,0").values
            status = robot.command("RSTATS").values
            robot.command("SVON 1")
            try:
                robot.command("MOVL 0,10.00,0,1,2,3,0,0,0,0,0,0,0,0,0,0,0")
            except JrcNotReady as exc:
                return pose, status, exc
        finally:
            robot.close()

    thread, result = in_thread(session)
    server.start_session()
    server.expect(b"HOSTCTRL_REQUEST RPOSC 4\r\n")
    server.send(b"OK: RPOSC\r\n")
    server.expect(b"0,0\r")
    server.send(b"1.000,2.000,3.000,0.00,0.00,0.00,0,0\r")
    server.expect(b"HOSTCTRL_REQUEST RSTATS 0\r\n")
    server.send(b"OK: RSTATS\r\n192,64\r")  # no operands: the answer follows the acknowledgement
    server.expect(b"HOSTCTRL_REQUEST SVON 2\r\n")
    server.send(b"OK: SVON\r\n")
    server.expect(b"1\r")
    server.send(b"0000\r\n")
    movl = b"0,10.00,0,1,2,3,0,0,0,0,0,0,0,0,0,0,0\r"
    server.expect(b"HOSTCTRL_REQUEST MOVL %d\r\n" % len(movl))
    server.send(b"OK: MOVL\r\n")
    server.expect(movl)
    server.send(b"ERROR: MOVL is not successful(2070).\r\n")
    assert server.closed_by_host()
    thread.join(10)
    pose, status, refusal = result["value"]
    assert pose == ("1.000", "2.000", "3.000", "0.00", "0.00", "0.00", "0", "0")
    assert status == ("192", "64")
    assert refusal.code == 2070 and "MOVL refused by the JRC: 2070 servo power is off" in str(refusal)


def test_a_server_that_grants_one_command_a_session_is_connected_to_again_for_the_next(server, config):
    robot = scripted_host(server, config)
    thread, result = in_thread(lambda: (robot.open(), robot.command("RSTATS").values, robot.command("RSTATS").values))
    for reply in (b"192,64\r", b"200,64\r"):
        server.accept()
        server.expect(b"CONNECT Robot_access Keep-Alive:-1\r\n")
        server.send(b"OK: DX Information Server( Ver. test).\r\n")  # no Keep-Alive: one command
        server.expect(b"HOSTCTRL_REQUEST RSTATS 0\r\n")
        server.send(b"OK: RSTATS\r\n" + reply)
        server.connection.close()  # its one command served
    thread.join(10)
    robot.close()
    assert result["value"][1:] == (("192", "64"), ("200", "64"))
    assert robot.link.connections == 2
    assert keep_alive_of("OK: DX Information Server(Ver) Keep-Alive:-1.") == -1
    assert keep_alive_of("OK: DX Information Server(Ver) Keep-Alive:5.") == 5


def test_a_command_the_server_refuses_names_its_words_and_the_next_connects_again(server, config):
    robot = scripted_host(server, config)
    thread, result = in_thread(lambda: (robot.open(), robot.command("RSTATS")))
    server.start_session()
    server.expect(b"HOSTCTRL_REQUEST RSTATS 0\r\n")
    server.send(b"NG: command remote is not set\r\n")
    server.connection.close()  # the server closes the connection after NG
    thread.join(10)
    refused = result["value"]
    assert isinstance(refused, CommandNotOffered) and not isinstance(refused, LinkError)
    assert "RSTATS refused by the Ethernet server" in str(refused) and "command remote is not set" in str(refused)

    def rstats_then_jwait():
        values = robot.command("RSTATS").values
        try:
            robot.command("JWAIT 1")
        except CommandNotOffered as exc:
            return values, exc

    thread, result = in_thread(rstats_then_jwait)
    server.start_session()
    server.expect(b"HOSTCTRL_REQUEST RSTATS 0\r\n")
    server.send(b"OK: RSTATS\r\n192,64\r")
    thread.join(10)
    robot.close()
    assert server.closed_by_host()  # and nothing sent for the JWAIT
    values, not_offered = result["value"]
    assert values == ("192", "64") and "JWAIT is not offered by the Ethernet server" in str(not_offered)


def test_a_silent_peer_fails_the_command_after_its_timer_and_the_hold_after_it(server, config):
    """A controller that goes silent after a request: the command fails after timer A, and
    so does the HOLD 1 tried on a new connection (whose start goes unanswered); the
    error says both."""
    robot = JrcBackend(config.jrc.on_ethernet(*server.address))
    thread, result = in_thread(lambda: (robot.open(), robot.command("RPOSC 0,0")))
    server.start_session()
    server.expect(b"HOSTCTRL_REQUEST RPOSC 4\r\n")  # and silence
    assert server.closed_by_host()
    server.connection.close()
    server.accept()  # the hold's connection
    server.expect(b"CONNECT Robot_access Keep-Alive:-1\r\n")  # silence again
    assert server.closed_by_host()
    thread.join(10)
    robot.close()
    error = result["value"]
    assert isinstance(error, LinkError), error
    message = str(error)
    timer_a = f"within timer A ({TEST_LINE['timer_a_s']:g} s)"
    assert message.startswith(
        f"RPOSC failed: the acknowledgement of RPOSC did not come from 127.0.0.1:{server.address[1]} {timer_a}"
    )
    assert f"HOLD 1 failed too (the start acknowledgement did not come from 127.0.0.1:{server.address[1]} {timer_a})" in message


def test_a_refused_connection_says_where(config):
    listener = socket.create_server(("127.0.0.1", 0))
    address = listener.getsockname()[:2]
    listener.close()  # nothing listens there now
    robot = JrcBackend(config.jrc.on_ethernet(*address))
    with pytest.raises(LinkError, match=f"cannot connect to the Ethernet server at 127.0.0.1:{address[1]}"):
        robot.connect()
    assert robot.link.connections == 0


# -- the emulator's Ethernet server ------------------------------------------------------


@pytest.fixture
def cell(config):
    return SimulatedCell(config)


def test_the_emulator_refuses_jwait_and_a_request_it_cannot_read_and_closes_the_connection(cell, config):
    emulator = JrcEmulator(cell, config.jrc, time_scale=TIME_SCALE)
    address = emulator.start_on_tcp()
    try:
        for request, refusal in (
            (b"HOSTCTRL_REQUEST JWAIT 3\r\n", b"NG: JWAIT is not a command of this server\r\n"),
            (b"HOSTCTRL_REQUEST RSTATS\r\n", b"NG: 'HOSTCTRL_REQUEST RSTATS' is not HOSTCTRL_REQUEST <command> <size>\r\n"),
        ):
            with socket.create_connection(address, timeout=10) as client:
                client.sendall(b"CONNECT Robot_access Keep-Alive:-1\r\n")
                assert client.recv(200) == b"OK: DX Information Server( Ver. vservo emulator) Keep-Alive:-1.\r\n"
                client.sendall(request)
                assert client.recv(200) == refusal
                assert client.recv(1) == b""  # closed
        with socket.create_connection(address, timeout=10) as client:
            client.sendall(b"GET / HTTP/1.1\r\n")
            assert client.recv(200) == b"NG: HTTP Error Response\r\n"
    finally:
        emulator.stop()


def test_wait_motion_reads_the_status_until_the_move_has_ended(cell, config):
    """No JWAIT over Ethernet: the end of a motion is RSTATS's running bit dropping."""
    with jrc_link(cell, config, transport=ETHERNET) as (robot, emulator):
        robot.servo(True)
        start = robot.read_pose()
        target = transform(t=(0.0, 0.02, 0.0)) @ start
        before = emulator.exchanges
        robot.move_to(target, 0.05)
        assert robot.wait_motion() is True
        statuses = emulator.exchanges - before - 1
        assert pose_error(cell.jrc_arm.fk(cell.state.q), target)[0] < 1e-6
    assert statuses >= 1 and not any(text.startswith("JWAIT") for text in emulator.executed)


def test_a_dropped_connection_after_a_move_leaves_the_move_done_once_and_the_robot_held(cell, config):
    """The server carries out the MOVL and closes the connection before answering: the
    host cannot know, holds the robot on a new connection and says so; the move was
    carried out once."""
    with jrc_link(cell, config, transport=ETHERNET) as (robot, emulator):
        robot.servo(True)
        target = transform(t=(0.02, 0.0, 0.0)) @ robot.read_pose()
        emulator.faults.inject("drop")
        with pytest.raises(
            LinkError,
            match=r"MOVL failed: the controller at .* closed the connection before the answer to MOVL; the robot is held",
        ):
            robot.move_to(target, 0.05)
        status = robot.status()
        assert status.held and "command hold" in status.detail
        assert len(emulator.executed) == 1 and emulator.executed[0].startswith("MOVL")
        robot.hold(False)
        robot.move_to(target, 0.05)
        assert robot.wait_motion()
        assert pose_error(cell.jrc_arm.fk(cell.state.q), target)[0] < 1e-6
        assert robot.link.connections == 2 and emulator.faults.injected["drop"] == 1


def test_a_silent_controller_fails_the_command_within_its_wait_and_the_robot_is_left_held(cell, config):
    with jrc_link(cell, config, transport=ETHERNET) as (robot, emulator):
        robot.servo(True)
        emulator.faults.inject("timeout")
        with pytest.raises(
            LinkError,
            match=r"RPOSC failed: the answer to RPOSC did not come from .* within the reply wait \(0.5 s\); the robot is held",
        ):
            robot.read_pose()
        status = robot.status()  # a new connection, in a known state
        assert status.held and "command hold" in status.detail
        robot.hold(False)
        assert robot.status().ready


def test_a_late_answer_within_the_wait_is_taken(cell, config):
    with jrc_link(cell, config, transport=ETHERNET) as (robot, emulator):
        emulator.faults.inject("delay")
        assert robot.status().servo_on is False
        assert robot.link.connections == 1 and emulator.faults.injected["delay"] == 1


def test_faults_a_tcp_connection_cannot_meet_are_refused(cell, config):
    emulator = JrcEmulator(cell, config.jrc, FaultPlan(0.1, kinds=("bcc", "drop")))
    with pytest.raises(ValueError, match=r"fault kinds \['bcc'\] cannot happen on this link"):
        emulator.start_on_tcp()
    emulator = JrcEmulator(cell, config.jrc)
    emulator.start_on_tcp()
    try:
        with pytest.raises(ValueError, match="unknown fault kind 'nak' on this link"):
            emulator.faults.inject("nak")
    finally:
        emulator.stop()


# -- the cell file ------------------------------------------------------------------------


def ethernet_cell(**keys):
    data = default_data()
    data["jrc"] = {"transport": "ethernet", "host": "192.168.255.1", **keys}
    return parse_cell(data, "test cell")


def test_the_cell_file_names_the_controllers_address_and_its_timers():
    line = ethernet_cell(port=80, timer_a_s=1.0, status_poll_s=0.02).jrc
    assert line.transport is ETHERNET and line.address == "192.168.255.1:80"
    assert line.timer_a_s == 1.0 and line.timer_b_s == 20.0 and line.status_poll_s == 0.02
    assert ethernet_cell().jrc.tcp_port == 80  # the Ethernet server's port by default
    assert "baud" not in line.in_use() and line.in_use()["host"] == "192.168.255.1"  # what `vservo info` shows
    assert isinstance(JrcBackend(ethernet_cell().jrc).link, EthernetLink)  # built, not connected


@pytest.mark.parametrize(
    "keys, words",
    [
        ({"port": 0}, ["jrc.port = 0", "a TCP port, 1 to 65535"]),
        ({"port": "/dev/ttyS0"}, ["jrc.port", "must be an integer"]),
        ({"baud": 9600}, ["jrc.baud = 9600", 'has no meaning with transport = "ethernet"']),
        ({"jwait_slice_s": 0.5}, ["jrc.jwait_slice_s", "has no meaning"]),
        ({"status_poll_s": 0.0}, ["jrc.status_poll_s", "must be positive"]),
        ({"host": ""}, ["jrc.host", "non-empty string"]),
    ],
)
def test_a_bad_ethernet_key_is_refused_by_name(keys, words):
    with pytest.raises(ConfigError) as refused:
        ethernet_cell(**keys)
    assert all(word in str(refused.value) for word in words), str(refused.value)


def test_the_ethernet_keys_are_refused_on_a_serial_line_and_the_host_is_required():
    data = default_data()
    data["jrc"]["host"] = "192.168.255.1"
    with pytest.raises(ConfigError, match='jrc.host = .*has no meaning with transport = "serial"'):
        parse_cell(data, "test cell")
    data = default_data()
    data["jrc"] = {"transport": "ethernet"}
    with pytest.raises(ConfigError, match="missing key jrc.host"):
        parse_cell(data, "test cell")
    data["jrc"] = {"transport": "wifi"}
    with pytest.raises(ConfigError, match="jrc.transport = 'wifi': must be one of serial, ethernet"):
        parse_cell(data, "test cell")


def test_a_simulated_cell_file_on_ethernet_gets_its_emulated_jrc_as_an_ethernet_server():
    data = default_data()
    data["robot"]["backend"] = "jrc"
    data["jrc"] = {"transport": "ethernet", "host": "192.168.255.1", "timer_a_s": ETHERNET_TIMER_A_S, "timer_b_s": 0.5}
    rig = simulated_rig(parse_cell(data, "test cell"), seed=1)
    try:
        jrc = rig.robot.robot
        assert isinstance(jrc.link, EthernetLink) and jrc.port.startswith("127.0.0.1:")  # the emulator's, not the file's
        rig.robot.connect()
        assert pose_error(rig.robot.read_pose(), rig.cell.jrc_arm.fk(rig.cell.state.q))[0] < 1e-6
    finally:
        rig.close()
