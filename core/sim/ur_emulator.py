"""The UR controller emulator's network side: RTDE, the dashboard server and the script port.

The ports a real controller opens, on one address (a real arm has its own IP; ur-rtde's
RTDE client always connects to port 30004, so each emulator takes its own loopback address
127.x.y.z and the standard ports on it):

- RTDE (30004), protocol version 2 (Universal Robots' RTDE guide): a client negotiates
  the version ("V"), asks the controller's version ("v"), sets up an output recipe
  ("O": a frequency and variable names; the answer is a recipe id and each variable's
  type, NOT_FOUND for a name the controller does not have), starts ("S") and pauses
  ("P"); while started the controller sends a data package ("U": the recipe id, then
  each variable big-endian) every control period divided down to the recipe's frequency.
  Input recipes ("I") are answered, every variable NOT_FOUND: vservo writes no input.
- the dashboard server (29999): one text command a line, one answer a line.
- the secondary interface (30002): URScript programs, run by the controller as they arrive.
"""

from __future__ import annotations

import errno
import functools
import logging
import random
import socket
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass

from vservo.core.robot.ur_script import ur_pose
from vservo.core.sim.plant import SimulatedCell
from vservo.core.sim.ur_controller import RobotMode, RuntimeState, SafetyMode, ScriptError, UrController, UrLimits

log = logging.getLogger("vservo.ur_servers")

RTDE_PORT, DASHBOARD_PORT, SECONDARY_PORT = 30004, 29999, 30002
PROTOCOL_VERSION = 2
# The controller software the emulator reports: a CB3 (major 3) runs RTDE at 125 Hz, an e-Series (5) at 500 Hz.
CB3_VERSION, E_SERIES_VERSION = (3, 15, 8, 106339), (5, 11, 6, 108249)


def _vector(values) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


def _zeros6(controller: UrController) -> tuple[float, ...]:
    """What the emulator does not model (joint speeds, forces) reads as zero."""
    return (0.0,) * 6


# Each variable: its RTDE type and how to read it from the controller (the lock held).
def _variables() -> dict[str, tuple[str, Callable[[UrController], object]]]:
    zeros6 = _zeros6
    table: dict[str, tuple[str, Callable[[UrController], object]]] = {
        "timestamp": ("DOUBLE", lambda c: c.time_s),
        "actual_q": ("VECTOR6D", lambda c: _vector(c.q)),
        "target_q": ("VECTOR6D", lambda c: _vector(c.q)),
        "actual_qd": ("VECTOR6D", zeros6),
        "target_qd": ("VECTOR6D", zeros6),
        "actual_TCP_pose": ("VECTOR6D", lambda c: _vector(ur_pose(c.tcp_pose()))),
        "target_TCP_pose": ("VECTOR6D", lambda c: _vector(ur_pose(c.tcp_pose()))),
        "actual_TCP_speed": ("VECTOR6D", lambda c: _vector(c.tcp_speed)),
        "target_TCP_speed": ("VECTOR6D", lambda c: _vector(c.tcp_speed)),
        "actual_TCP_force": ("VECTOR6D", zeros6),
        "robot_mode": ("INT32", lambda c: int(c.state.robot_mode)),
        "safety_mode": ("INT32", lambda c: int(c.state.safety_mode)),
        "safety_status": ("INT32", lambda c: int(c.state.safety_mode)),
        "runtime_state": ("UINT32", lambda c: int(RuntimeState.PLAYING if c.running else RuntimeState.STOPPED)),
        "robot_status_bits": ("UINT32", lambda c: int(c.state.robot_mode is RobotMode.RUNNING) | int(c.running) << 1),
        "safety_status_bits": ("UINT32", _safety_bits),
        "actual_digital_input_bits": ("UINT64", lambda c: c.digital_input_bits()),
        "actual_digital_output_bits": ("UINT64", lambda c: c.digital_output_bits()),
        "speed_scaling": ("DOUBLE", lambda c: 1.0),
        "target_speed_fraction": ("DOUBLE", lambda c: 1.0),
    }
    for n in range(48):
        table[f"output_int_register_{n}"] = ("INT32", functools.partial(_register, n=n))
        table[f"output_double_register_{n}"] = ("DOUBLE", lambda c: 0.0)
    return table


def _register(controller: UrController, n: int) -> int:
    """An output integer register, as the programs wrote it (0 until then)."""
    return controller.state.registers.get(n, 0)


def _safety_bits(controller: UrController) -> int:
    """safety_status_bits: 0 normal, 2 protective stopped, 6 robot emergency stopped, 7 emergency stopped."""
    mode = controller.state.safety_mode
    if mode is SafetyMode.NORMAL:
        return 1
    if mode is SafetyMode.PROTECTIVE_STOP:
        return 1 << 2
    return 1 << 6 | 1 << 7


VARIABLES = _variables()
_FORMATS = {"DOUBLE": "d", "VECTOR6D": "6d", "INT32": "i", "UINT32": "I", "UINT64": "Q"}


@dataclass
class _Recipe:
    names: tuple[str, ...]
    fmt: struct.Struct
    every_ticks: int


class _RtdeSession:
    """One RTDE client: its handshake on its own thread, its data packages from the controller's ticks."""

    def __init__(self, connection: socket.socket, controller: UrController, version: tuple[int, int, int, int]) -> None:
        self.connection, self.controller, self.version = connection, controller, version
        self.recipe: _Recipe | None = None
        self.started = False
        self.ticks = 0
        self.closed = False
        self._send_lock = threading.Lock()

    def send(self, kind: str, payload: bytes) -> None:
        with self._send_lock:
            self.connection.sendall(struct.pack(">HB", 3 + len(payload), ord(kind)) + payload)

    def serve(self) -> None:
        buffer = b""
        try:
            while True:
                chunk = self.connection.recv(4096)
                if not chunk:
                    return
                buffer += chunk
                while len(buffer) >= 3:
                    size, kind = struct.unpack_from(">HB", buffer)
                    if size < 3 or len(buffer) < size:
                        break
                    self._on_package(chr(kind), buffer[3:size])
                    buffer = buffer[size:]
        except OSError:
            return
        finally:
            self.closed = True
            self.connection.close()

    def _on_package(self, kind: str, payload: bytes) -> None:
        if kind == "V":
            (version,) = struct.unpack(">H", payload[:2])
            self.send("V", struct.pack(">B", version == PROTOCOL_VERSION))
        elif kind == "v":
            self.send("v", struct.pack(">IIII", *self.version))
        elif kind == "O":
            (frequency,) = struct.unpack(">d", payload[:8])
            # (ur-rtde ends the list with a comma, as a real controller accepts)
            names = [name for name in payload[8:].decode("utf-8").split(",") if name]
            types = [VARIABLES[name][0] if name in VARIABLES else "NOT_FOUND" for name in names]
            known = "NOT_FOUND" not in types and 0.0 < frequency <= self.controller.frequency_hz
            if known:
                every = max(1, round(self.controller.frequency_hz / frequency))
                self.recipe = _Recipe(tuple(names), struct.Struct(">B" + "".join(_FORMATS[t] for t in types)), every)
            self.send("O", struct.pack(">B", 1 if known else 0) + ",".join(types).encode())
        elif kind == "I":
            names = [name for name in payload.decode("utf-8").split(",") if name]
            self.send("I", struct.pack(">B", 0) + ",".join("NOT_FOUND" for _ in names).encode())
        elif kind == "S":
            self.started = self.recipe is not None
            self.send("S", struct.pack(">B", self.started))
        elif kind == "P":
            self.started = False
            self.send("P", struct.pack(">B", 1))
        else:
            log.debug("RTDE: package %r ignored", kind)

    def on_tick(self) -> None:
        """After a control period (the controller's lock held): a data package when it is due."""
        recipe = self.recipe
        if not self.started or recipe is None or self.closed:
            return
        self.ticks += 1
        if self.ticks % recipe.every_ticks:
            return
        values: list[object] = [1]
        for name in recipe.names:
            value = VARIABLES[name][1](self.controller)
            values.extend(value if isinstance(value, tuple) else (value,))
        try:
            self.send("U", recipe.fmt.pack(*values))
        except OSError:
            self.closed = True


class _Listener:
    """A TCP port whose every connection is served by ``serve(connection)`` on its own thread."""

    def __init__(self, host: str, port: int, serve: Callable[[socket.socket], None], name: str) -> None:
        self.socket = socket.create_server((host, port))
        self.serve, self.name = serve, name
        self.thread = threading.Thread(target=self._accept, name=name, daemon=True)
        self.connections: list[socket.socket] = []

    def _accept(self) -> None:
        while True:
            try:
                connection, _ = self.socket.accept()
            except OSError:
                return
            connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.connections.append(connection)
            threading.Thread(target=self.serve, args=(connection,), name=f"{self.name}-client", daemon=True).start()

    def close(self) -> None:
        try:
            self.socket.shutdown(socket.SHUT_RDWR)  # wakes the accept (a close alone does not)
        except OSError:
            pass
        self.socket.close()
        for connection in self.connections:
            try:
                connection.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            connection.close()


class UrServers:
    """The controller's ports on ``host`` (``start`` binds them; ``close`` ends them)."""

    def __init__(self, controller: UrController, host: str | None = None) -> None:
        self.controller = controller
        self.host = host
        self.version = CB3_VERSION if controller.frequency_hz <= 125.0 else E_SERIES_VERSION
        self.sessions: list[_RtdeSession] = []
        self.listeners: list[_Listener] = []
        self.programs_refused: list[str] = []

    def start(self) -> str:
        """Bind the three ports (on a free loopback address unless ``host`` was given); the address."""
        for _ in range(50):
            host = self.host or f"127.{random.randint(1, 254)}.{random.randint(0, 255)}.{random.randint(1, 254)}"
            try:
                self.listeners = [
                    _Listener(host, RTDE_PORT, self._serve_rtde, "ur-rtde"),
                    _Listener(host, DASHBOARD_PORT, self._serve_dashboard, "ur-dashboard"),
                    _Listener(host, SECONDARY_PORT, self._serve_script, "ur-script"),
                ]
            except OSError as exc:
                for listener in self.listeners:
                    listener.close()
                self.listeners = []
                if exc.errno != errno.EADDRINUSE or self.host:
                    raise
                continue
            self.host = host
            self.controller.on_tick.append(self._tick)
            for listener in self.listeners:
                listener.thread.start()
            return host
        raise OSError("no free loopback address for the UR controller's ports")

    def close(self) -> None:
        for listener in self.listeners:
            listener.close()
        for listener in self.listeners:
            listener.thread.join()
        self.listeners = []

    def _tick(self) -> None:
        self.sessions = [session for session in self.sessions if not session.closed]
        for session in self.sessions:
            session.on_tick()

    def _serve_rtde(self, connection: socket.socket) -> None:
        session = _RtdeSession(connection, self.controller, self.version)
        with self.controller.lock:
            self.sessions.append(session)
        session.serve()

    def _serve_script(self, connection: socket.socket) -> None:
        """Programs arrive as text; one ends with a line 'end' (a 'def'), or is one line."""
        pending: list[str] = []
        for line in _lines(connection):
            if not pending and not line.strip():
                continue
            pending.append(line)
            if pending[0].lstrip().startswith("def ") and line.strip() != "end":
                continue
            text, pending = "\n".join(pending), []
            try:
                self.controller.run_program(text)
            except ScriptError as exc:
                log.warning("script port: %s", exc)
                self.programs_refused.append(str(exc))

    def _serve_dashboard(self, connection: socket.socket) -> None:
        try:
            connection.sendall(b"Connected: Universal Robots Dashboard Server\n")
            for line in _lines(connection):
                connection.sendall((self._dashboard(line.strip()) + "\n").encode())
        except OSError:
            return

    def _dashboard(self, command: str) -> str:
        controller = self.controller
        state = controller.state
        if command == "power on":
            controller.power(True)
            return "Powering on"
        if command == "brake release":
            return "Brake releasing"
        if command == "power off":
            controller.power(False)
            return "Powering off"
        if command == "stop":
            controller.stop_program()
            return "Stopped"
        if command == "pause":
            controller.stop_program("pause")
            return "Pausing program"
        if command == "unlock protective stop":
            unlocked = controller.unlock_protective_stop()
            return "Protective stop releasing" if unlocked else "Cannot unlock protective stop until 5s after occurrence."
        if command == "close safety popup":
            return "closing safety popup"
        if command == "robotmode":
            return f"Robotmode: {state.robot_mode.name}"
        if command == "safetystatus":
            return f"Safetystatus: {state.safety_mode.name}"
        if command == "safetymode":
            return f"Safetymode: {state.safety_mode.name}"
        if command == "running":
            return f"Program running: {str(controller.running).lower()}"
        if command == "programState":
            return "PLAYING <unnamed>" if controller.running else "STOPPED <unnamed>"
        if command == "is in remote control":
            return "true"
        if command == "PolyscopeVersion":
            return f"URSoftware {'.'.join(map(str, self.version[:3]))}.{self.version[3]} (vservo emulator)"
        return f"could not understand: '{command}'"


def _lines(connection: socket.socket):
    """The text lines a client sends, until it closes."""
    buffer = b""
    while True:
        try:
            chunk = connection.recv(4096)
        except OSError:
            return
        if not chunk:
            return
        buffer += chunk
        while b"\n" in buffer:
            line, buffer = buffer.split(b"\n", 1)
            yield line.decode("utf-8", "replace").rstrip("\r")


class UrEmulator:
    """A UR controller on the simulated cell behind its real ports: the controller ticking
    on its thread and its servers on a loopback address of their own."""

    def __init__(
        self,
        cell: SimulatedCell,
        frequency_hz: float = 125.0,
        limits: UrLimits = UrLimits(),
        vacuum=None,
        time_scale: float = 1.0,
    ) -> None:
        self.controller = UrController(cell, frequency_hz, limits, vacuum, time_scale)
        self.servers = UrServers(self.controller)
        self.lock = self.controller.lock
        self.host: str | None = None

    def start(self) -> str:
        """Bind the ports and start the controller; the address the host connects to."""
        self.host = self.servers.start()
        self.controller.start()
        return self.host

    def stop(self) -> None:
        self.servers.close()
        self.controller.stop()

    def advance(self) -> None:
        self.controller.advance()

    @property
    def motion(self) -> object | None:
        return self.controller.motion
