"""An emulator of the JRC's side of the host link, on the kinematic simulator.

It answers the host commands of docs/robot-link.md over a real serial device (a
pseudo-terminal it creates, or a given port) in BSC blocks, or, as a DX100 or later
controller's Ethernet server, on a loopback TCP port (core/sim/ethernet_server.py); what
a command does (``answer``) is the same behind either. Its own controller state: servo power,
the three holds (pendant, external, command), an alarm, and one motion at a time. The
robot is a SimulatedCell, the same plant the simulated camera looks at: a MOVL or IMOV
target goes through the JRC's nominal IK, and the arm travels there in joint
space at the commanded speed (or the JRC's rotation rate when the rotation takes
longer), reporting running until it arrives. A hold, servo off or an alarm stops the
motion where it is and discards the rest of it: the host decides how to go on.

I/O: given the cell's vacuum wiring (the cell file's [vacuum] with device = "jrc_io"),
it does what a real cell's ladder and pressure switch do: IOWRITE to the suction network input
switches the simulated cup, and IOREAD of the grip input answers whether the cup holds
the part. Given a PLC on its I/O ([line.plc] with transport = "jrc_io"), it has the I/O
panel a PLC is wired to: the PLC's signals drive the JRC's general inputs at the
[line.plc.inputs] addresses (``set_inputs``: what the PLC's program switches), which IOREAD
reports, and the network inputs at the [line.plc.outputs] addresses take IOWRITE, the
ladder copying each to the general output wired to the PLC (``io_panel`` shows them).
Other bytes read 0 and refuse IOWRITE (2110): this JRC has no other wiring.

Time: the plant's clock runs ``time_scale`` times faster than the wall clock, so tests
need not wait real seconds; JWAIT's time is JRC (plant) time. The plant is only
touched while a command is handled, when the host is waiting for the reply, so a host
thread may read the same SimulatedCell between commands without a lock.

Fault injection (FaultPlan): each host exchange meets a fault with probability ``rate``,
of a kind drawn uniformly from ``kinds``: a reply block with a corrupted BCC, a byte
dropped or an answer delayed (0.3 .. 1.5 timer A) in one of the emulator's next
transmissions, a block accepted without its ACK (missing ACK), a good block refused
with NAK, a silence that outlasts the host's retries (timeout), or an alarm or a
pendant hold in the middle of the next motion. Over TCP only the kinds a connection can
meet (ETHERNET_FAULT_KINDS): the connection dropped, the answer delayed or never sent.

Inferred behaviour (no public JRC document; check on the real JRC): JWAIT answers
0 when the motion ended, -1 when it was stopped, and status 2010 when its time ran out
with the robot still moving; IMOV takes MOVL's operands with increments; RALARM answers
``code,text`` pairs; a target out of reach is refused with 5200; IOREAD addr,n answers
n/8 bytes as decimal values, IOWRITE addr,n,d1.. takes them, n a multiple of 8 and addr
a byte's bit 0 (else 1013).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import serial

from vservo.core.cell.config import HostTransport, JrcLineConfig, PlcConfig, PlcTransport, VacuumDeviceConfig
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.geometry.spatial import Matrix, pose_error
from vservo.core.robot.backend import apply_increment
from vservo.core.robot.bsc import BscStation, ByteChannel, LinkError, Message, Port
from vservo.core.robot.host_link import Answer
from vservo.core.robot.jrc import (
    D1_RUNNING,
    D2_ALARM,
    D2_COMMAND_HOLD,
    D2_EXTERNAL_HOLD,
    D2_PENDANT_HOLD,
    D2_SERVO_ON,
    OUT_OF_RANGE,
    ROBOT_OPERATING,
    SIGNALS_PER_BYTE,
    io_byte,
    pose_from_wire,
    wire_pose,
)
from vservo.core.robot.serial_link import HOST_COMMAND, open_serial, reply_message
from vservo.core.sim.ethernet_server import EthernetServer
from vservo.core.sim.plant import ROTATION_SPEED_RAD_S, SimulatedCell
from vservo.core.sim.pseudo_terminal import PseudoTerminal

log = logging.getLogger("vservo.jrc_emulator")

FAULT_KINDS = ("bcc", "drop", "delay", "missing_ack", "nak", "timeout", "alarm", "hold")
# A TCP connection has no BCC, ACK or NAK to fault: over Ethernet a drop closes the
# connection, a delay holds the answer back, a timeout never answers.
ETHERNET_FAULT_KINDS = ("drop", "delay", "timeout", "alarm", "hold")
MOTION_FAULTS = ("alarm", "hold")
MAX_SPEED_MM_S = 1000.0
MAX_ROTATION_SPEED_DEG_S = 180.0
EMULATED_ALARM = (4315, "COLLISION DETECT (EMULATED)")
# RSTATS d1: play mode and command remote, as a cell under host control runs.
D1_PLAY, D1_REMOTE = 1 << 6, 1 << 7
MOTION_FIELDS = 17
NOT_ACCESSIBLE = 2110
IDLE_POLL_S = 0.05


@dataclass(frozen=True)
class FaultPlan:
    """Which faults to inject, how often, from which seed."""

    rate: float = 0.0
    seed: int = 0
    kinds: tuple[str, ...] = FAULT_KINDS
    pendant_hold_s: float = 1.0  # JRC time an injected pendant hold lasts

    def __post_init__(self) -> None:
        if not 0.0 <= self.rate <= 1.0:
            raise ValueError(f"fault rate {self.rate!r} must lie in [0, 1]")
        unknown = set(self.kinds) - set(FAULT_KINDS)
        if unknown or not self.kinds:
            raise ValueError(f"unknown fault kinds {sorted(unknown)}: choose from {', '.join(FAULT_KINDS)}")


class FaultInjector:
    """The emulator's faults (a bsc.LinkFaults), one per host exchange at most.

    ``injected`` counts the faults that really happened, by kind (a drop aimed past the
    end of a short exchange, say, does not count).
    """

    def __init__(self, plan: FaultPlan, line: JrcLineConfig) -> None:
        self.plan, self.line = plan, line
        self.rng = np.random.default_rng(plan.seed)
        self.injected: Counter[str] = Counter()
        self._armed: str | None = None
        self._countdown = 0  # outgoing transmissions before a drop or delay hits
        self.pending_motion_fault: str | None = None
        self._forced: list[str] = []
        self.kinds_here: tuple[str, ...] = FAULT_KINDS  # the kinds the link being served can meet

    def serve_over(self, kinds: tuple[str, ...]) -> None:
        """Serve a link that can meet only ``kinds``: a plan drawing others is refused."""
        foreign = sorted(set(self.plan.kinds) - set(kinds)) if self.plan.rate > 0.0 else []
        if foreign:
            raise ValueError(f"fault kinds {foreign} cannot happen on this link: choose from {', '.join(kinds)}")
        self.kinds_here = kinds

    def inject(self, kind: str) -> None:
        """Force a fault of ``kind`` on the next exchange (an alarm or hold: on the next motion)."""
        if kind not in self.kinds_here:
            raise ValueError(f"unknown fault kind {kind!r} on this link: choose from {', '.join(self.kinds_here)}")
        self._forced.append(kind)

    def draw(self) -> str | None:
        """This exchange's fault, if any; an alarm or a hold is set aside for the next motion."""
        if self._forced:
            kind = self._forced.pop(0)
        elif self.rng.random() < self.plan.rate:
            kind = str(self.rng.choice(self.plan.kinds))
        else:
            return None
        if kind in MOTION_FAULTS:
            self.pending_motion_fault = kind  # strikes the next motion, whichever exchange carries it
            return None
        return kind

    def begin_exchange(self) -> str | None:
        """Draw a BSC exchange's fault; returns "timeout" when the bid is to be ignored."""
        self._armed = None
        kind = self.draw()
        if kind == "timeout":
            self.injected[kind] += 1
            return kind
        if kind is not None:
            self._armed = kind
            self._countdown = int(self.rng.integers(0, 4))  # ACK0, ACK1, the reply's ENQ, the reply block
        return None

    def outgoing(self, data: bytes, what: str) -> bytes | None:
        kind = self._armed
        if kind == "bcc" and what == "block":
            self._fired(kind)
            return data[:-1] + bytes(((data[-1] + 1) & 0xFF,))
        if kind in ("drop", "delay") and what in ("ack", "enq", "block"):
            if self._countdown > 0:
                self._countdown -= 1
                return data
            self._fired(kind)
            if kind == "drop":
                cut = int(self.rng.integers(0, len(data)))
                return data[:cut] + data[cut + 1 :]
            time.sleep(self.rng.uniform(0.3, 1.5) * self.line.timer_a_s)
        return data

    def on_block(self) -> str | None:
        kind = self._armed
        if kind in ("nak", "missing_ack"):
            self._fired(kind)
            return "nak" if kind == "nak" else "no_ack"
        return None

    def take_motion_fault(self) -> str | None:
        """The alarm or pendant hold waiting for a motion; it counts once it strikes."""
        kind, self.pending_motion_fault = self.pending_motion_fault, None
        return kind

    def _fired(self, kind: str) -> None:
        self.injected[kind] += 1
        self._armed = None


@dataclass(frozen=True)
class IoPanel:
    """The lines a PLC on the JRC's I/O is wired to, by byte.bit address: the JRC's inputs its
    signals drive, and the outputs the ladder copies from the network inputs the host wrote."""

    inputs: dict[int, bool]
    outputs: dict[int, bool]


@dataclass
class Motion:
    """One linear move under way, in joint space, in JRC (plant) time."""

    q_start: Matrix
    q_end: Matrix
    duration_s: float
    elapsed_s: float = 0.0
    stop_at_s: float | None = None  # an injected alarm or pendant hold strikes here
    stop_kind: str | None = None

    def joints_at(self, t_s: float) -> Matrix:
        s = min(t_s / self.duration_s, 1.0) if self.duration_s > 0.0 else 1.0
        return self.q_start + s * (self.q_end - self.q_start)


class JrcEmulator:
    """The JRC side of the link, on ``cell``; start it on a pseudo-terminal or a port.

    ``executed`` lists the motion commands the JRC accepted, in order: the proof
    that no move was lost or carried out twice. ``vacuum``: the cell file's [vacuum] device; when
    it is "jrc_io", the cup is wired to the I/O at its addresses.
    """

    def __init__(
        self,
        cell: SimulatedCell,
        line: JrcLineConfig,
        faults: FaultPlan = FaultPlan(),
        time_scale: float = 1.0,
        pace: bool = False,
        vacuum: VacuumDeviceConfig | None = None,
        plc: PlcConfig | None = None,
    ) -> None:
        if not time_scale > 0.0:
            raise ValueError(f"time scale {time_scale!r} must be positive")
        self.cell, self.line, self.time_scale, self.pace = cell, line, time_scale, pace
        # (suction_output, grip_input) when the cup is wired to the I/O
        self.vacuum_io = vacuum.jrc_io() if vacuum is not None and vacuum.device == "jrc_io" else None
        self.network_inputs: dict[int, int] = {}  # byte address -> the value the host wrote
        # The PLC's wiring: the inputs its signals drive, the network inputs the ladder copies out to it.
        wired = plc is not None and plc.transport is PlcTransport.JRC_IO
        self.plc_inputs = plc.inputs.addresses() if plc is not None and wired else ()
        self.plc_outputs = plc.outputs.addresses() if plc is not None and wired else ()
        self.panel: dict[int, int] = {}  # byte address -> the PLC's signals on those general inputs
        self.faults = FaultInjector(faults, line)
        self.executed: list[str] = []
        self.exchanges = 0
        self.servo_on = False
        self.command_hold = False
        self.external_hold = False
        self.pendant_hold_until_s: float | None = None
        self.alarm: tuple[int, str] | None = None
        self.motion: Motion | None = None
        self.last_motion_stopped = False
        self.device: str | None = None  # the serial device served, or None
        self.address: tuple[str, int] | None = None  # the TCP address served, or None
        self.station: BscStation | None = None
        self.ethernet: EthernetServer | None = None
        self._pty: PseudoTerminal | None = None
        self._serial: serial.SerialBase | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_real_s = time.monotonic()
        # The plant is shared: the serving thread moves it, and a virtual cell's camera
        # and fixture read or change it from theirs. Whoever touches it holds this lock.
        self.lock = threading.RLock()

    # -- running -----------------------------------------------------------------------

    def start_on_pty(self) -> str:
        """Create a raw pseudo-terminal, serve on it, and return the device the host opens."""
        self._pty = PseudoTerminal()
        self.device = self._pty.device
        self._start(self._pty.port)
        return self.device

    def start_on_tcp(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Serve the Ethernet server's framing on a TCP port (0: any free one), and return
        the (host, port) the host connects to."""
        self.faults.serve_over(ETHERNET_FAULT_KINDS)
        self.ethernet = EthernetServer(self.answer, self.line, self.faults, self._stop, host, port)
        self.address = self.ethernet.address
        self._run(self.ethernet.serve, "jrc-emulator-tcp")
        return self.address

    def start_for(self, line: JrcLineConfig) -> JrcLineConfig:
        """Serve the link ``line`` names, a new pseudo-terminal for a serial line or a
        loopback TCP port for an Ethernet server, and return ``line`` pointed at it."""
        if line.transport is HostTransport.ETHERNET:
            return line.on_ethernet(*self.start_on_tcp())
        return replace(line, port=self.start_on_pty())

    def start_on_port(self, device: str) -> None:
        """Serve on a real serial port, with the line settings of ``line``."""
        self._serial = open_serial(self.line, device)
        self.device = device
        self._start(self._serial)

    def _start(self, port: Port) -> None:
        channel = ByteChannel(port, self.line.wire_time_s(1) if self.pace else None)
        station = self.station = BscStation(channel, self.line, yields=False, faults=self.faults)
        self._run(lambda: self._serve(station), "jrc-emulator")

    def _run(self, serve: Callable[[], None], name: str) -> None:
        self._last_real_s = time.monotonic()
        self._stop.clear()
        self._thread = threading.Thread(target=serve, name=name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop serving and close the device; safe to call twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._pty is not None:
            self._pty.close()
            self._pty = None
        if self._serial is not None:
            self._serial.close()
            self._serial = None

    def __enter__(self) -> JrcEmulator:
        self.start_on_pty()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _serve(self, station: BscStation) -> None:
        ignoring = 0
        while not self._stop.is_set():
            if not station.wait_for_bid(time.monotonic() + IDLE_POLL_S):
                continue
            if ignoring:
                ignoring -= 1
                continue
            if self.faults.begin_exchange() == "timeout":
                ignoring = self.line.retry_1  # this bid and every repeat the host will try
                continue
            try:
                request = station.receive_text()
            except LinkError as exc:
                log.info("host message lost: %s", exc)
                continue
            reply = self.handle(request)
            try:
                station.send(reply)
            except LinkError as exc:
                log.info("reply lost: %s", exc)

    # -- the JRC -----------------------------------------------------------------------

    def handle(self, request: Message) -> Message:
        """One host command in a BSC message in, its reply message out."""
        if request.header != HOST_COMMAND:
            return reply_message(Answer.status(1010))
        return reply_message(self.answer(request.text.rstrip("\r")))

    def answer(self, text: str) -> Answer:
        """One host command (its text, no line end) in, its answer out, whatever the link."""
        with self.lock:
            self.exchanges += 1
            return self._answer(text)

    def advance(self) -> None:
        """Bring the plant up to now: a camera looking at it between commands sees the arm
        where the motion under way has taken it."""
        with self.lock:
            self._advance()

    def _answer(self, text: str) -> Answer:
        self._advance()
        name, _, operands = text.partition(" ")
        fields = [f.strip() for f in operands.split(",")] if operands.strip() else []
        handler = getattr(self, f"_cmd_{name.lower()}", None)
        if handler is None:
            return Answer.status(1010)
        try:
            return handler(fields)
        except _Refused as refusal:
            return Answer.status(refusal.code)

    def _cmd_rstats(self, fields: list[str]) -> Answer:
        _count(fields, 0, 0)
        d1 = D1_PLAY | D1_REMOTE | (D1_RUNNING if self.motion is not None else 0)
        d2 = (
            (D2_PENDANT_HOLD if self.pendant_hold_until_s is not None else 0)
            | (D2_EXTERNAL_HOLD if self.external_hold else 0)
            | (D2_COMMAND_HOLD if self.command_hold else 0)
            | (D2_ALARM if self.alarm is not None else 0)
            | (D2_SERVO_ON if self.servo_on else 0)
        )
        return Answer.data(f"{d1},{d2}")

    def _cmd_ralarm(self, fields: list[str]) -> Answer:
        _count(fields, 0, 0)
        code, text = self.alarm or (0, "")
        return Answer.data(f"{code},{text}")

    def _cmd_reset(self, fields: list[str]) -> Answer:
        _count(fields, 0, 0)
        self.alarm = None
        return Answer.status(0)

    def _cmd_cancel(self, fields: list[str]) -> Answer:
        _count(fields, 0, 0)
        return Answer.status(0)

    def _cmd_rposc(self, fields: list[str]) -> Answer:
        _count(fields, 2, 2)
        frame, external = _integers(fields)
        if frame != 0 or external not in (0, 1):
            raise _Refused(1013)  # base coordinates only
        x, y, z, rx, ry, rz = wire_pose(self.cell.jrc_arm.fk(self.cell.state.q))
        values = f"{x:.3f},{y:.3f},{z:.3f},{rx:.2f},{ry:.2f},{rz:.2f},0,0" + (",0" * 6 if external else "")
        return Answer.data(values)

    def _cmd_svon(self, fields: list[str]) -> Answer:
        (on,) = _switch(fields)
        if on and self.alarm is not None:
            raise _Refused(2060)
        self.servo_on = on
        if not on:
            self._stop_motion()
        return Answer.status(0)

    def _cmd_hold(self, fields: list[str]) -> Answer:
        (on,) = _switch(fields)
        self.command_hold = on
        if on:
            self._stop_motion()
        return Answer.status(0)

    def _cmd_movl(self, fields: list[str]) -> Answer:
        return self._start_motion("MOVL", fields, lambda bMe, target: target)

    def _cmd_imov(self, fields: list[str]) -> Answer:
        return self._start_motion("IMOV", fields, apply_increment)

    def _cmd_jwait(self, fields: list[str]) -> Answer:
        _count(fields, 1, 1)
        try:
            wait_s = float(fields[0])
        except ValueError:
            raise _Refused(5170) from None
        waited_s = 0.0
        while self.motion is not None and (wait_s < 0 or waited_s < wait_s) and not self._stop.is_set():
            # Wake at the motion's computed end (or the wait's), not on polling ticks: a
            # tick's overshoot would delay the reply by up to a tick of wall time, which
            # is time_scale ticks of JRC time.
            motion = self.motion
            left_s = (motion.duration_s if motion.stop_at_s is None else motion.stop_at_s) - motion.elapsed_s
            if wait_s >= 0:
                left_s = min(left_s, wait_s - waited_s)
            self.lock.release()  # handle() holds it once: while the JRC waits, a camera may look
            try:
                self._stop.wait(max(left_s, 0.0) / self.time_scale)
            finally:
                self.lock.acquire()
            waited_s += self._advance()
        if self.motion is not None:
            return Answer.status(ROBOT_OPERATING)
        return Answer.data("-1" if self.last_motion_stopped else "0")

    # -- I/O ---------------------------------------------------------------------------

    def _cmd_ioread(self, fields: list[str]) -> Answer:
        _count(fields, 2, 2)
        address, count = _integers(fields)
        n_bytes = _io_bytes(address, count)
        return Answer.data(",".join(str(self._io_value(address + 10 * i)) for i in range(n_bytes)))

    def _cmd_iowrite(self, fields: list[str]) -> Answer:
        _count(fields, 3, 2 + 64)
        address, count, *values = _integers(fields)
        if len(values) != _io_bytes(address, count) or not all(0 <= v <= 0xFF for v in values):
            raise _Refused(1013)
        writable = {io_byte(a)[0] for a in self.plc_outputs}
        if self.vacuum_io is not None:
            writable.add(io_byte(self.vacuum_io[0])[0])
        if len(values) != 1 or address not in writable:
            raise _Refused(NOT_ACCESSIBLE)
        self.network_inputs[address] = values[0]
        if self.vacuum_io is not None and address == io_byte(self.vacuum_io[0])[0]:
            # The ladder line: the suction network input drives the valve's output.
            _, bit = io_byte(self.vacuum_io[0])
            self.cell.vacuum(bool(values[0] >> bit & 1))
        return Answer.status(0)

    def set_inputs(self, signals: dict[int, bool]) -> None:
        """The PLC switches its signals on the JRC's general inputs, {byte.bit address: on};
        a ValueError for an address no PLC signal is wired to."""
        unwired = sorted(set(signals) - set(self.plc_inputs))
        if unwired:
            raise ValueError(f"input {unwired[0]} is not wired to the PLC: its inputs are {', '.join(map(str, self.plc_inputs))}")
        with self.lock:
            for address, on in signals.items():
                byte, bit = io_byte(address)
                value = self.panel.get(byte, 0)
                self.panel[byte] = value | 1 << bit if on else value & ~(1 << bit)

    def io_panel(self) -> IoPanel:
        """The PLC's lines now."""

        def bit_of(values: dict[int, int], address: int) -> bool:
            byte, bit = io_byte(address)
            return bool(values.get(byte, 0) >> bit & 1)

        with self.lock:
            return IoPanel(
                inputs={a: bit_of(self.panel, a) for a in self.plc_inputs},
                outputs={a: bit_of(self.network_inputs, a) for a in self.plc_outputs},
            )

    def _io_value(self, byte: int) -> int:
        value = self.network_inputs.get(byte, 0) | self.panel.get(byte, 0)
        if self.vacuum_io is not None:
            grip_byte, bit = io_byte(self.vacuum_io[1])
            if byte == grip_byte:  # the pressure switch
                value = value | 1 << bit if self.cell.holding_part else value & ~(1 << bit)
        return value

    # -- motion ------------------------------------------------------------------------

    def _start_motion(self, name: str, fields: list[str], target_of) -> Answer:
        _count(fields, MOTION_FIELDS, MOTION_FIELDS)
        try:
            numbers = [float(f) for f in fields]
        except ValueError:
            raise _Refused(5170) from None
        speed_kind, speed, frame = numbers[:3]
        if speed_kind not in (0, 1) or frame != 0 or not speed > 0:
            raise _Refused(1013)
        if speed > (MAX_SPEED_MM_S if speed_kind == 0 else MAX_ROTATION_SPEED_DEG_S):
            raise _Refused(OUT_OF_RANGE)
        self._refuse_unless_ready()
        bMe = self.cell.jrc_arm.fk(self.cell.state.q)
        target = target_of(bMe, pose_from_wire(numbers[3:9]))
        try:
            q_end = self.cell.jrc_ik(target)
        except UnreachableTarget:
            raise _Refused(OUT_OF_RANGE) from None
        translation, rotation = pose_error(bMe, target)
        if speed_kind == 0:
            duration = max(translation * 1000.0 / speed, rotation / ROTATION_SPEED_RAD_S)
        else:
            duration = max(np.degrees(rotation) / speed, translation * 1000.0 / MAX_SPEED_MM_S)
        # The arm stood still while the JRC worked the target out: the motion starts now,
        # not when the command arrived (else it would end that much early on the host's clock).
        self._advance()
        motion = Motion(self.cell.state.q.copy(), q_end, duration)
        fault = self.faults.take_motion_fault()
        if fault is not None:
            motion.stop_at_s, motion.stop_kind = float(self.faults.rng.uniform(0.2, 0.8)) * duration, fault
        self.motion, self.last_motion_stopped = motion, False
        self.executed.append(f"{name} {','.join(fields)}")
        return Answer.status(0)

    def _refuse_unless_ready(self) -> None:
        if self.alarm is not None:
            raise _Refused(2060)
        if self.pendant_hold_until_s is not None:
            raise _Refused(2020)
        if self.external_hold:
            raise _Refused(2040)
        if self.command_hold:
            raise _Refused(2050)
        if not self.servo_on:
            raise _Refused(2070)
        if self.motion is not None:
            raise _Refused(ROBOT_OPERATING)

    def _advance(self) -> float:
        """Bring the plant up to now (JRC time); returns the JRC time passed."""
        now = time.monotonic()
        dt = (now - self._last_real_s) * self.time_scale
        self._last_real_s = now
        cell, motion = self.cell, self.motion
        if motion is not None:
            end = motion.duration_s if motion.stop_at_s is None else motion.stop_at_s
            step = min(dt, end - motion.elapsed_s)
            motion.elapsed_s += step
            if motion.elapsed_s < end:
                cell.move_joints(motion.joints_at(motion.elapsed_s), step, settle=False)
            elif motion.stop_kind is None:
                cell.move_joints(motion.q_end, step, settle=True)
                self.motion = None
            else:
                cell.move_joints(motion.joints_at(motion.elapsed_s), step, settle=False)
                self._strike(motion.stop_kind)
            cell.pass_time(dt - step)
        else:
            cell.pass_time(dt)
        if self.pendant_hold_until_s is not None and cell.state.time_s >= self.pendant_hold_until_s:
            self.pendant_hold_until_s = None
        return dt

    def _strike(self, kind: str) -> None:
        """An injected alarm (servo power drops) or pendant hold in the middle of a motion."""
        self.faults.injected[kind] += 1
        if kind == "alarm":
            self.alarm = EMULATED_ALARM
            self.servo_on = False
        else:
            self.pendant_hold_until_s = self.cell.state.time_s + self.faults.plan.pendant_hold_s
        self._stop_motion()

    def _stop_motion(self) -> None:
        if self.motion is not None:
            self.motion = None
            self.last_motion_stopped = True


class _Refused(Exception):
    def __init__(self, code: int) -> None:
        self.code = code


def _count(fields: list[str], low: int, high: int) -> None:
    if len(fields) > high:
        raise _Refused(1011)
    if len(fields) < low:
        raise _Refused(1012)


def _integers(fields: list[str]) -> list[int]:
    try:
        return [int(f) for f in fields]
    except ValueError:
        raise _Refused(5170) from None


def _io_bytes(address: int, count: int) -> int:
    """How many bytes an I/O command's address and signal count span; 1013 unless whole bytes."""
    if address < 0 or address % 10 != 0 or count <= 0 or count % SIGNALS_PER_BYTE:
        raise _Refused(1013)
    return count // SIGNALS_PER_BYTE


def _switch(fields: list[str]) -> list[bool]:
    _count(fields, 1, 1)
    (value,) = _integers(fields)
    if value not in (0, 1):
        raise _Refused(1013)
    return [bool(value)]
