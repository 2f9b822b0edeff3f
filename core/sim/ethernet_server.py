"""The controller's side of the Ethernet server function, on a loopback TCP port.

The framing of core/robot/ethernet_link.py seen from the controller (docs/robot-link.md,
"Over Ethernet"): a start request answered ``OK: ... Keep-Alive:n.``, then for each
command its request line answered ``OK: NAME``, its operand line of the announced size,
and the answer: data with CR, ``0000`` CR LF, or ``ERROR: ...(code)`` CR LF. A request it
cannot read, or a command it does not offer (JWAIT), is answered ``NG: ...`` and the
connection closed, as the controller's server does. One connection is served at a time;
the next is accepted once the host has closed the last (a host that gave up on a silent
connection and connects again finds the server at its accept).

What each command does is the emulator's (``answer``), as behind the serial link. The
faults of the plan that a TCP connection can meet (jrc_emulator.ETHERNET_FAULT_KINDS):
``drop`` closes the connection after the command has been carried out, before its
answer; ``delay`` sends the answer 0.3 .. 1.5 timer A late; ``timeout`` never answers,
until the host closes the connection.
"""

from __future__ import annotations

import logging
import re
import select
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import NoReturn, Protocol

import numpy as np

from vservo.core.cell.config import JrcLineConfig
from vservo.core.errors import VservoError
from vservo.core.robot.ethernet_link import ACCEPTED, COMMAND_REQUEST, DONE, FAILED, NOT_OFFERED, REFUSED, UNLIMITED
from vservo.core.robot.host_link import Answer, ReplyKind

log = logging.getLogger("vservo.ethernet_server")

START_REQUEST = re.compile(r"CONNECT Robot_access(?: Keep-Alive:(-?\d+))?$")
SERVER_NAME = "DX Information Server( Ver. vservo emulator)"
POLL_S = 0.05  # how often a waiting server looks whether it is to stop
MAX_REQUEST_BYTES = 1024


class ServerFaults(Protocol):
    """What the server needs of the emulator's FaultInjector: a fault drawn per command,
    the count of those that struck, and the generator that times a delay."""

    injected: Counter[str]
    rng: np.random.Generator

    def draw(self) -> str | None: ...


class _Closed(VservoError):
    """The host closed the connection, or the server is stopping (caught by the server)."""


def framed(name: str, answer: Answer) -> bytes:
    """An answer as the server sends it: data ends with CR, a status with CR LF."""
    if answer.kind is ReplyKind.DATA:
        return (answer.text + "\r").encode("ascii")
    if int(answer.text) == 0:
        return f"{DONE}\r\n".encode("ascii")
    return f"{FAILED} {name} is not successful({answer.text}).\r\n".encode("ascii")


class EthernetServer:
    """Serves ``answer`` (host command text in, Answer out) on ``host``:``port`` (0: any free one).

    ``faults`` is the emulator's FaultInjector (its ``draw`` and ``injected``);
    ``connections`` counts the sessions started; ``count(name, answer, request_bytes,
    reply_bytes)`` hears of each command answered, before its answer goes out (the
    emulator's cell clock).
    """

    def __init__(
        self,
        answer: Callable[[str], Answer],
        line: JrcLineConfig,
        faults: ServerFaults,
        stop: threading.Event,
        host: str = "127.0.0.1",
        port: int = 0,
        count: Callable[[str, Answer, int, int], None] = lambda name, answer, request_bytes, reply_bytes: None,
    ) -> None:
        self.answer, self.line, self.faults, self._stop = answer, line, faults, stop
        self.count = count
        self.listener = socket.create_server((host, port))
        self.address: tuple[str, int] = self.listener.getsockname()[:2]
        self.connections = 0
        self._buffer = bytearray()

    def serve(self) -> None:
        """Accept and serve connections until ``stop`` is set; then close the listener."""
        try:
            while not self._stop.is_set():
                if not select.select([self.listener], [], [], POLL_S)[0]:
                    continue
                connection, _ = self.listener.accept()
                with connection:
                    connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    self._buffer.clear()
                    try:
                        self._session(connection)
                    except _Closed:
                        pass
                    except OSError as exc:  # the host reset the connection
                        log.info("connection lost: %s", exc)
        finally:
            self.listener.close()

    def _session(self, connection: socket.socket) -> None:
        start = START_REQUEST.match(self._line(connection))
        if start is None:
            connection.sendall(f"{REFUSED} HTTP Error Response\r\n".encode("ascii"))
            return
        granted = int(start.group(1)) if start.group(1) is not None else 1
        keep_alive = f" Keep-Alive:{granted}" if start.group(1) is not None else ""
        connection.sendall(f"{ACCEPTED} {SERVER_NAME}{keep_alive}.\r\n".encode("ascii"))
        self.connections += 1
        served = 0
        while granted == UNLIMITED or served < granted:
            if not self._command(connection):
                return
            served += 1

    def _command(self, connection: socket.socket) -> bool:
        """Serve one command; False when the connection is to close."""
        request = self._line(connection).split(" ")
        if len(request) != 3 or request[0] != COMMAND_REQUEST or not request[2].isdigit():
            words = " ".join(request)
            connection.sendall(f"{REFUSED} {words!r} is not {COMMAND_REQUEST} <command> <size>\r\n".encode("ascii", "replace"))
            return False
        name, size = request[1], int(request[2])
        request_bytes = len(" ".join(request)) + 2 + size  # the request line with CR LF, the operands
        if name in NOT_OFFERED or not name.isalpha():
            connection.sendall(f"{REFUSED} {name} is not a command of this server\r\n".encode("ascii"))
            return False
        fault = self.faults.draw()
        accepted = f"{ACCEPTED} {name}\r\n".encode("ascii")
        connection.sendall(accepted)
        operands = self._exactly(connection, size).decode("ascii", "replace").rstrip("\r") if size else ""
        if fault == "timeout":  # never answer: the host gives up and closes the connection
            self.faults.injected[fault] += 1
            self._until_closed(connection)
        answer = self.answer(f"{name} {operands}" if operands else name)
        reply = framed(name, answer)
        self.count(name, answer, request_bytes, len(accepted) + len(reply))
        if fault == "drop":
            self.faults.injected[fault] += 1
            return False  # carried out, and the connection closed before its answer
        if fault == "delay":
            self.faults.injected[fault] += 1
            time.sleep(self.faults.rng.uniform(0.3, 1.5) * self.line.timer_a_s)
        connection.sendall(reply)
        return True

    # -- reading -----------------------------------------------------------------------

    def _line(self, connection: socket.socket) -> str:
        """The next line up to CR (a CR LF's LF skipped: hosts end request lines either way)."""
        while True:
            self._skip_line_feeds(connection)
            end = self._buffer.find(b"\r")
            if end >= 0:
                line = bytes(self._buffer[:end]).decode("ascii", "replace")
                del self._buffer[: end + 1]
                return line
            if len(self._buffer) > MAX_REQUEST_BYTES:
                raise _Closed
            self._receive(connection)

    def _exactly(self, connection: socket.socket, size: int) -> bytes:
        """The operand line of ``size`` bytes, after the request line's LF if it has one."""
        self._skip_line_feeds(connection)
        while len(self._buffer) < size:
            self._receive(connection)
        data = bytes(self._buffer[:size])
        del self._buffer[:size]
        return data

    def _skip_line_feeds(self, connection: socket.socket) -> None:
        while not self._buffer:
            self._receive(connection)
        while self._buffer[:1] == b"\n":
            del self._buffer[0]
            if not self._buffer:
                self._receive(connection)

    def _until_closed(self, connection: socket.socket) -> NoReturn:
        while True:
            self._receive(connection)

    def _receive(self, connection: socket.socket) -> None:
        while not select.select([connection], [], [], POLL_S)[0]:
            if self._stop.is_set():
                raise _Closed
        chunk = connection.recv(4096)
        if not chunk:
            raise _Closed
        self._buffer.extend(chunk)
