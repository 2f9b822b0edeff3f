"""The channel between the controller process and the app: authenticated, local, versioned.

Transport: ``multiprocessing.connection`` over TCP on the loopback interface. Both ends
prove they hold the shared key (an HMAC challenge each way) before a byte of a message
is read, so another program on the PC cannot drive the robot. The key is handed to the
controller process in the environment (never on a command line, where ``ps`` shows it).
Each connection is served by a thread of its own from the moment it is accepted, and the
challenge and the hello must be done within HANDSHAKE_DEADLINE_S: a program that connects
and says nothing holds only its own thread, for a few seconds, never the next app.

Messages are JSON objects with a ``type``; a camera frame is a ``frame`` object followed
by one binary message, the JPEG. The app's side:

    hello {version}                      -> welcome {version, state} | refused {error}
    command {id, name, args}             -> reply {id, ok, result | error}
                                            state {state}            (on every change)
                                            frame {meta} + JPEG      (the live image)

State and frames are sent newest-first: a slow reader skips to the latest one instead
of queueing the past, so one stalled browser never slows the controller.

A command the controller cannot carry out (unknown, arguments of the wrong shape or
type, numbers out of range) is answered with an error reply; the connection goes on.

Commands of one app are carried out in the order sent, one at a time, except ``estop``:
it is carried out the moment it arrives, even while a long move of that app is under
way. When the last app disconnects (closed, crashed, cable pulled) while a run or a jog
is moving the robot, the controller e-stops: the robot is held and the state says why.
"""

from __future__ import annotations

import json
import logging
import queue
import secrets
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing import AuthenticationError
from multiprocessing.connection import Client, Connection, Listener, answer_challenge, deliver_challenge
from typing import Any

import cv2
import numpy as np

from vservo.core.geometry.spatial import Matrix
from vservo.core.production.cell_controller import CellController, CommandRefused, ControllerState, FrameView
from vservo.core.production.jobs import JobError

log = logging.getLogger("vservo.channel")

PROTOCOL_VERSION = 1
KEY_ENVIRONMENT = "VSERVO_CONTROLLER_KEY"
LIVE_VIEW_PERIOD_S = 0.1  # the camera image while no run owns the camera
JPEG_QUALITY = 85
HANDSHAKE_DEADLINE_S = 5.0  # key challenge and hello; a loopback app needs milliseconds
ACCEPT_BACKLOG = 128  # connects waiting for the accept thread (the default, 1, drops a burst of them)
MAX_LIST_LIMIT = 10_000  # rows of a list command
MAX_HELLO_BYTES = 1024


class ChannelError(RuntimeError):
    """The other end is gone, refused us, or speaks another version."""


def new_key() -> bytes:
    return secrets.token_bytes(32)


def _vector(value: Any, length: int, name: str) -> Matrix:
    array = np.asarray(value, dtype=float)
    if array.shape != (length,) or not np.all(np.isfinite(array)):
        raise CommandRefused(f"{name} must be {length} finite numbers, got {value!r}")
    return array


def _pose(value: Any) -> Matrix:
    array = np.asarray(value, dtype=float)
    if array.shape != (4, 4) or not np.all(np.isfinite(array)):
        raise CommandRefused(f"a pose must be a 4 x 4 matrix of finite numbers, got {value!r}")
    return array


def _steps(value: Any) -> list[str]:
    """Commissioning's steps by name (the controller checks the names)."""
    if not isinstance(value, list) or not all(isinstance(step, str) for step in value):
        raise CommandRefused(f"steps must be a list of step names, got {value!r}")
    return value


def _jobs(controller: CellController) -> list[dict]:
    return [
        {"name": e.name, "saved_at": e.saved_at, "problem": e.problem, "shipped": e.shipped} for e in controller.store.list_jobs()
    ]


def _limit(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_LIST_LIMIT:
        raise CommandRefused(f"limit must be a whole number from 1 to {MAX_LIST_LIMIT}, got {value!r}")
    return value


def _runs(controller: CellController, limit: int = 50) -> list[dict]:
    return [r.__dict__ for r in controller.store.list_runs(limit)]


# Every command the app may send: name -> how to carry it out with its JSON arguments.
COMMANDS: dict[str, Callable[[CellController, dict], Any]] = {
    "jog": lambda c, a: c.jog(
        _vector(a.get("translation_m", [0, 0, 0]), 3, "translation_m"),
        _vector(a.get("rotation_rad", [0, 0, 0]), 3, "rotation_rad"),
        str(a.get("frame", "base")),
    ),
    "move_to": lambda c, a: c.move_to(_pose(a.get("bMe"))),
    "begin_teach": lambda c, a: c.begin_teach(a.get("template")),
    "capture_desired": lambda c, a: c.capture_desired().corners_px.tolist(),
    "capture_check_view": lambda c, a: c.capture_check_view().corners_px.tolist(),
    "set_start_pose": lambda c, a: c.set_start_pose(),
    "set_pick_pose": lambda c, a: c.set_pick_pose(),
    "set_place_pose": lambda c, a: c.set_place_pose(),
    "set_settings": lambda c, a: c.set_settings(
        float(a["threshold_px"]),
        float(a["gain"]),
        float(a["approach_m"]),
        None if a.get("placement_tolerance_mm") is None else float(a["placement_tolerance_mm"]),
    ),
    "save_job": lambda c, a: c.save_job(str(a.get("name", "")), str(a.get("description", ""))).name,
    "cancel_teach": lambda c, a: c.cancel_teach(),
    "present_part": lambda c, a: c.present_part(
        None if a.get("centre_mm") is None else _vector(a["centre_mm"], 2, "centre_mm"), float(a.get("turn_deg", 0.0))
    ),
    "suction": lambda c, a: c.suction(bool(a["on"])),
    "test_pick": lambda c, a: c.test_pick(),
    "start": lambda c, a: c.start(str(a.get("job", ""))),
    "commission": lambda c, a: str(c.commission(_steps(a["steps"]) if "steps" in a else None, a.get("out"))),
    "apply_commissioning": lambda c, a: str(c.apply_commissioning()),
    "estop": lambda c, a: c.estop(),
    "reset": lambda c, a: c.reset(),
    "list_jobs": lambda c, a: _jobs(c),
    "list_runs": lambda c, a: _runs(c, _limit(a.get("limit", 50))),
    "get_job": lambda c, a: c.store.load_job(str(a.get("name", ""))).as_dict(),
}
IMMEDIATE = "estop"  # never waits behind another command of the same app
APP_GONE = "e-stop: the app disconnected while the robot was moving"


def frame_message(view: FrameView) -> tuple[dict, bytes]:
    """The live image as JPEG and what was seen in it (pixels, for the app's overlays)."""
    ok, jpeg = cv2.imencode(".jpg", view.frame.image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ChannelError("a camera frame could not be encoded")

    def pixels(values: Matrix | None) -> list | None:
        return None if values is None else np.where(np.isfinite(values), values, -1.0).round(2).tolist()

    meta = {
        "index": view.frame.index,
        "time_s": view.frame.timestamp_s,
        "corners_px": pixels(view.corners_px),
        "laser_spot_px": pixels(view.laser_spot_px),
        "desired_corners_px": pixels(view.desired.corners_px if view.desired else None),
        "desired_laser_px": pixels(view.desired.laser_spot_px if view.desired else None),
        "trail_px": pixels(view.trail_px),
    }
    return meta, jpeg.tobytes()


class _Subscriber:
    """One connected app: its connection and the newest unsent state and frame."""

    def __init__(self, connection: Connection) -> None:
        self.connection = connection
        self.send_lock = threading.Lock()
        self.pending = threading.Condition()
        self.state: ControllerState | None = None
        self.frame: FrameView | None = None
        self.closed = False

    def offer(self, state: ControllerState | None = None, frame: FrameView | None = None) -> None:
        with self.pending:
            if state is not None:
                self.state = state
            if frame is not None:
                self.frame = frame
            self.pending.notify()

    def send(self, message: dict, payload: bytes | None = None) -> None:
        with self.send_lock:
            self.connection.send_bytes(json.dumps(message).encode())
            if payload is not None:
                self.connection.send_bytes(payload)

    def close(self) -> None:
        """Close the connection, never under a send of another thread.

        A send that had read the descriptor before a plain close would write into whatever
        connection the next accept gave that descriptor, in the middle of its key challenge.
        Shutting down first makes a send blocked on a peer that stopped reading fail at once.
        """
        _shut_down(self.connection)
        with self.send_lock:
            self.connection.close()


class ControllerServer:
    """Serves a CellController on 127.0.0.1 to apps that hold the key."""

    def __init__(self, controller: CellController, authkey: bytes, host: str = "127.0.0.1", port: int = 0) -> None:
        self.controller = controller
        # No authkey here: Listener.accept would run the key challenge on the accept thread,
        # where one silent client blocks every later one. Each client's thread runs it.
        self.listener = Listener((host, port), backlog=ACCEPT_BACKLOG)
        self._authkey = authkey
        self.address: tuple[str, int] = self.listener.address
        self.subscribers: list[_Subscriber] = []
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        controller.state_subscribers.append(self._on_state)
        controller.frame_subscribers.append(self._on_frame)
        self._threads = [
            threading.Thread(target=self._accept, name="channel-accept", daemon=True),
            threading.Thread(target=self._live_view, name="live-view", daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def _on_state(self, state: ControllerState) -> None:
        for subscriber in list(self.subscribers):
            subscriber.offer(state=state)

    def _on_frame(self, view: FrameView) -> None:
        for subscriber in list(self.subscribers):
            subscriber.offer(frame=view)

    def _accept(self) -> None:
        while not self._stopping.is_set():
            try:
                connection = self.listener.accept()
            except OSError as exc:  # the listener closed, or the client left before it was accepted
                if self._stopping.is_set():
                    return
                log.warning("accept failed: %r", exc)
                continue
            threading.Thread(target=self._serve, args=(connection,), name="channel-client", daemon=True).start()

    def _handshake(self, connection: Connection) -> bool:
        """The key challenge both ways and the hello, within HANDSHAKE_DEADLINE_S; False if refused.

        The deadline shuts the socket down, which ends whatever read the client keeps waiting.
        """
        deadline = threading.Timer(HANDSHAKE_DEADLINE_S, _shut_down, args=(connection,))
        deadline.start()
        try:
            deliver_challenge(connection, self._authkey)
            answer_challenge(connection, self._authkey)
            hello = json.loads(connection.recv_bytes(MAX_HELLO_BYTES))
            version = hello.get("version") if isinstance(hello, dict) else None
            if not isinstance(hello, dict) or hello.get("type") != "hello" or version != PROTOCOL_VERSION:
                connection.send_bytes(
                    json.dumps(
                        {
                            "type": "refused",
                            "error": f"this controller speaks channel version {PROTOCOL_VERSION}, the app sent {version!r}",
                        }
                    ).encode()
                )
                return False
            return True
        except (AuthenticationError, EOFError, OSError, ValueError) as exc:
            log.warning("channel: a client failed the handshake: %r", exc)
            return False
        finally:
            deadline.cancel()
            deadline.join()  # a deadline firing just now must not reach a descriptor closed and reused after us

    def _serve(self, connection: Connection) -> None:
        if not self._handshake(connection):
            connection.close()
            return
        subscriber = _Subscriber(connection)
        commands: queue.Queue[dict | None] = queue.Queue()
        try:
            subscriber.send({"type": "welcome", "version": PROTOCOL_VERSION, "state": self.controller.state.as_dict()})
            with self._lock:
                self.subscribers.append(subscriber)
            threading.Thread(target=self._push, args=(subscriber,), name="channel-push", daemon=True).start()
            threading.Thread(target=self._carry_out, args=(subscriber, commands), name="channel-commands", daemon=True).start()
            while True:
                message = json.loads(connection.recv_bytes())
                if not isinstance(message, dict) or message.get("type") != "command":
                    continue
                if message.get("name") == IMMEDIATE:
                    subscriber.send(self._execute(message))
                else:
                    commands.put(message)
        except (EOFError, OSError, TypeError, ValueError):
            pass  # the app went away (or sent garbage, or the server closed)
        finally:
            commands.put(None)
            with self._lock:
                if subscriber in self.subscribers:
                    self.subscribers.remove(subscriber)
                last_gone = not self.subscribers
            with subscriber.pending:
                subscriber.closed = True
                subscriber.pending.notify()
            subscriber.close()
            if last_gone and not self._stopping.is_set() and self.controller.in_motion:
                log.warning(APP_GONE)
                self.controller.estop(APP_GONE)

    def _carry_out(self, subscriber: _Subscriber, commands: queue.Queue) -> None:
        """One app's commands, in order; replies go back as each one ends."""
        while (message := commands.get()) is not None:
            reply = self._execute(message)
            try:
                subscriber.send(reply)
            except (OSError, EOFError):
                return

    def _execute(self, message: dict) -> dict:
        name, args = message.get("name"), message.get("args", {})
        reply = {"type": "reply", "id": message.get("id")}
        command = COMMANDS.get(name) if isinstance(name, str) else None
        if command is None:
            return {**reply, "ok": False, "error": f"unknown command {name!r}"}
        if not isinstance(args, dict):
            return {**reply, "ok": False, "error": f"{name}: the arguments must be an object of names, got {args!r}"}
        try:
            return {**reply, "ok": True, "result": command(self.controller, args)}
        except (CommandRefused, JobError, KeyError, TypeError, ValueError) as exc:
            return {**reply, "ok": False, "error": str(exc)}
        except Exception as exc:  # a command that fails otherwise is still answered: the app waits for it
            log.exception("command %s failed", name)
            return {**reply, "ok": False, "error": f"{name} failed: {exc!r}"}

    def _push(self, subscriber: _Subscriber) -> None:
        while True:
            with subscriber.pending:
                subscriber.pending.wait_for(lambda: subscriber.closed or subscriber.state or subscriber.frame)
                if subscriber.closed:
                    return
                state, frame = subscriber.state, subscriber.frame
                subscriber.state = subscriber.frame = None
            try:
                if state is not None:
                    subscriber.send({"type": "state", "state": state.as_dict()})
                if frame is not None:
                    meta, jpeg = frame_message(frame)
                    subscriber.send({"type": "frame", "meta": meta}, jpeg)
            except (OSError, EOFError):
                return

    def _live_view(self) -> None:
        while not self._stopping.wait(LIVE_VIEW_PERIOD_S):
            if self.subscribers and not self.controller.running:
                try:
                    self.controller.look()
                except CommandRefused:
                    pass  # a run took the camera meanwhile
                except Exception as exc:  # a camera that fails is shown as such, the server lives on
                    log.warning("live view: %s", exc)

    def close(self) -> None:
        self._stopping.set()
        self.listener.close()
        # Shut down, not close: each connection's own thread closes it as its read ends, and
        # two threads closing one Connection at once may close a descriptor reused meanwhile.
        for subscriber in list(self.subscribers):
            _shut_down(subscriber.connection)


def _shut_down(connection: Connection) -> None:
    """End the reads and writes under way on ``connection`` (a close alone wakes neither)."""
    try:
        with socket.fromfd(connection.fileno(), socket.AF_INET, socket.SOCK_STREAM) as duplicate:
            duplicate.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass  # already closed or shut down by the other end


@dataclass
class Reply:
    ok: bool
    result: Any = None
    error: str | None = None


class ControllerClient:
    """The app's end: commands with replies, and callbacks for state and frames."""

    def __init__(
        self,
        address: tuple[str, int],
        authkey: bytes,
        on_state: Callable[[dict], None] = lambda state: None,
        on_frame: Callable[[dict, bytes], None] = lambda meta, jpeg: None,
    ) -> None:
        try:
            self.connection = Client(address, authkey=authkey)
        except Exception as exc:  # ConnectionRefusedError, AuthenticationError
            raise ChannelError(f"cannot connect to the controller at {address[0]}:{address[1]}: {exc!r}") from exc
        self.on_state, self.on_frame = on_state, on_frame
        self.connection.send_bytes(json.dumps({"type": "hello", "version": PROTOCOL_VERSION}).encode())
        welcome = json.loads(self.connection.recv_bytes())
        if welcome.get("type") != "welcome":
            raise ChannelError(welcome.get("error", f"unexpected answer {welcome!r}"))
        self.state: dict = welcome["state"]
        self._replies: dict[int, Reply] = {}
        self._reply_ready = threading.Condition()
        self._next_id = 0
        self._send_lock = threading.Lock()
        self.connected = True
        self._reader = threading.Thread(target=self._read, name="controller-client", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        try:
            while True:
                message = json.loads(self.connection.recv_bytes())
                kind = message.get("type")
                if kind == "state":
                    self.state = message["state"]
                    self.on_state(self.state)
                elif kind == "frame":
                    self.on_frame(message["meta"], self.connection.recv_bytes())
                elif kind == "reply":
                    with self._reply_ready:
                        self._replies[message["id"]] = Reply(message["ok"], message.get("result"), message.get("error"))
                        self._reply_ready.notify_all()
        except (EOFError, OSError, TypeError):
            pass  # the controller went away, or close() shut the connection down
        finally:
            # The reader closes the connection, as it ends and not under a send: a descriptor
            # closed under a read or a write in progress may be reused by the next connection
            # of this process, which would then lose its bytes to us.
            with self._send_lock:
                self.connection.close()
            with self._reply_ready:
                self.connected = False
                self._reply_ready.notify_all()

    def call(self, command: str, timeout_s: float = 30.0, **args: Any) -> Reply:
        """Send ``command`` with its arguments (``save_job`` takes one called name) and wait for the reply."""
        with self._send_lock:
            self._next_id += 1
            request = self._next_id
            try:
                self.connection.send_bytes(json.dumps({"type": "command", "id": request, "name": command, "args": args}).encode())
            except OSError as exc:
                raise ChannelError(f"the controller is gone: {exc}") from exc
        with self._reply_ready:
            if not self._reply_ready.wait_for(lambda: request in self._replies or not self.connected, timeout_s):
                raise ChannelError(f"no reply to {command!r} within {timeout_s} s")
            if request not in self._replies:
                raise ChannelError("the controller is gone")
            return self._replies.pop(request)

    def close(self) -> None:
        # Shut the socket down: it wakes our reader blocked in recv, which closes it, and
        # tells the controller we are gone.
        _shut_down(self.connection)
        self._reader.join(5.0)
