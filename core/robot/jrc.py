"""The JRC over RS-232: a RobotBackend speaking the Yaskawa host commands.

Each method is one or two host commands (docs/robot-link.md): a ``01,000`` message sent
over the BSC link (core/robot/bsc.py) and the JRC's reply, ``90,000`` with a
status code or ``90,001`` with data. The commands used: RPOSC (pose), RSTATS (status),
RALARM (alarm text), RESET and CANCEL, SVON, HOLD, MOVL (linear move to a Cartesian
target), IMOV (incremental linear move), JWAIT (wait for the end of the motion),
IOREAD and IOWRITE (the I/O signals a vacuum cup is wired to; their forms are inferred).

Units and angles at the wire: X, Y, Z in mm, Rx, Ry, Rz in degrees, base coordinates.
Rx, Ry, Rz are taken as fixed-axis rotations about the base X, then Y, then Z, so
R = Rz(Rz) Ry(Ry) Rx(Rx): eq. 2-13 with phi = Rz, theta = Ry, psi = Rx
(core/geometry/spatial.py). RPOSC is asked for tool 0, taken to be the bare flange: bMe. Both
are the conventions of the Yaskawa manuals of the family and need one check on the real
controller (jog about one axis, compare the pendant's readout with ``read_pose``).

A command that fails after the link's retries ends the exchange with EOT (the ACK parity
starts again with the next one), holds the robot with HOLD 1 if the link still carries
it, and raises LinkError naming the command, the cause and whether the hold got
through. An error code in a reply raises JrcCommandError (RobotNotReady for holds,
alarms and servo off) with the code's meaning.
"""

from __future__ import annotations

import logging
import os
import termios
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import serial

from vservo.core.cell.config import JrcLineConfig
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.geometry.spatial import Matrix, Pose6, matrix_from_pose, pose_from_matrix, pose_from_mm_deg, pose_to_mm_deg
from vservo.core.robot.backend import RobotError, RobotNotReady, RobotStatus
from vservo.core.robot.bsc import BscStation, ByteChannel, LinkError, Message

log = logging.getLogger("vservo.jrc")

HOST_COMMAND = "01,000"
STATUS_REPLY = "90,000"
DATA_REPLY = "90,001"

# Status codes of a 90,000 reply, after the host-control manuals of the ERC/MRC/XRC family.
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


def reads_as(reading: list[float], sent: list[float]) -> bool:
    """Whether an RPOSC reading is the wire pose ``sent``, to the reading's resolution."""
    mm = np.abs(np.subtract(reading[:3], sent[:3]))
    deg = np.abs((np.subtract(reading[3:], sent[3:]) + 180.0) % 360.0 - 180.0)
    return bool(np.all(mm <= READBACK_TOLERANCE_MM) and np.all(deg <= READBACK_TOLERANCE_DEG))


def open_serial(line: JrcLineConfig, port: str) -> serial.SerialBase:
    """Open a serial port (a device or a pyserial URL) with the line settings, exclusively:
    a second program's bytes on the line would wreck the first one's exchanges, so a port
    another process holds is refused, naming that process."""
    try:
        return serial.serial_for_url(
            port,
            baudrate=line.baud,
            bytesize={7: serial.SEVENBITS, 8: serial.EIGHTBITS}[line.data_bits],
            parity={"even": serial.PARITY_EVEN, "odd": serial.PARITY_ODD, "none": serial.PARITY_NONE}[line.parity],
            stopbits={1: serial.STOPBITS_ONE, 2: serial.STOPBITS_TWO}[line.stop_bits],
            rtscts=line.rtscts,
            timeout=0.005,  # a short poll: the link keeps its own deadlines
            exclusive=True,
        )
    except serial.SerialException as exc:
        if "exclusively lock" in str(exc):
            raise RobotError(
                f"the serial port {port} is in use by {_holders(port)}: stop it first (one program drives a robot)"
            ) from None
        raise RobotError(f"cannot open the serial port {port}: {exc}") from exc
    except (ValueError, OSError, termios.error) as exc:
        raise RobotError(f"cannot open the serial port {port}: {exc}") from exc


def _holders(port: str) -> str:
    """Who holds ``port``'s exclusive lock, as 'process PID (command)', from the kernel's
    table of file locks (Linux); 'another process' where it cannot be seen."""
    try:
        device = os.stat(port)
        locks = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return "another process"
    wanted = f"{os.major(device.st_dev):02x}:{os.minor(device.st_dev):02x}:{device.st_ino}"
    found = []
    for line in locks:  # "1: FLOCK  ADVISORY  WRITE 4242 00:1a:5 0 EOF"
        fields = line.split()
        if len(fields) > 5 and fields[1] == "FLOCK" and fields[5] == wanted:
            try:
                command = Path(f"/proc/{fields[4]}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                command = "?"
            found.append(f"process {fields[4]} ({command.strip()[:80]})")
    return ", ".join(found) or "another process"


@dataclass(frozen=True)
class Reply:
    """A JRC's answer: the values of a data reply (none for a status reply)."""

    values: tuple[str, ...]


class JrcBackend:
    """A JRC on a serial port, with the line settings of the cell file's [jrc].

    ``port`` overrides the configured one (an emulator's pseudo-terminal, say). Every
    method is safe to call from several threads (the loop, an e-stop, the watchdog):
    commands go out one at a time.

    The cell clock (``cell_clock_s``) undoes an emulated JRC's speed-up (the line's
    ``time_scale``, 1 on a real JRC): the wall clock, with every motion of the arm (from
    the JRC taking the move to its answer that the move ended) and every dwell counted
    ``time_scale`` times, and every
    exchange at least as long as its bytes take at the line's baud rate (a
    pseudo-terminal carries them faster).
    """

    name = "jrc"

    def __init__(self, line: JrcLineConfig, port: str | None = None) -> None:
        self.line = line
        self.port = port or line.port
        self._cell_ahead_s = 0.0  # how far the cell clock runs ahead of the wall clock
        self._motion_from_s: float | None = None  # a motion's span not yet counted starts here (_count_cell_time)
        self._serial: serial.SerialBase | None = None
        self._station: BscStation | None = None
        self._lock = threading.RLock()
        self._holds_waiting = 0  # holds from other threads (e-stop, watchdog) go before the next JWAIT
        self._posture = 0  # the RPOSC "type": the arm configuration, sent back with MOVL
        self._sent: list[float] | None = None  # the wire pose of the last MOVL
        self.last_command = ""  # the text of the last command sent, for diagnostics
        self._lost: str | None = None  # why the port was given up, until it is opened again

    # -- the link --------------------------------------------------------------------

    def open(self) -> None:
        """Open the port, without a word to the JRC yet; a lost one is opened anew (the
        device may be back, under the same name, as another one)."""
        with self._lock:
            if self._serial is None:
                self._serial = open_serial(self.line, self.port)
                self._station = BscStation(ByteChannel(self._serial), self.line, yields=True)
                self._lost = None

    def connect(self) -> None:
        """Open the port and ask the JRC for its status: fails clearly if nothing answers."""
        self.open()
        try:
            self.status()
        except RobotError:
            self.close()
            raise

    def close(self) -> None:
        with self._lock:
            if self._serial is not None:
                self._serial.close()
            self._serial = self._station = None

    def _drop_lost_port(self, exc: Exception) -> str:
        """Close a port whose device is gone: its file descriptor never works again, and
        connect() opens the device anew. What to tell the caller."""
        self._lost = f"the serial port {self.port} is lost ({exc})"
        try:
            self._serial.close()
        except (OSError, serial.SerialException):
            pass  # closing a dead descriptor may fail too; it is dropped either way
        self._serial = self._station = None
        log.error("%s; the link is closed until it is connected again", self._lost)
        return self._lost

    @property
    def station(self) -> BscStation:
        """The data link, for its counters (and for benchmarks)."""
        if self._station is None:
            if self._lost is not None:
                raise LinkError(f"{self._lost}: reset (connect) to open it again")
            raise RobotError(f"the JRC on {self.port} is not connected: call connect() first")
        return self._station

    def command(self, text: str, reply_wait_s: float | None = None) -> Reply:
        """Send one host command (text without CR) and return its reply.

        Raises JrcCommandError for an error code; LinkError, after holding the robot, when
        the link fails after its retries.
        """
        name = text.split(" ", 1)[0]
        with self._lock:
            station = self.station
            self.last_command = text
            started_s, bytes_before = time.monotonic(), station.channel.bytes_in + station.channel.bytes_out
            try:
                station.channel.discard_input()
                station.send(Message(HOST_COMMAND, text + "\r"))
                reply = station.receive(reply_wait_s or self.line.timer_b_s, f"the reply to {name}")
                self._count_cell_time(
                    name,
                    reply,
                    time.monotonic() - started_s,
                    station.bid_at_s,
                    station.channel.bytes_in + station.channel.bytes_out - bytes_before,
                )
            except LinkError as exc:  # the station has ended the exchange with EOT
                raise LinkError(f"{name} failed: {exc}; {self._hold_after_failure(name)}") from exc
            except (OSError, serial.SerialException) as exc:  # the port itself is gone (unplugged, closed)
                unheld = "" if name == "HOLD" else "no hold could be sent: "  # a failed HOLD says so itself
                raise LinkError(f"{name} failed: {self._drop_lost_port(exc)}; {unheld}the robot may still be moving") from exc
        return self._parse(name, reply)

    def _hold_after_failure(self, failed: str) -> str:
        """Hold the robot after a failed command, if the link carries HOLD 1 at all."""
        if failed == "HOLD":
            return "the hold itself failed: the robot may still be moving"
        try:
            self._parse("HOLD", self._exchange("HOLD 1"))
        except RobotError as exc:
            return f"HOLD 1 failed too ({exc}): the robot may still be moving"
        except (OSError, serial.SerialException) as exc:  # the port went while the link was failing
            return f"HOLD 1 could not be sent ({self._drop_lost_port(exc)}): the robot may still be moving"
        return "the robot is held (release with HOLD 0)"

    def _exchange(self, text: str) -> Message:
        self.station.send(Message(HOST_COMMAND, text + "\r"))
        return self.station.receive(self.line.timer_b_s, f"the reply to {text}")

    def _parse(self, name: str, reply: Message) -> Reply:
        text = reply.text.rstrip("\r")
        if reply.header == STATUS_REPLY:
            try:
                code = int(text)
            except ValueError:
                raise RobotError(f"{name}: the JRC's status reply {text!r} is not a code") from None
            if code == 0:
                return Reply(())
            error = JrcNotReady if code in NOT_READY_CODES else JrcOutOfRange if code == OUT_OF_RANGE else JrcCommandError
            raise error(name, code)
        if reply.header == DATA_REPLY:
            return Reply(tuple(v.strip() for v in text.split(",")))
        raise RobotError(f"{name}: unexpected reply header {reply.header!r} (text {text!r})")

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
        values = self.command("RPOSC 0,0").values
        try:
            numbers = [float(v) for v in values[:8]]
        except ValueError:
            raise RobotError(f"RPOSC: the JRC's reply {values!r} is not a pose") from None
        if len(numbers) < 8:
            raise RobotError(f"RPOSC: the JRC's reply {values!r} has fewer than 8 values")
        self._posture = int(numbers[6])
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
        self.command(f"MOVL 0,{self._speed(speed_m_s)},0,{pose},{self._posture},0,0,0,0,0,0,0")
        self._sent = [float(v) for v in pose.split(",")]

    def move_by(self, bMe_increment: Matrix, speed_m_s: float) -> None:
        self.command(f"IMOV 0,{self._speed(speed_m_s)},0,{format_pose(wire_pose(bMe_increment))},{self._posture},0,0,0,0,0,0,0")

    def move_timed(self, bMe_target: Matrix, duration_s: float) -> None:
        raise RobotError(
            "the JRC takes one position target at a time and is not real-time (section 5.3): "
            'servo it with [motion] mode = "position_steps"'
        )

    def wait_motion(self, timeout_s: float | None = None) -> bool:
        """JWAITs of jwait_slice_s until the motion ends; between two, a hold can get through.

        JWAIT answers 0 when the motion is done, -1 when it was stopped (hold, alarm,
        servo off), and 2010 (robot operating) when its time ran out with the robot still
        moving (the last is inferred: check it on the real JRC). A motion still
        running after timeout_s is held and reported.
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        slice_s = self.line.jwait_slice_s
        while True:
            while self._holds_waiting:  # a lock is not fair: let a hold from another thread through first
                time.sleep(0.001)
            try:
                (done,) = self._integers(f"JWAIT {slice_s:g}", 1, reply_wait_s=self.line.timer_b_s + slice_s)
            except JrcCommandError as exc:
                if exc.code != ROBOT_OPERATING:
                    raise
                if deadline is not None and time.monotonic() > deadline:
                    self.hold(True)
                    raise RobotError(f"the motion has not ended after {timeout_s:g} s: the robot is held") from None
                continue
            return done == 0

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
        """Switch one network input: its byte is read, changed in that bit only and written
        back, under the link's lock, so the byte's other signals keep their state."""
        byte, bit = io_byte(address)
        with self._lock:
            (value,) = self.read_io(byte)
            self.write_io(byte, [value | 1 << bit if on else value & ~(1 << bit)])

    def clock_s(self) -> float:
        return time.monotonic()

    def cell_clock_s(self) -> float:
        return time.monotonic() + self._cell_ahead_s

    def dwell(self, seconds: float) -> None:
        if seconds > 0.0:
            time.sleep(seconds)
            self._cell_ahead_s += (self.line.time_scale - 1.0) * seconds

    def _count_cell_time(self, name: str, reply: Message, wall_s: float, bid_at_s: float, n_bytes: int) -> None:
        """What one exchange cost the cell beyond its wall time (class docstring).

        The arm's motion, which an emulator runs time_scale times faster, lasts from the
        JRC's bid to answer the MOVL or IMOV it has just set going to its bid to answer the
        JWAIT that finds the motion ended (``bid_at_s``, as the host sees them): that span
        counts time_scale times, the link's exchanges outside it once. Scaling each JWAIT's
        whole exchange instead would count its handshakes, and a loaded host's delays in
        them, time_scale times.
        """
        sped_up_s = 0.0  # the part of this exchange's wall time the emulator ran time_scale times faster
        if name in ("MOVL", "IMOV") and reply.header == STATUS_REPLY and reply.text.strip().isdigit() and int(reply.text) == 0:
            self._motion_from_s = bid_at_s
        elif name == "JWAIT" and self._motion_from_s is not None:
            sped_up_s = max(bid_at_s - self._motion_from_s, 0.0)
            # A data reply: the motion ended (done or stopped); a status: still running, go on from here.
            self._motion_from_s = None if reply.header == DATA_REPLY else bid_at_s
        cell_s = wall_s + (self.line.time_scale - 1.0) * sped_up_s
        # The exchange's bytes take their time at the baud rate, during the arm's motion as on a real line.
        self._cell_ahead_s += max(self.line.wire_time_s(n_bytes), cell_s) - wall_s

    # -- helpers ---------------------------------------------------------------------

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
