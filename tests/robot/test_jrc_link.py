"""The JRC host link over a real pseudo-terminal: the framing and its test vectors, the
data link's recovery against a scripted JRC, the host commands against the
JRC emulator, every injected fault, and a short soak. The host commands are tested over
the Ethernet server's loopback TCP port too (``TRANSPORTS``); its framing and failures
are in tests/test_jrc_ethernet.py."""

import os
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
import serial

from tests.jrc_fixtures import ETHERNET_TIMER_A_S, TEST_LINE, TIME_SCALE, jrc_link, short_timer_cell
from vservo.core.cell.config import HostTransport
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.geometry.spatial import Pose6, inverse, matrix_from_pose, pose_error, rot_x, rot_z, transform
from vservo.core.robot.backend import RobotError
from vservo.core.robot.bsc import (
    ACK0,
    ACK1,
    ENQ,
    EOT,
    ETB,
    ETX,
    NAK,
    SOH,
    STX,
    BscStation,
    ByteChannel,
    LinkError,
    Message,
    block_check,
    encode_blocks,
)
from vservo.core.robot.jrc import (
    ERROR_MESSAGES,
    JrcBackend,
    JrcCommandError,
    JrcNotReady,
    describe_error,
    pose_from_wire,
    wire_pose,
)
from vservo.core.robot.jrc_vacuum import JrcVacuum
from vservo.core.sim.jrc_emulator import ETHERNET_FAULT_KINDS, FAULT_KINDS, FaultPlan, JrcEmulator
from vservo.core.sim.plant import SimulatedCell
from vservo.core.sim.pseudo_terminal import PseudoTerminal
from vservo.core.study.link_soak import run_soak

pytestmark = pytest.mark.usefixtures("no_leaked_threads")


@pytest.fixture(scope="module")
def config():
    return short_timer_cell()


@pytest.fixture
def cell(config):
    return SimulatedCell(config)


# The host command set behind either link: a test parametrized over these runs over both.
TRANSPORTS = pytest.mark.parametrize("transport", list(HostTransport))


@pytest.fixture
def transport():
    return HostTransport.SERIAL


@pytest.fixture
def link(cell, config, transport):
    with jrc_link(cell, config, transport=transport) as (robot, emulator):
        yield robot, emulator


@pytest.fixture
def emulator(link):
    return link[1]


@pytest.fixture
def robot(link):
    return link[0]


def bcc_by_hand(body: bytes) -> bytes:
    total = 0
    for b in body:
        total = (total + b) % 65536
    return bytes((total % 256, total // 256))


# -- framing ---------------------------------------------------------------------------


def test_the_bcc_of_the_protocol_test_vector():
    """docs/robot-link.md: header 02,030, text SYSTEM CR, ETB: the sum from '0' through ETB is
    0x032C, sent as 0x2C 0x03."""
    assert block_check(b"02,030" + bytes((STX,)) + b"SYSTEM\r" + bytes((ETB,))) == bytes((0x2C, 0x03))


def test_a_long_text_is_cut_into_blocks_ended_by_etb_then_etx():
    text = "A" * 300 + "\r"
    first, second = encode_blocks(Message("02,030", text))
    assert first[0] == SOH and first[1:7] == b"02,030" and first[7] == STX
    assert first[8 : 8 + 256] == b"A" * 256 and first[8 + 256] == ETB
    assert first[-2:] == bcc_by_hand(first[1:-2])
    assert second[0] == STX and second[1:-3] == b"A" * 44 + b"\r" and second[-3] == ETX
    assert second[-2:] == bcc_by_hand(second[1:-2])


def test_every_jrc_error_code_has_a_clear_message():
    for code in (1010, 1011, 1012, 1013, 2010, 2020, 2030, 2040, 2050, 2060, 2070, 2100, 3010, 3040, 3070, 4040, 5110, 5200):
        assert code in ERROR_MESSAGES, code
    assert "servo power is off" in describe_error(2070)
    assert "remote" in describe_error(2100)
    assert describe_error(5150) == "5150 syntax, format or range error"
    assert describe_error(2045) == "2045 the robot is held"
    assert "unknown" in describe_error(9999)


def test_the_wire_pose_is_x_y_z_then_rx_ry_rz_about_the_fixed_base_axes():
    """Rx, Ry, Rz are phi's, theta's and psi's places swapped: R = Rz(Rz) Ry(Ry) Rx(Rx)."""
    bMe = matrix_from_pose(Pose6(0.1, -0.2, 0.3, np.radians(10.0), np.radians(-20.0), np.radians(30.0)))
    assert np.allclose(wire_pose(bMe), [100.0, -200.0, 300.0, 30.0, -20.0, 10.0])
    # A turn about the base X axis alone is Rx alone.
    assert np.allclose(wire_pose(transform(rot_x(np.radians(25.0)))), [0, 0, 0, 25.0, 0, 0], atol=1e-9)
    assert np.allclose(pose_from_wire(wire_pose(bMe)), bMe)


# -- the data link against a scripted JRC ----------------------------------------------


class ScriptedJrc:
    """The JRC's end of a pty driven byte by byte by the test (no emulator code)."""

    def __init__(self, pty: PseudoTerminal) -> None:
        self.fd = pty.master_fd

    def expect(self, expected: bytes, timeout_s: float = 5.0) -> None:
        assert self.read(len(expected), timeout_s) == expected

    def read(self, n: int, timeout_s: float = 5.0) -> bytes:
        data, deadline = b"", time.monotonic() + timeout_s
        while len(data) < n and time.monotonic() < deadline:
            if pty_ready(self.fd, 0.01):
                data += os.read(self.fd, n - len(data))
        return data

    def read_block(self) -> bytes:
        data = b""
        while not data or data[-1] not in (ETX, ETB):
            data += self.read(1)
        return data + self.read(2)

    def send(self, data: bytes) -> None:
        os.write(self.fd, data)

    def accept_bid(self) -> None:
        self.expect(bytes((ENQ,)))
        self.send(ACK0)

    def bid(self) -> None:
        self.send(bytes((ENQ,)))
        self.expect(ACK0)

    def end_command(self) -> None:
        """ACK1 for the host's (single) block, then its EOT."""
        self.send(ACK1)
        self.expect(bytes((EOT,)))

    def reply(self, block: bytes) -> None:
        """Bid, send one reply block, take the host's ACK1 and end with EOT."""
        self.bid()
        self.send(block)
        self.expect(ACK1)
        self.send(bytes((EOT,)))


def pty_ready(fd: int, timeout_s: float) -> bool:
    import select

    return bool(select.select([fd], [], [], timeout_s)[0])


def reply_block(text: bytes) -> bytes:
    body = b"90,001" + bytes((STX,)) + text + b"\r" + bytes((ETX,))
    return bytes((SOH,)) + body + bcc_by_hand(body)


def run_host(line, device, text):
    """A host command in a thread: (reply values or the exception, the backend's counters)."""
    result = {}

    def host():
        robot = JrcBackend(line, device)
        robot.open()
        try:
            result["reply"] = robot.command(text).values
        except RobotError as exc:
            result["reply"] = exc
        result["counters"] = robot.station.counters
        robot.close()

    thread = threading.Thread(target=host)
    thread.start()
    return thread, result


def test_the_host_resends_on_nak_and_refuses_a_bad_bcc(config):
    """One RPOSC the way docs/robot-link.md draws it, with a NAK from the JRC and a
    corrupted reply block the host must NAK."""
    with PseudoTerminal() as pty:
        jrc = ScriptedJrc(pty)
        thread, result = run_host(config.jrc, pty.device, "RPOSC 0,0")
        jrc.accept_bid()
        body = b"01,000" + bytes((STX,)) + b"RPOSC 0,0\r" + bytes((ETX,))
        command = bytes((SOH,)) + body + bcc_by_hand(body)
        assert jrc.read_block() == command
        jrc.send(bytes((NAK,)))
        assert jrc.read_block() == command  # sent again
        jrc.end_command()
        jrc.bid()
        good = reply_block(b"1.000,2.000,3.000,0.00,0.00,0.00,0,0")
        jrc.send(good[:-1] + bytes(((good[-1] + 1) % 256,)))
        jrc.expect(bytes((NAK,)))
        jrc.send(good)
        jrc.expect(ACK1)
        jrc.send(bytes((EOT,)))
        thread.join(10)
    assert result["reply"] == ("1.000", "2.000", "3.000", "0.00", "0.00", "0.00", "0", "0")
    assert result["counters"].naks_received == 1 and result["counters"].naks_sent == 1


def test_a_lost_ack_is_asked_for_with_enq_and_the_block_is_not_sent_twice(config):
    with PseudoTerminal() as pty:
        jrc = ScriptedJrc(pty)
        thread, result = run_host(config.jrc, pty.device, "RSTATS")
        jrc.accept_bid()
        jrc.read_block()
        # No ACK1: after timer A the host asks with ENQ; ACK1 says the block arrived.
        jrc.expect(bytes((ENQ,)))
        jrc.end_command()
        jrc.reply(reply_block(b"192,64"))
        thread.join(10)
        assert not pty_ready(pty.master_fd, 0.1)  # nothing more: the command block went once
    assert result["reply"] == ("192", "64")
    assert result["counters"].enq_retries == 1 and result["counters"].text_resends == 0


def test_the_host_yields_when_both_ends_bid(config):
    """The JRC bids with a late reply as the host bids: the host takes it, then bids again."""
    with PseudoTerminal() as pty:
        jrc = ScriptedJrc(pty)
        thread, result = run_host(config.jrc, pty.device, "RSTATS")
        jrc.expect(bytes((ENQ,)))
        jrc.reply(reply_block(b"stale"))  # contention: the JRC bids too
        jrc.expect(bytes((ENQ,)))  # the host bids again
        jrc.send(ACK0)
        jrc.read_block()
        jrc.end_command()
        jrc.reply(reply_block(b"192,64"))
        thread.join(10)
    assert result["reply"] == ("192", "64")
    assert result["counters"].contentions == 1


def test_after_its_retries_the_host_ends_with_eot_and_names_the_command(config):
    line = config.jrc
    with PseudoTerminal() as pty:
        jrc = ScriptedJrc(pty)
        thread, result = run_host(line, pty.device, "SVON 1")
        # Never answer: the host bids 1 + retry_1 times, ends with EOT, then tries HOLD 1 the same way.
        received = jrc.read(2 * (line.retry_1 + 2), timeout_s=10.0)
        thread.join(10)
    bid = bytes((ENQ,)) * (line.retry_1 + 1) + bytes((EOT,))
    assert received == bid + bid
    error = result["reply"]
    assert isinstance(error, LinkError)
    assert str(error).startswith("SVON failed: no ACK0 to ENQ after 4 tries") and "HOLD 1 failed too" in str(error)


def test_a_block_refused_more_than_retry_2_times_fails_the_command(config):
    line = config.jrc
    with PseudoTerminal() as pty:
        jrc = ScriptedJrc(pty)
        thread, result = run_host(line, pty.device, "SVON 1")
        jrc.accept_bid()
        for _ in range(line.retry_2 + 1):
            jrc.read_block()
            jrc.send(bytes((NAK,)))
        jrc.expect(bytes((EOT,)))
        thread.join(10)
    assert str(result["reply"]).startswith("SVON failed: block 1 of 1 refused 4 times (retry 2 = 3)")


def test_a_reply_that_never_ends_fails_after_timer_b(config):
    with PseudoTerminal() as pty:
        jrc = ScriptedJrc(pty)
        thread, result = run_host(config.jrc, pty.device, "RSTATS")
        jrc.accept_bid()
        jrc.read_block()
        jrc.end_command()
        jrc.bid()
        jrc.send(reply_block(b"192,64")[:6])  # cut short, then silence
        thread.join(10)
    assert str(result["reply"]).startswith("RSTATS failed: the text did not end within timer B (0.5 s)")


# -- the JRC emulator, byte by byte ----------------------------------------------------


def test_the_emulator_answers_one_transaction_as_the_protocol_draws_it(emulator, cell, config):
    port = serial.Serial(emulator.device, timeout=2.0)
    try:
        port.write(bytes((ENQ,)))
        assert port.read(2) == ACK0
        body = b"01,000" + bytes((STX,)) + b"RPOSC 0,0\r" + bytes((ETX,))
        port.write(bytes((SOH,)) + body + bcc_by_hand(body))
        assert port.read(2) == ACK1
        port.write(bytes((EOT,)))
        assert port.read(1) == bytes((ENQ,))
        port.write(ACK0)
        block = port.read_until(bytes((ETX,))) + port.read(2)
        port.write(ACK1)
        assert port.read(1) == bytes((EOT,))
    finally:
        port.close()
    assert block[0] == SOH and block[1:8] == b"90,001" + bytes((STX,))
    assert block[-2:] == bcc_by_hand(block[1:-2])
    values = [float(v) for v in block[8:-4].decode().split(",")]
    bMe = cell.jrc_arm.fk(cell.state.q)
    assert np.allclose(values[:3], bMe[:3, 3] * 1000.0, atol=0.0005)
    assert len(values) == 8


def test_the_emulator_serves_a_serial_port_it_is_given(cell, config):
    """On a port opened with pyserial (the slave of a pty); the host here is the master end."""
    with PseudoTerminal() as pty:
        emulator = JrcEmulator(cell, config.jrc, time_scale=TIME_SCALE)
        emulator.start_on_port(pty.device)
        try:
            host = BscStation(ByteChannel(pty.port), config.jrc, yields=True)
            host.send(Message("01,000", "RSTATS\r"))
            reply = host.receive(config.jrc.timer_b_s)
        finally:
            emulator.stop()
    assert reply == Message("90,001", "192,0\r")  # play and remote; no hold, alarm or servo power


# -- host commands against the emulator ------------------------------------------------


@TRANSPORTS
def test_status_servo_pose_and_moves(robot, cell):
    assert not robot.status().servo_on
    robot.servo(True)
    status = robot.status()
    assert status.servo_on and status.ready and not status.running
    bMe = robot.read_pose()
    translation, rotation = pose_error(bMe, cell.jrc_arm.fk(cell.state.q))
    assert translation < 1e-6 and rotation < np.radians(0.006)  # RPOSC's 0.001 mm and 0.01 deg

    target = transform(t=(0.02, -0.01, 0.005)) @ bMe
    robot.move_to(target, 0.05)
    assert robot.wait_motion() is True
    translation, _ = pose_error(cell.jrc_arm.fk(cell.state.q), target)
    assert translation < 1e-6
    before = cell.jrc_arm.fk(cell.state.q)
    robot.move_by(transform(t=(0.0, 0.0, -0.01)), 0.05)
    assert robot.wait_motion()
    after = cell.jrc_arm.fk(cell.state.q)
    assert np.allclose(after[:3, 3] - before[:3, 3], [0.0, 0.0, -0.01], atol=1e-6)
    assert np.allclose(after[:3, :3], before[:3, :3], atol=1e-6)


@TRANSPORTS
def test_a_turn_finer_than_the_readback_is_not_lost(robot, cell):
    """RPOSC reads degrees to 0.01; a servo step of a fiftieth turns by less. Aimed from
    a reading rounded back to where it started, the arm would stand still step after step."""
    robot.servo(True)
    bMe = robot.read_pose()
    for _ in range(10):  # ten turns of 0.003 deg about the flange's own z
        target = bMe @ transform(R=rot_z(np.radians(0.003)))
        robot.move_to(target, 0.05)
        assert robot.wait_motion()
        bMe = robot.read_pose()
        assert pose_error(bMe, target)[1] < np.radians(1e-4)  # the target, to its 4 decimals
    _, turned = pose_error(cell.jrc_arm.fk(cell.state.q), bMe)
    assert turned < np.radians(1e-4)
    # A pose the host did not send (an IMOV here) is read as the JRC reports it.
    robot.move_by(transform(t=(0.0, 0.0, -0.005)), 0.05)
    assert robot.wait_motion()
    translation, rotation = pose_error(robot.read_pose(), cell.jrc_arm.fk(cell.state.q))
    assert translation < 1e-6 and rotation < np.radians(0.006)


@TRANSPORTS
def test_refusals_carry_the_jrcs_reason(robot):
    bMe = robot.read_pose()
    with pytest.raises(JrcNotReady, match="2070 servo power is off"):
        robot.move_to(bMe, 0.05)
    robot.servo(True)
    robot.hold(True)
    with pytest.raises(JrcNotReady, match="MOVL refused by the JRC: 2050 held by the host"):
        robot.move_to(bMe, 0.05)
    robot.hold(False)
    with pytest.raises(JrcCommandError, match="1010"):
        robot.command("FLY 1")
    with pytest.raises(JrcCommandError, match="1012 too few operands"):
        robot.command("RPOSC 0")
    with pytest.raises(RobotError, match="position_steps"):
        robot.move_timed(bMe, 0.1)
    with pytest.raises(UnreachableTarget, match="MOVL refused by the JRC: 5200 data out of range"):
        robot.move_to(transform(t=(2.0, 0.0, 0.0)) @ bMe, 0.05)


@TRANSPORTS
def test_a_hold_stops_the_motion_where_it_is(robot, cell, emulator):
    emulator.time_scale = 1.0  # a 40 mm move at 10 mm/s lasts 4 s
    robot.servo(True)
    start = robot.read_pose()
    target = transform(t=(0.04, 0.0, 0.0)) @ start
    robot.move_to(target, 0.01)
    robot.hold(True)
    assert robot.wait_motion() is False
    status = robot.status()
    assert status.held and not status.running and "command hold" in status.detail
    assert pose_error(cell.jrc_arm.fk(cell.state.q), target)[0] > 0.03


@TRANSPORTS
def test_an_alarm_in_the_middle_of_a_move_is_reported_and_reset(robot, cell, emulator):
    robot.servo(True)
    start = robot.read_pose()
    target = transform(t=(0.0, 0.03, 0.0)) @ start
    emulator.faults.inject("alarm")
    robot.move_to(target, 0.05)
    assert robot.wait_motion() is False
    status = robot.status()
    assert status.alarm and not status.servo_on and "4315 COLLISION DETECT" in status.detail
    travelled = pose_error(cell.jrc_arm.fk(cell.state.q), start)[0]
    assert 0.0 < travelled < 0.03  # stopped part of the way
    with pytest.raises(JrcNotReady, match="2060"):
        robot.move_to(target, 0.05)
    robot.reset_alarms()
    robot.servo(True)
    robot.move_to(target, 0.05)
    assert robot.wait_motion() and pose_error(cell.jrc_arm.fk(cell.state.q), target)[0] < 1e-6
    assert emulator.faults.injected["alarm"] == 1


@TRANSPORTS
def test_a_pendant_hold_lasts_until_the_pendant_releases_it(cell, config, transport):
    # A hold of 40 s of JRC time, 2 s of wall time: long enough that a loaded machine still
    # reads the status before the pendant releases it.
    with jrc_link(cell, config, FaultPlan(pendant_hold_s=40.0), transport=transport) as (robot, emulator):
        robot.servo(True)
        target = transform(t=(0.0, -0.03, 0.0)) @ robot.read_pose()
        emulator.faults.inject("hold")
        robot.move_to(target, 0.05)
        assert robot.wait_motion() is False
        status = robot.status()
        assert status.held and "pendant hold" in status.detail
        robot.hold(False)  # the host cannot release the pendant's hold
        with pytest.raises(JrcNotReady, match="2020 held from the programming pendant"):
            robot.move_to(target, 0.05)
        deadline = time.monotonic() + 10.0
        while robot.status().held and time.monotonic() < deadline:
            time.sleep(0.01)
        robot.move_to(target, 0.05)
        assert robot.wait_motion()


@pytest.mark.parametrize(
    "kind, counter",
    [
        ("bcc", "naks_sent"),
        ("nak", "text_resends"),
        ("missing_ack", "enq_retries"),
        ("drop", None),
        ("delay", None),
    ],
)
def test_every_link_fault_is_recovered(cell, config, kind, counter):
    with jrc_link(cell, config, FaultPlan(1.0, seed=3, kinds=(kind,))) as (robot, emulator):
        poses = [robot.read_pose() for _ in range(12)]
        counters = robot.station.counters
    bMe = cell.jrc_arm.fk(cell.state.q)
    assert all(pose_error(pose, bMe)[0] < 1e-6 for pose in poses)
    assert emulator.faults.injected[kind] >= 12
    if counter is not None:
        assert getattr(counters, counter) >= 12


def test_a_silent_jrc_fails_the_command_and_the_robot_is_left_held(robot, emulator):
    robot.servo(True)
    emulator.faults.inject("timeout")
    with pytest.raises(LinkError, match=r"RPOSC failed: no ACK0 to ENQ after 4 tries .*the robot is held"):
        robot.read_pose()
    status = robot.status()  # the link works again, in a known state
    assert status.held and "command hold" in status.detail
    robot.hold(False)
    assert robot.status().ready


def test_the_emulator_refuses_bad_fault_plans():
    with pytest.raises(ValueError, match="rate"):
        FaultPlan(1.5)
    with pytest.raises(ValueError, match="unknown fault kinds"):
        FaultPlan(0.1, kinds=("gremlins",))


# -- I/O: the vacuum cup on the JRC's signals --------------------------------------------

VACUUM_IO = {"device": "jrc_io", "suction_output": 27013, "grip_input": 20}


@TRANSPORTS
def test_the_cup_on_the_jrcs_io_switches_suction_and_reads_its_pressure_switch(cell, transport):
    """Suction is bit 3 of network input byte 27010, which the emulator's ladder copies to the
    valve; the pressure switch is input 20. The byte's other signals keep their state."""
    config = short_timer_cell(robot={"backend": "jrc"}, vacuum=VACUUM_IO)
    with jrc_link(cell, config, transport=transport) as (robot, emulator):
        cup = JrcVacuum(robot, 27013, 20)
        emulator.network_inputs[27010] = 0b1000_0001  # two signals the cell's ladder uses for something else
        cup.set_vacuum(True)
        assert emulator.network_inputs[27010] == 0b1000_1001
        assert not cup.holding() and not cell.holding_part  # nothing under the cup
        cup.set_vacuum(False)
        assert emulator.network_inputs[27010] == 0b1000_0001

        side = cell.state.scene.cube.side_m
        bMv = cell.ground_truth_bMe() @ cell.truth.model.eMv
        cell.place_cube(bMv @ inverse(transform(rot_x(np.pi), (side / 2, side / 2, 0.0))))  # the part on the cup
        cup.set_vacuum(True)
        assert cell.holding_part and cup.holding() and robot.read_io(20) == [1]
        cup.set_vacuum(False)
        assert not cell.holding_part and not cup.holding() and robot.read_io(20) == [0]


@TRANSPORTS
def test_io_commands_take_whole_bytes_and_write_only_the_wired_network_input(cell, transport):
    config = short_timer_cell(robot={"backend": "jrc"}, vacuum=VACUUM_IO)
    with jrc_link(cell, config, transport=transport) as (robot, emulator):
        robot.write_io(27010, [5])
        assert robot.read_io(27010, 2) == [5, 0]
        for text in ("IOREAD 27013,8", "IOREAD 27010,4", "IOWRITE 27010,8,256", "IOWRITE 27010,16,1"):
            with pytest.raises(JrcCommandError) as refused:
                robot.command(text)
            assert refused.value.code == 1013, text
        with pytest.raises(JrcCommandError, match="2110"):
            robot.write_io(30000, [1])  # no ladder reads this byte
    with jrc_link(cell, short_timer_cell(), transport=transport) as (robot, emulator):  # a cell whose cup is not on the I/O
        with pytest.raises(JrcCommandError, match="2110"):
            robot.write_signal(27013, True)
        assert robot.read_signal(20) is False


# -- the soak --------------------------------------------------------------------------


@TRANSPORTS
def test_a_short_soak_loses_no_move_and_accounts_for_every_fault(config, transport):
    """Over TCP the faults are a connection's own (ETHERNET_FAULT_KINDS), with no retries:
    one timer A, and a dropped connection loses the answer as a silence does."""
    ethernet = transport is HostTransport.ETHERNET
    result = run_soak(
        config,
        moves=120,
        fault_rate=0.15,
        seed=5,
        time_scale=TIME_SCALE,
        timer_a_s=ETHERNET_TIMER_A_S if ethernet else TEST_LINE["timer_a_s"],
        timer_b_s=TEST_LINE["timer_b_s"],
        transport=transport,
    )
    injected = result["faults_injected"]
    assert set(injected) == set(ETHERNET_FAULT_KINDS if ethernet else FAULT_KINDS)
    assert all(injected[kind] > 0 for kind in injected), injected
    for kind in injected:
        assert result["faults_recovered"][kind] + result["faults_reported"][kind] == injected[kind], kind
    assert result["faults_unaccounted"] == 0
    for kind in ("timeout", "drop") if ethernet else ("timeout",):  # a silence outlasts every retry
        assert result["faults_reported"][kind] == injected[kind], kind
    assert sum(result["faults_recovered"].values()) > 0
    assert result["moves_off_path"] == 0 and result["commands_accepted_twice"] == 0
    assert result["final_pose_error_mm"] < 0.01 and result["final_pose_error_deg"] < 0.001


def bsc_exchange_s(line, text: str) -> float:
    """One message's exchange on the line, its bytes counted by hand from the framing: the
    sender's ENQ, the ACK0, SOH + a 6-byte header + STX + the text + CR + ETX + a 2-byte
    BCC, the ACK1, the EOT."""
    return line.wire_time_s(1 + 2 + (1 + 6 + 1 + len(text) + 1 + 1 + 2) + 2 + 1)


def test_the_cell_clock_counts_the_motion_and_the_wire_whatever_the_wall_clock_did(config):
    """A 40 mm move at 10 mm/s counts as a real JRC at 9600 baud takes it: the MOVL crosses,
    the arm moves 4 s while the MOVL's answer and the JWAITs cross, and the JWAIT's answer
    that it has ended crosses after. The same figure, to the last bit, at any speed-up of
    the emulator and with the host busy elsewhere for most of the motion (0.06 s on the
    wall is 3 s of the arm's 4 at 50 x); a dwell counts the controller time it is given,
    waited out time_scale times faster."""
    moves = []
    for time_scale, host_busy_s in ((50.0, 0.0), (50.0, 0.06), (400.0, 0.0)):
        line = replace(config.jrc, time_scale=time_scale)
        with jrc_link(SimulatedCell(config), replace(config, jrc=line), time_scale=time_scale) as (robot, _):
            robot.servo(True)
            start = robot.read_pose()
            before = robot.cell_clock_s()
            robot.move_to(transform(t=(0.04, 0.0, 0.0)) @ start, 0.01)
            movl = robot.last_command
            time.sleep(host_busy_s)
            assert robot.wait_motion()
            moves.append(robot.cell_clock_s() - before)
            before, wall_s = robot.cell_clock_s(), time.monotonic()
            robot.dwell(2.0)
            assert robot.cell_clock_s() - before == pytest.approx(2.0)
            assert time.monotonic() - wall_s >= 2.0 / time_scale
        # 4 s, within what the reading's rounding (0.001 mm, 0.01 deg) moves the target.
        assert moves[-1] == pytest.approx(bsc_exchange_s(line, movl) + 4.0 + bsc_exchange_s(line, "0"), abs=1e-3)
    assert moves[0] == moves[1] == moves[2]
