"""Host commands over TCP: the Ethernet server function of DX100 and later controllers.

docs/robot-link.md, "Over Ethernet". The controller listens on TCP port 80. A session
opens with a start request and the server's acknowledgement; each host command then
takes up to three lines each way:

```
host: CONNECT Robot_access Keep-Alive:-1 CR LF     ctrl: OK: DX Information Server(...) Keep-Alive:-1. CR LF
host: HOSTCTRL_REQUEST RPOSC 4 CR LF               ctrl: OK: RPOSC CR LF
host: 0,0 CR                                       ctrl: 120.000,...,0,0 CR
```

The number after the command's name counts the bytes of its operands with their CR, 0
for none (RSTATS, RALARM): no operand line is sent then, and the answer follows the
acknowledgement at once. The answer is data ending with CR, ``0000`` CR LF when the
command was done and has nothing to say, or ``ERROR: ...(xxxx)`` CR LF carrying the
4-digit code of the refusal. ``NG: ...`` instead of ``OK:`` means the server refuses the
request itself, and closes the connection. ``Keep-Alive:-1`` asks for any number of
commands on one connection (n: n commands, none: one); the server's acknowledgement
says how many it grants, and the link connects again when they are used up.

The server does not offer every command of the serial link: JWAIT is not among those
vservo relies on over it (``offers``), and the backend reads the status (RSTATS) until
the motion has ended instead. A connection that fails (refused, closed by the
controller, silent past its timer) is closed and connected again for the next command,
so a HOLD after a failure goes out on a fresh connection.
"""

from __future__ import annotations

import re
import socket
import time

from vservo.core.cell.config import JrcLineConfig
from vservo.core.robot.backend import RobotError
from vservo.core.robot.host_link import Answer, CommandNotOffered, LinkError, ReplyKind

CR, LF = b"\r", b"\n"
START_REQUEST = "CONNECT Robot_access Keep-Alive:-1"
COMMAND_REQUEST = "HOSTCTRL_REQUEST"
ACCEPTED, REFUSED, FAILED = "OK:", "NG:", "ERROR:"
DONE = "0000"
UNLIMITED = -1
NOT_OFFERED = frozenset({"JWAIT"})  # commands of the serial link the Ethernet server does not take
ETHERNET_BIT_RATE = 100e6  # the controllers' LAN port, 100BASE-TX
MAX_LINE_BYTES = 4096
_KEEP_ALIVE = re.compile(r"Keep-Alive:\s*(-?\d+)")
_ERROR_CODE = re.compile(r"\((\d{4})\)")


def keep_alive_of(acknowledgement: str) -> int:
    """How many commands the server's start acknowledgement grants on the connection
    (UNLIMITED for -1; one when it names none)."""
    match = _KEEP_ALIVE.search(acknowledgement)
    return int(match.group(1)) if match else 1


def answer_of(name: str, line: str) -> Answer:
    """The answer an answer line carries: ``0000`` and ``ERROR: ...(xxxx)`` are statuses,
    anything else data. RobotError for an error answer without its code."""
    if line.startswith(FAILED):
        match = _ERROR_CODE.search(line)
        if match is None:
            raise RobotError(f"{name}: the controller's error answer {line!r} carries no 4-digit code")
        return Answer.status(int(match.group(1)))
    if line == DONE:
        return Answer(ReplyKind.STATUS, DONE)
    return Answer.data(line)


class EthernetLink:
    """A HostLink to a controller's Ethernet server at ``line.host``:``line.tcp_port``."""

    def __init__(self, line: JrcLineConfig) -> None:
        self.line = line
        self._opened = False  # between open() and close(): a failed connection is made again
        self._socket: socket.socket | None = None
        self._buffer = bytearray()
        self._commands_left = 0  # on this connection; UNLIMITED, or a count
        self.server = ""  # the server's start acknowledgement, once connected
        self.connections = 0  # made so far: a figure of how often the link failed

    @property
    def where(self) -> str:
        return self.line.address

    def open(self) -> None:
        """Connect and start a session now (a failure raises LinkError)."""
        self._opened = True
        if self._socket is None:
            self._connect()

    def close(self) -> None:
        self._opened = False
        self._drop()

    def offers(self, command: str) -> bool:
        return command not in NOT_OFFERED

    def exchange(self, text: str, reply_wait_s: float) -> Answer:
        if not self._opened:
            raise RobotError(f"the controller at {self.where} is not connected: call connect() first")
        name, _, operands = text.partition(" ")
        if not self.offers(name):
            raise CommandNotOffered(f"{name} is not offered by the Ethernet server at {self.where}")
        data = (operands + "\r").encode("ascii") if operands else b""
        if self._socket is None or self._commands_left == 0:
            self._drop()
            self._connect()
        self._send(f"{COMMAND_REQUEST} {name} {len(data)}\r\n".encode("ascii"), f"the request for {name}")
        acknowledgement = self._read_line(self.line.timer_a_s, f"the acknowledgement of {name}", "timer A")
        if acknowledgement.startswith(REFUSED):
            self._drop()  # the server closes the connection after NG
            raise CommandNotOffered(f"{name} refused by the Ethernet server at {self.where}: {acknowledgement}")
        if not acknowledgement.startswith(ACCEPTED):
            self._drop()
            raise LinkError(f"{name}: the server's acknowledgement {acknowledgement!r} is neither OK nor NG")
        if data:
            self._send(data, f"the operands of {name}")
        line = self._read_line(reply_wait_s, f"the answer to {name}", "the reply wait")
        if self._commands_left != UNLIMITED:
            self._commands_left -= 1
        return answer_of(name, line)

    # -- the connection ----------------------------------------------------------------

    def _connect(self) -> None:
        timer_a = self.line.timer_a_s
        try:
            self._socket = socket.create_connection((self.line.host, self.line.tcp_port), timeout=timer_a)
        except OSError as exc:
            raise LinkError(f"cannot connect to the Ethernet server at {self.where}: {exc}") from exc
        self._socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # short lines, each waited for
        self._buffer.clear()
        self.connections += 1
        self._send(f"{START_REQUEST}\r\n".encode("ascii"), "the start request")
        acknowledgement = self._read_line(timer_a, "the start acknowledgement", "timer A")
        if not acknowledgement.startswith(ACCEPTED):
            self._drop()
            raise LinkError(f"the Ethernet server at {self.where} refused the session: {acknowledgement}")
        self.server = acknowledgement
        self._commands_left = keep_alive_of(acknowledgement)

    def _drop(self) -> None:
        """Close the connection (a failed exchange leaves it in an unknown state)."""
        if self._socket is not None:
            self._socket.close()
        self._socket = None
        self._buffer.clear()

    def _send(self, data: bytes, what: str) -> None:
        try:
            if self._socket is None:
                raise ConnectionError("not connected")
            self._socket.sendall(data)
        except OSError as exc:
            self._drop()
            raise LinkError(f"{what} could not be sent to {self.where}: {exc}") from exc

    def _read_line(self, wait_s: float, what: str, timer: str) -> str:
        """The next line up to its CR, waiting up to wait_s (a CR LF's LF is skipped
        before the next line)."""
        deadline = time.monotonic() + wait_s
        while True:
            while self._buffer[:1] == LF:
                del self._buffer[0]
            end = self._buffer.find(CR)
            if end >= 0:
                line = bytes(self._buffer[:end]).decode("ascii", "replace")
                del self._buffer[: end + 1]
                return line
            if len(self._buffer) > MAX_LINE_BYTES:
                self._drop()
                raise LinkError(f"{what} from {self.where} has no line end after {MAX_LINE_BYTES} bytes")
            self._receive(deadline, what, f"{timer} ({wait_s:g} s)")

    def _receive(self, deadline: float, what: str, timer: str) -> None:
        left_s = deadline - time.monotonic()
        sock = self._socket
        try:
            if left_s <= 0.0 or sock is None:
                raise TimeoutError
            sock.settimeout(left_s)
            chunk = sock.recv(MAX_LINE_BYTES)
        except TimeoutError:
            self._drop()
            raise LinkError(f"{what} did not come from {self.where} within {timer}") from None
        except OSError as exc:
            self._drop()
            raise LinkError(f"the connection to {self.where} failed waiting for {what}: {exc}") from exc
        if not chunk:
            self._drop()
            raise LinkError(f"the controller at {self.where} closed the connection before {what}")
        self._buffer.extend(chunk)
