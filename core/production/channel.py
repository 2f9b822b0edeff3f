"""The controller's end of the channel: authenticated, local, versioned (core/production/protocol/).

The messages, commands and states are the protocol's (core/production/protocol/): this
module serves a CellController to the apps that hold the key. Each connection is served
by a thread of its own from the moment it is accepted, and the challenge and the hello
must be done within HANDSHAKE_DEADLINE_S: a program that connects and says nothing holds
only its own thread, for a few seconds, never the next app.

State and frames are sent newest-first: a slow reader skips to the latest one instead
of queueing the past, so one stalled browser never slows the controller.

A command is read into its dataclass, which checks its fields, and carried out by the
controller's method of its name. The reply says ok with the result, or one line:
a VservoError (a refusal: unknown, out of range, not possible now) says its own message;
anything else is a bug, answered "internal error" with its traceback in this process's log.
The connection goes on either way.

Commands of one app are carried out in the order sent, one at a time, except ``estop``:
it is carried out the moment it arrives, even while a long move of that app is under
way. When the last app disconnects (closed, crashed, cable pulled) while a run it started
or a jog is moving the robot, the controller e-stops: the robot is held and the state says
why. A run the line started (PLC, OPC UA) goes on: its own client watches it.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
from multiprocessing import AuthenticationError
from multiprocessing.connection import Connection, Listener, answer_challenge, deliver_challenge

import cv2
import numpy as np

from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix
from vservo.core.production.cell_controller import CellController, FrameView
from vservo.core.production.protocol.catalogue import Refusal, refusal_kind
from vservo.core.production.protocol.client import (
    MAX_HELLO_BYTES,
    PROTOCOL_VERSION,
    ChannelError,
    encode,
    frame_message,
    refused_message,
    shut_down,
    state_message,
    welcome_message,
)
from vservo.core.production.protocol.commands import CommandRefused, Estop, command_from
from vservo.core.production.protocol.state import ControllerState, FrameMeta

log = logging.getLogger("vservo.channel")

LIVE_VIEW_PERIOD_S = 0.1  # the camera image while no run owns the camera
JPEG_QUALITY = 85
HANDSHAKE_DEADLINE_S = 5.0  # key challenge and hello; a loopback app needs milliseconds
ACCEPT_BACKLOG = 128  # connects waiting for the accept thread (the default, 1, drops a burst of them)
APP_GONE = "e-stop: the app disconnected while the robot was moving"
INTERNAL_ERROR = "internal error (its traceback is in the controller's log)"


def frame_payload(view: FrameView) -> tuple[FrameMeta, bytes]:
    """The live image as JPEG and what was seen in it (pixels, for the app's overlays)."""
    ok, jpeg = cv2.imencode(".jpg", view.frame.image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ChannelError("a camera frame could not be encoded")

    def pixels(values: Matrix | None) -> Matrix | None:
        return None if values is None else np.round(np.asarray(values, float), 2)

    meta = FrameMeta(
        index=view.frame.index,
        time_s=view.frame.timestamp_s,
        corners_px=pixels(view.corners_px),
        laser_spot_px=pixels(view.laser_spot_px),
        desired_corners_px=pixels(view.desired.corners_px if view.desired else None),
        desired_laser_px=pixels(view.desired.laser_spot_px if view.desired else None),
        trail_px=pixels(view.trail_px),
    )
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

    def send(self, message: dict | bytes, payload: bytes | None = None) -> None:
        with self.send_lock:
            self.connection.send_bytes(message if isinstance(message, bytes) else encode(message))
            if payload is not None:
                self.connection.send_bytes(payload)

    def close(self) -> None:
        """Close the connection, never under a send of another thread.

        A send that had read the descriptor before a plain close would write into whatever
        connection the next accept gave that descriptor, in the middle of its key challenge.
        Shutting down first makes a send blocked on a peer that stopped reading fail at once.
        """
        shut_down(self.connection)
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
        deadline = threading.Timer(HANDSHAKE_DEADLINE_S, shut_down, args=(connection,))
        deadline.start()
        try:
            deliver_challenge(connection, self._authkey)
            answer_challenge(connection, self._authkey)
            hello = json.loads(connection.recv_bytes(MAX_HELLO_BYTES))
            version = hello.get("version") if isinstance(hello, dict) else None
            if not isinstance(hello, dict) or hello.get("type") != "hello" or version != PROTOCOL_VERSION:
                connection.send_bytes(encode(refused_message(version)))
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
            subscriber.send(welcome_message(self.controller.state))
            with self._lock:
                self.subscribers.append(subscriber)
            threading.Thread(target=self._push, args=(subscriber,), name="channel-push", daemon=True).start()
            threading.Thread(target=self._carry_out, args=(subscriber, commands), name="channel-commands", daemon=True).start()
            while True:
                message = json.loads(connection.recv_bytes())
                if not isinstance(message, dict) or message.get("type") != "command":
                    continue
                if message.get("name") == Estop.command_name:
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
            if last_gone and not self._stopping.is_set() and self.controller.moved_by_apps:
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

    def _execute(self, message: dict) -> bytes:
        """Carry out one command message; its reply, encoded (never raises: the app waits for it)."""
        name = message.get("name")
        reply = {"type": "reply", "id": message.get("id")}
        try:
            command = command_from(name, message.get("args", {}))
            return encode({**reply, "ok": True, "result": command.reply_value(command.carry_out(self.controller))})
        except VservoError as exc:  # the kind (protocol/catalogue.py) is what the page explains
            advice = getattr(exc, "advice", "")
            return encode({**reply, "ok": False, "error": str(exc), "kind": refusal_kind(exc).value, "advice": advice})
        except Exception:
            log.exception("command %s: internal error", name)
            return encode({**reply, "ok": False, "error": f"{name}: {INTERNAL_ERROR}", "kind": Refusal.INTERNAL.value})

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
                    subscriber.send(state_message(state))
                if frame is not None:
                    meta, jpeg = frame_payload(frame)
                    subscriber.send(frame_message(meta), jpeg)
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
            shut_down(subscriber.connection)
