"""Host commands over RS-232: each one a BSC message and the controller's reply message.

docs/robot-link.md, "The host protocol". A command travels as a ``01,000`` message over
the BSC data link (core/robot/bsc.py); the controller bids and replies with ``90,000``
and a status code or ``90,001`` and data. A device that goes away under the link (an
unplugged adapter) is closed at once: its descriptor never works again, and ``open``
opens the device anew, which may be back under the same name as another one.
"""

from __future__ import annotations

import logging
import os
import termios
from pathlib import Path

import serial

from vservo.core.cell.config import JrcLineConfig
from vservo.core.robot.backend import RobotError
from vservo.core.robot.bsc import BscStation, ByteChannel, Message
from vservo.core.robot.host_link import Answer, LinkLost, ReplyKind

log = logging.getLogger("vservo.serial_link")

HOST_COMMAND = "01,000"
STATUS_REPLY = "90,000"
DATA_REPLY = "90,001"
REPLY_KINDS = {STATUS_REPLY: ReplyKind.STATUS, DATA_REPLY: ReplyKind.DATA}
REPLY_HEADERS = {kind: header for header, kind in REPLY_KINDS.items()}


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


def command_message(text: str) -> Message:
    """A host command (its text without CR) as the BSC message that carries it."""
    return Message(HOST_COMMAND, text + "\r")


def answer_of(name: str, reply: Message) -> Answer:
    """The answer a controller's reply message to command ``name`` carries; RobotError
    for a header that is none."""
    kind = REPLY_KINDS.get(reply.header)
    if kind is None:
        raise RobotError(f"{name}: unexpected reply header {reply.header!r} (text {reply.text.rstrip(chr(13))!r})")
    return Answer(kind, reply.text.rstrip("\r"))


def reply_message(answer: Answer) -> Message:
    """The BSC message that carries an answer (the controller's side)."""
    return Message(REPLY_HEADERS[answer.kind], answer.text + "\r")


class SerialLink:
    """A HostLink on a serial port, with the line settings of the cell file's [jrc]."""

    def __init__(self, line: JrcLineConfig, port: str) -> None:
        self.line, self.port = line, port
        self._serial: serial.SerialBase | None = None
        self._station: BscStation | None = None
        self._lost: str | None = None  # why the port was given up, until it is opened again

    @property
    def where(self) -> str:
        return self.port

    def open(self) -> None:
        """Open the port, without a word to the controller yet."""
        if self._serial is None:
            self._serial = open_serial(self.line, self.port)
            self._station = BscStation(ByteChannel(self._serial), self.line, yields=True)
            self._lost = None

    def close(self) -> None:
        if self._serial is not None:
            self._serial.close()
        self._serial = self._station = None

    @property
    def station(self) -> BscStation:
        """The data link, for its counters (and for benchmarks)."""
        if self._station is None:
            if self._lost is not None:
                raise LinkLost(f"{self._lost}: reset (connect) to open it again")
            raise RobotError(f"the JRC on {self.port} is not connected: call connect() first")
        return self._station

    def exchange(self, text: str, reply_wait_s: float) -> Answer:
        name = text.split(" ", 1)[0]
        station = self.station
        try:
            station.channel.discard_input()  # late answers of an abandoned exchange
            station.send(command_message(text))
            reply = station.receive(reply_wait_s, f"the reply to {name}")
        except (OSError, serial.SerialException) as exc:  # the port itself is gone (unplugged, closed)
            raise LinkLost(self._drop_lost_port(exc)) from exc
        return answer_of(name, reply)

    def offers(self, command: str) -> bool:
        return True  # the JRC takes the whole command set over its serial line

    def _drop_lost_port(self, exc: Exception) -> str:
        """Close a port whose device is gone; what to tell the caller."""
        self._lost = f"the serial port {self.port} is lost ({exc})"
        try:
            if self._serial is not None:
                self._serial.close()
        except (OSError, serial.SerialException):
            pass  # closing a dead descriptor may fail too; it is dropped either way
        self._serial = self._station = None
        log.error("%s; the link is closed until it is connected again", self._lost)
        return self._lost
