"""The JRC and its family: a RobotBackend speaking the Yaskawa host commands.

Each method is one or two host commands (docs/robot-link.md), carried by a HostLink
(core/robot/host_link.py): BSC blocks over RS-232 (core/robot/serial_link.py), as the
JRC takes them, or TCP to the Ethernet server of a DX100 or later controller
(core/robot/ethernet_link.py), as the cell file's ``[jrc] transport`` says. The answer
is a status code or data, whatever the link. The commands used: RPOSC (pose), RSTATS
(status), RALARM (alarm text), RESET and CANCEL, SVON, HOLD, MOVL (linear move to a
Cartesian target), IMOV (incremental linear move), JWAIT (wait for the end of the
motion; over Ethernet, which does not offer it, RSTATS read until the motion has ended),
IOREAD and IOWRITE (the I/O signals a vacuum cup is wired to; their forms are inferred).

Units and angles at the wire: X, Y, Z in mm, Rx, Ry, Rz in degrees, base coordinates.
Rx, Ry, Rz are taken as fixed-axis rotations about the base X, then Y, then Z, so
R = Rz(Rz) Ry(Ry) Rx(Rx): eq. 2-13 with phi = Rz, theta = Ry, psi = Rx
(core/geometry/spatial.py). RPOSC is asked for tool 0, taken to be the bare flange: bMe. Both
are the conventions of the Yaskawa manuals of the family and need one check on the real
controller (jog about one axis, compare the pendant's readout with ``read_pose``).

A command whose link fails (after the BSC link's retries, or a TCP connection that
closed or stayed silent) holds the robot with HOLD 1 if the link still carries it, and
raises LinkError naming the command, the cause and whether the hold got through. An
error code in an answer raises JrcCommandError (RobotNotReady for holds, alarms and
servo off) with the code's meaning.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from vservo.core.cell.config import HostTransport, JrcLineConfig
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.geometry.spatial import Matrix, Pose6, matrix_from_pose, pose_from_matrix, pose_from_mm_deg, pose_to_mm_deg
from vservo.core.robot.backend import RobotError, RobotNotReady, RobotStatus, apply_increment
from vservo.core.robot.bsc import BscStation
from vservo.core.robot.ethernet_link import EthernetLink
from vservo.core.robot.host_link import Answer, Exchange, HostLink, LinkError, LinkLost, ReplyKind
from vservo.core.robot.serial_link import SerialLink

# Status codes of a status answer, after the host-control manuals of the ERC/MRC/XRC family.
ERROR_MESSAGES = {
    1010: "command error: the JRC does not know this command",
    1011: "too many operands",
    1012: "too few operands",
    1013: "an operand is out of range",
    2010: "the robot is moving: wait for the end of the motion",
    2020: "held from the programming pendant",
    2030: "held from the playback panel",
    2040: "held by the external hold input",
    2050: "held by the host (HOLD 1): release it with HOLD 0",
    2060: "an alarm or error is active: read it (RALARM) and reset it",
    2070: "servo power is off",
    2080: "the JRC is in the wrong mode (teach or play)",
    2090: "another function is using the file",
    2100: "command remote is not set: select remote mode on the JRC",
    2110: "this data cannot be accessed",
    3010: "turn servo power on first",
    3040: "home positioning has not been done",
    3050: "confirm the positions first",
    3070: "the current position has not been made",
    4040: "no such job",
    5110: "syntax error: no such instruction",
    5120: "position data error",
    5170: "format error",
    5180: "wrong number of data",
    5200: "data out of range (a target the robot cannot reach, or a speed beyond its limits)",
}
ERROR_RANGES = (
    (1010, 1019, "command or operand error"),
    (2020, 2059, "the robot is held"),
    (5110, 5200, "syntax, format or range error"),
)
NOT_READY_CODES = frozenset({2020, 2030, 2040, 2050, 2060, 2070, 3010})
OUT_OF_RANGE = 5200
ROBOT_OPERATING = 2010

# RSTATS: d1 bit 3 running; d2 bits 1..3 holds (pendant, external, command), 4 alarm,
# 5 error, 6 servo on.
D1_RUNNING = 1 << 3
D2_PENDANT_HOLD, D2_EXTERNAL_HOLD, D2_COMMAND_HOLD = 1 << 1, 1 << 2, 1 << 3
D2_HOLDS = {D2_PENDANT_HOLD: "pendant hold", D2_EXTERNAL_HOLD: "external hold", D2_COMMAND_HOLD: "command hold"}
D2_ANY_HOLD = D2_PENDANT_HOLD | D2_EXTERNAL_HOLD | D2_COMMAND_HOLD
D2_ALARM, D2_ERROR, D2_SERVO_ON = 1 << 4, 1 << 5, 1 << 6


SIGNALS_PER_BYTE = 8


def io_byte(address: int) -> tuple[int, int]:
    """(the byte's first address, the bit) of a byte.bit I/O address: 27013 is bit 3 of 27010..27017."""
    if isinstance(address, bool) or not isinstance(address, int) or address < 0 or address % 10 >= SIGNALS_PER_BYTE:
        raise ValueError(f"I/O address {address!r}: a byte.bit address >= 0 whose last digit, the bit, is 0..7")
    return address - address % 10, address % 10


def describe_error(code: int) -> str:
    """'2070 servo power is off': every status code of a 90,000 reply in words."""
    if code in ERROR_MESSAGES:
        return f"{code} {ERROR_MESSAGES[code]}"
    for low, high, meaning in ERROR_RANGES:
        if low <= code <= high:
            return f"{code} {meaning}"
    return f"{code} unknown error code"


class JrcCommandError(RobotError):
    """The JRC answered a command with an error code."""

    def __init__(self, command: str, code: int) -> None:
        super().__init__(f"{command} refused by the JRC: {describe_error(code)}")
        self.command, self.code = command, code


class JrcNotReady(JrcCommandError, RobotNotReady):
    """Refused because the robot is held, in alarm or without servo power."""


class JrcOutOfRange(JrcCommandError, UnreachableTarget):
    """A move refused as out of range: the JRC cannot reach the target."""


def wire_pose(bMe: Matrix) -> list[float]:
    """X, Y, Z (mm), Rx, Ry, Rz (deg) of a flange pose, as MOVL and RPOSC carry it."""
    x, y, z, phi, theta, psi = pose_to_mm_deg(pose_from_matrix(bMe))
    return [x, y, z, psi, theta, phi]


def pose_from_wire(values: list[float]) -> Matrix:
    """bMe from X, Y, Z (mm), Rx, Ry, Rz (deg)."""
    x, y, z, rx, ry, rz = values
    return matrix_from_pose(pose_from_mm_deg(Pose6(x, y, z, rz, ry, rx)))


def format_pose(values: list[float]) -> str:
    """Millimetres to 3 decimals, degrees to 4."""
    return ",".join([f"{v:.3f}" for v in values[:3]] + [f"{v:.4f}" for v in values[3:]])


# RPOSC carries millimetres to 3 decimals but degrees only to 2 (0.01 deg, 0.17 mrad), while
# MOVL takes 4: how far a reading may lie from the target last sent and still be that target.
READBACK_TOLERANCE_MM = 0.0015
READBACK_TOLERANCE_DEG = 0.0055


# Where no JWAIT says whether a motion ended done or stopped (over Ethernet), the arm
# must stand at its target to count as done: within twice a reading's resolution, as an
# IMOV's target, worked out from a reading, may lie that far from where the JRC aimed.
ARRIVED_MM = 0.002
ARRIVED_DEG = 0.011


def reads_as(
    reading: list[float],
    sent: list[float],
    tolerance_mm: float = READBACK_TOLERANCE_MM,
    tolerance_deg: float = READBACK_TOLERANCE_DEG,
) -> bool:
    """Whether an RPOSC reading is the wire pose ``sent``, to the reading's resolution
    (or to the tolerances given)."""
    mm = np.abs(np.subtract(reading[:3], sent[:3]))
    deg = np.abs((np.subtract(reading[3:], sent[3:]) + 180.0) % 360.0 - 180.0)
    return bool(np.all(mm <= tolerance_mm) and np.all(deg <= tolerance_deg))


def host_link(line: JrcLineConfig, port: str | None = None) -> HostLink:
    """The link [jrc] names: its serial port (``port`` in its place, an emulator's
    pseudo-terminal, say), or its Ethernet server."""
    if line.transport is HostTransport.ETHERNET:
        if port is not None:
            raise ValueError(f"a serial port ({port}) given for a JRC on Ethernet at {line.address}")
        return EthernetLink(line)
    return SerialLink(line, port or line.port)


@dataclass(frozen=True)
class Reply:
    """A JRC's answer: the values of a data reply (none for a status reply)."""

    values: tuple[str, ...]


class JrcBackend:
    """A JRC-family controller on the link of the cell file's [jrc].

    ``port`` overrides the configured serial port (an emulator's pseudo-terminal, say);
    ``link`` replaces the link altogether. Every method is safe to call from several
    threads (the loop, an e-stop, the watchdog): commands go out one at a time.

    The cell clock (``cell_clock_s``) undoes an emulated JRC's speed-up (the line's
    ``time_scale``, 1 on a real JRC): the wall clock, with every motion of the arm (from
    the JRC taking the move to its answer that the move ended) and every dwell counted
    ``time_scale`` times, and every
    exchange at least as long as its bytes take on the link (at the line's baud rate: a
    pseudo-terminal carries them faster).
    """

    name = "jrc"

    def __init__(self, line: JrcLineConfig, port: str | None = None, link: HostLink | None = None) -> None:
        self.line = line
        self.link = link if link is not None else host_link(line, port)
        self.port = self.link.where
        self._cell_ahead_s = 0.0  # how far the cell clock runs ahead of the wall clock
        self._motion_from_s: float | None = None  # a motion's span not yet counted starts here (_count_cell_time)
        self._lock = threading.RLock()
        self._holds_waiting = 0  # holds from other threads (e-stop, watchdog) go before the next motion wait
        self._posture = 0  # the RPOSC "type": the arm configuration, sent back with MOVL
        self._sent: list[float] | None = None  # the wire pose of the last MOVL
        self._aim: list[float] | None = None  # the wire pose the last move aims at, when a motion wait checks it
        self.last_command = ""  # the text of the last command sent, for diagnostics

    # -- the link --------------------------------------------------------------------

    def open(self) -> None:
        """Open the link, without a command to the JRC yet; a lost one is opened anew
        (the device may be back, under the same name, as another one)."""
        with self._lock:
            self.link.open()

    def connect(self) -> None:
        """Open the link and ask the JRC for its status: fails clearly if nothing answers."""
        try:
            self.open()
            self.status()
        except RobotError:
            self.close()
            raise

    def close(self) -> None:
        with self._lock:
            self.link.close()

    @property
    def station(self) -> BscStation:
        """The serial link's BSC data link, for its counters (and for benchmarks)."""
        if not isinstance(self.link, SerialLink):
            raise RobotError(f"the JRC at {self.port} is reached over Ethernet: its link has no BSC station")
        return self.link.station

    def command(self, text: str, reply_wait_s: float | None = None) -> Reply:
        """Send one host command (text without CR) and return its reply.

        Raises JrcCommandError for an error code; LinkError, after holding the robot, when
        the link fails; CommandNotOffered for a command the link's server does not take.
        """
        name = text.split(" ", 1)[0]
        with self._lock:
            self.last_command = text
            started_s = time.monotonic()
            try:
                exchange = self.link.exchange(text, reply_wait_s or self.line.timer_b_s)
            except LinkLost as exc:  # the device itself is gone (unplugged, closed)
                unheld = "" if name == "HOLD" else "no hold could be sent: "  # a failed HOLD says so itself
                raise LinkError(f"{name} failed: {exc}; {unheld}the robot may still be moving") from exc
            except LinkError as exc:  # the link has ended the exchange
                raise LinkError(f"{name} failed: {exc}; {self._hold_after_failure(name)}") from exc
            self._count_cell_time(name, exchange, time.monotonic() - started_s)
        return self._parse(name, exchange.answer)

    def _hold_after_failure(self, failed: str) -> str:
        """Hold the robot after a failed command, if the link carries HOLD 1 at all."""
        if failed == "HOLD":
            return "the hold itself failed: the robot may still be moving"
        try:
            self._parse("HOLD", self.link.exchange("HOLD 1", self.line.timer_b_s).answer)
        except LinkLost as exc:  # the device went while the link was failing
            return f"HOLD 1 could not be sent ({exc}): the robot may still be moving"
        except RobotError as exc:
            return f"HOLD 1 failed too ({exc}): the robot may still be moving"
        return "the robot is held (release with HOLD 0)"

    def _parse(self, name: str, answer: Answer) -> Reply:
        if answer.kind is ReplyKind.DATA:
            return Reply(tuple(v.strip() for v in answer.text.split(",")))
        try:
            code = int(answer.text)
        except ValueError:
            raise RobotError(f"{name}: the JRC's status reply {answer.text!r} is not a code") from None
        if code == 0:
            return Reply(())
        error = JrcNotReady if code in NOT_READY_CODES else JrcOutOfRange if code == OUT_OF_RANGE else JrcCommandError
        raise error(name, code)

    # -- RobotBackend ----------------------------------------------------------------

    def status(self) -> RobotStatus:
        d1, d2 = self._integers("RSTATS", 2)
        holds = [name for bit, name in D2_HOLDS.items() if d2 & bit]
        alarm = bool(d2 & (D2_ALARM | D2_ERROR))
        detail = holds + ([self.alarm_text()] if alarm else [])
        return RobotStatus(
            servo_on=bool(d2 & D2_SERVO_ON),
            running=bool(d1 & D1_RUNNING),
            held=bool(holds),
            alarm=alarm,
            detail="; ".join(detail),
        )

    def alarm_text(self) -> str:
        """The JRC's current alarms (RALARM), e.g. '4315 COLLISION DETECT'."""
        values = self.command("RALARM").values
        pairs = [f"{code} {text}".strip() for code, text in zip(values[::2], values[1::2]) if code not in ("", "0")]
        return "; ".join(pairs) or "no alarm code"

    def read_pose(self) -> Matrix:
        numbers = self._reading()
        # A servo step of a fiftieth (section 5.3) turns by less than the reading's 0.01 deg:
        # aimed from the reading, the next step would aim at the same target again, and the
        # arm would stand still. Where the reading is the target last sent, that target is
        # where the JRC stands, to the 4 decimals it was sent with.
        if self._sent is not None and reads_as(numbers[:6], self._sent):
            return pose_from_wire(self._sent)
        return pose_from_wire(numbers[:6])

    def servo(self, on: bool) -> None:
        self.command(f"SVON {int(on)}")

    def hold(self, on: bool) -> None:
        self._holds_waiting += 1
        try:
            self.command(f"HOLD {int(on)}")
        finally:
            self._holds_waiting -= 1

    def reset_alarms(self) -> None:
        """RESET the alarms and CANCEL an error; servo power stays off."""
        self.command("RESET")
        self.command("CANCEL")

    def move_to(self, bMe_target: Matrix, speed_m_s: float) -> None:
        pose = format_pose(wire_pose(bMe_target))
        self._aim = None
        self.command(f"MOVL 0,{self._speed(speed_m_s)},0,{pose},{self._posture},0,0,0,0,0,0,0")
        self._sent = [float(v) for v in pose.split(",")]
        self._aim = self._sent

    def move_by(self, bMe_increment: Matrix, speed_m_s: float) -> None:
        self._aim = None
        # Without JWAIT the end of the move is checked against its target: worked out here.
        aim = None if self.link.offers("JWAIT") else wire_pose(apply_increment(self.read_pose(), bMe_increment))
        self.command(f"IMOV 0,{self._speed(speed_m_s)},0,{format_pose(wire_pose(bMe_increment))},{self._posture},0,0,0,0,0,0,0")
        self._aim = aim

    def move_timed(self, bMe_target: Matrix, duration_s: float) -> None:
        raise RobotError(
            "the JRC takes one position target at a time and is not real-time (section 5.3): "
            'servo it with [motion] mode = "position_steps"'
        )

    def wait_motion(self, timeout_s: float | None = None) -> bool:
        """Wait until the motion ends: True when it reached its target, False when it
        was stopped (hold, alarm, servo off). A motion still running after timeout_s is
        held and reported. Between two of the commands that wait, a hold from another
        thread gets through."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        wait = self._jwait if self.link.offers("JWAIT") else self._poll_status
        while True:
            while self._holds_waiting:  # a lock is not fair: let a hold from another thread through first
                time.sleep(0.001)
            ended = wait()
            if ended is not None:
                return ended
            if deadline is not None and time.monotonic() > deadline:
                self.hold(True)
                raise RobotError(f"the motion has not ended after {timeout_s:g} s: the robot is held")

    def _jwait(self) -> bool | None:
        """One JWAIT of jwait_slice_s: whether the motion ended done, None while it runs.

        JWAIT answers 0 when the motion is done, -1 when it was stopped (hold, alarm,
        servo off), and 2010 (robot operating) when its time ran out with the robot still
        moving (the last is inferred: check it on the real JRC).
        """
        slice_s = self.line.jwait_slice_s
        try:
            (done,) = self._integers(f"JWAIT {slice_s:g}", 1, reply_wait_s=self.line.timer_b_s + slice_s)
        except JrcCommandError as exc:
            if exc.code != ROBOT_OPERATING:
                raise
            return None
        return done == 0

    def _poll_status(self) -> bool | None:
        """One RSTATS, after status_poll_s of controller time while the motion runs: whether
        it ended done, None while it runs. Where no JWAIT is offered (the Ethernet server)
        nothing says whether the motion ended at its target or was stopped short (hold,
        alarm, servo off; a hold may even come and go between two reads): it was done
        when the arm stands at the target of the last move, one RPOSC more; without a
        move to compare with, when the robot stands ready for the next."""
        d1, d2 = self._integers("RSTATS", 2)
        if d1 & D1_RUNNING:
            time.sleep(self.line.status_poll_s / self.line.time_scale)
            return None
        if self._aim is not None:
            return reads_as(self._reading()[:6], self._aim, ARRIVED_MM, ARRIVED_DEG)
        return bool(d2 & D2_SERVO_ON) and not d2 & (D2_ALARM | D2_ERROR | D2_ANY_HOLD)

    # -- I/O (docs/robot-link.md, "I/O"; the command forms are inferred) -------------------

    def read_io(self, address: int, n_bytes: int = 1) -> list[int]:
        """IOREAD: ``n_bytes`` bytes of signals from the byte at ``address`` (bit 0), as 0..255 values."""
        values = self._integers(f"IOREAD {address},{n_bytes * SIGNALS_PER_BYTE}", n_bytes)
        if not all(0 <= v <= 0xFF for v in values):
            raise RobotError(f"IOREAD {address}: the JRC's reply {values!r} is not bytes")
        return values

    def write_io(self, address: int, values: list[int]) -> None:
        """IOWRITE: bytes of signals from the byte at ``address`` (network inputs only)."""
        data = ",".join(str(v) for v in values)
        self.command(f"IOWRITE {address},{len(values) * SIGNALS_PER_BYTE},{data}")

    def read_signal(self, address: int) -> bool:
        """One input or output signal at a byte.bit address."""
        byte, bit = io_byte(address)
        (value,) = self.read_io(byte)
        return bool(value >> bit & 1)

    def write_signal(self, address: int, on: bool) -> None:
        """Switch one network input (``write_signals``)."""
        self.write_signals({address: on})

    def write_signals(self, signals: Mapping[int, bool]) -> None:
        """Switch network inputs, {byte.bit address: on}: each byte they are in is read,
        changed in their bits only and written back, under the link's lock, so the byte's
        other signals keep their state."""
        by_byte: dict[int, list[tuple[int, bool]]] = {}
        for address, on in signals.items():
            byte, bit = io_byte(address)
            by_byte.setdefault(byte, []).append((bit, on))
        with self._lock:
            for byte, bits in by_byte.items():
                (value,) = self.read_io(byte)
                for bit, on in bits:
                    value = value | 1 << bit if on else value & ~(1 << bit)
                self.write_io(byte, [value])

    def clock_s(self) -> float:
        return time.monotonic()

    def cell_clock_s(self) -> float:
        return time.monotonic() + self._cell_ahead_s

    def dwell(self, seconds: float) -> None:
        if seconds > 0.0:
            time.sleep(seconds)
            self._cell_ahead_s += (self.line.time_scale - 1.0) * seconds

    def _count_cell_time(self, name: str, exchange: Exchange, wall_s: float) -> None:
        """What one exchange cost the cell beyond its wall time (class docstring).

        The arm's motion, which an emulator runs time_scale times faster, lasts from the
        JRC's answer to the MOVL or IMOV it has just set going to its answer that finds
        the motion ended (a JWAIT's, or an RSTATS's: ``exchange.answered_at_s``, as the
        host sees them): that span counts time_scale times, the link's exchanges outside
        it once. Scaling each waiting exchange whole instead would count its handshakes,
        and a loaded host's delays in them, time_scale times.
        """
        answer = exchange.answer
        sped_up_s = 0.0  # the part of this exchange's wall time the emulator ran time_scale times faster
        running = _still_moving(name, answer)
        if name in ("MOVL", "IMOV") and answer.kind is ReplyKind.STATUS and answer.text.isdigit() and int(answer.text) == 0:
            self._motion_from_s = exchange.answered_at_s
        elif running is not None and self._motion_from_s is not None:
            sped_up_s = max(exchange.answered_at_s - self._motion_from_s, 0.0)
            self._motion_from_s = exchange.answered_at_s if running else None
        cell_s = wall_s + (self.line.time_scale - 1.0) * sped_up_s
        # The exchange's bytes take their time on the link, during the arm's motion as on a real line.
        self._cell_ahead_s += max(self.link.wire_time_s(exchange.n_bytes), cell_s) - wall_s

    # -- helpers ---------------------------------------------------------------------

    def _reading(self) -> list[float]:
        """RPOSC's 8 numbers: X, Y, Z (mm), Rx, Ry, Rz (deg), type, tool; keeps the type
        (the arm's posture) for the next MOVL."""
        values = self.command("RPOSC 0,0").values
        try:
            numbers = [float(v) for v in values[:8]]
        except ValueError:
            raise RobotError(f"RPOSC: the JRC's reply {values!r} is not a pose") from None
        if len(numbers) < 8:
            raise RobotError(f"RPOSC: the JRC's reply {values!r} has fewer than 8 values")
        self._posture = int(numbers[6])
        return numbers

    def _integers(self, text: str, count: int, reply_wait_s: float | None = None) -> list[int]:
        values = self.command(text, reply_wait_s).values
        try:
            numbers = [int(v) for v in values[:count]]
        except ValueError:
            numbers = []
        if len(numbers) != count:
            raise RobotError(f"{text.split()[0]}: the JRC's reply {values!r} is not {count} integer(s)")
        return numbers

    @staticmethod
    def _speed(speed_m_s: float) -> str:
        """V in mm/s with 2 decimals; a speed the wire cannot carry is refused here."""
        mm_s = speed_m_s * 1000.0
        if not np.isfinite(mm_s) or round(mm_s, 2) <= 0.0:
            raise RobotError(f"speed {speed_m_s!r} m/s cannot be sent: V must be at least 0.01 mm/s")
        return f"{mm_s:.2f}"


def _still_moving(name: str, answer: Answer) -> bool | None:
    """What an answer says of the motion: True while it runs, False once it has ended,
    None when it says nothing of it. JWAIT's data answer comes when it has ended, its
    status (2010) while it runs; RSTATS's running bit says it directly."""
    if name == "JWAIT":
        return answer.kind is ReplyKind.STATUS
    if name == "RSTATS" and answer.kind is ReplyKind.DATA:
        first = answer.text.split(",", 1)[0].strip()
        return bool(int(first) & D1_RUNNING) if first.isdigit() else None
    return None
