"""The channel's messages, and the app's end of it: ``ControllerClient``.

Transport: ``multiprocessing.connection`` over TCP on the loopback interface. Both ends
prove they hold the shared key (an HMAC challenge each way) before a byte of a message
is read, so another program on the PC cannot drive the robot. The key is handed to the
controller process in the environment (never on a command line, where ``ps`` shows it).

Messages are JSON objects with a ``type``; a camera frame is a ``frame`` object followed
by one binary message, the JPEG. The app's side:

    hello {version}                      -> welcome {version, state} | refused {error}
    command {id, name, args}             -> reply {id, ok, result | error, kind, advice}
                                            state {state}            (on every change)
                                            frame {meta} + JPEG      (the live image)

``state`` is a ControllerState, ``meta`` a FrameMeta, ``name`` and ``args`` a command
(core/production/protocol/commands.py), each as ``codec.to_json`` writes it; the client
decodes each once, on its reader thread, and hands its callbacks the typed values.
A reply's ``error`` is one line for the operator: the controller's refusal, or
"internal error" when the command failed otherwise (its traceback is in the controller's log);
its ``kind`` the refusal's kind the page explains (protocol/catalogue.py), its ``advice``
the operator's words for this case, if any.
"""

from __future__ import annotations

import json
import logging
import secrets
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Client, Connection
from typing import Any

from vservo.core.errors import VservoError
from vservo.core.production.protocol.catalogue import Refusal, explain
from vservo.core.production.protocol.codec import from_json, to_json
from vservo.core.production.protocol.commands import Command, command_message
from vservo.core.production.protocol.state import ControllerState, FrameMeta

log = logging.getLogger("vservo.channel")

PROTOCOL_VERSION = 2  # 2: typed commands and states (1: a state of loose keys)
KEY_ENVIRONMENT = "VSERVO_CONTROLLER_KEY"
MAX_HELLO_BYTES = 1024


class ChannelError(VservoError, RuntimeError):
    """The other end is gone, refused us, or speaks another version."""


def new_key() -> bytes:
    return secrets.token_bytes(32)


def encode(message: dict[str, Any]) -> bytes:
    return json.dumps(message).encode()


def hello_message() -> dict[str, Any]:
    return {"type": "hello", "version": PROTOCOL_VERSION}


def welcome_message(state: ControllerState) -> dict[str, Any]:
    return {"type": "welcome", "version": PROTOCOL_VERSION, "state": to_json(state)}


def refused_message(version: object) -> dict[str, Any]:
    return {"type": "refused", "error": f"this controller speaks channel version {PROTOCOL_VERSION}, the app sent {version!r}"}


def state_message(state: ControllerState) -> dict[str, Any]:
    return {"type": "state", "state": to_json(state)}


def frame_message(meta: FrameMeta) -> dict[str, Any]:
    """The frame's meta; the JPEG follows as a binary message of its own."""
    return {"type": "frame", "meta": to_json(meta)}


@dataclass(frozen=True)
class Reply:
    """A command's answer: ok with its result (typed, ``Command.result_type``), or the one-line
    error (the engineer's), its kind and the operator's advice for this case."""

    ok: bool
    result: Any = None
    error: str | None = None
    kind: Refusal | None = None
    advice: str = ""

    def operator_words(self) -> str:
        """A refusal as the operator reads it: the catalogue's sentence, this case's advice, the action."""
        explanation = explain(self.kind or Refusal.INTERNAL)
        advice = f" {self.advice}" if self.advice else ""
        return f"{explanation.sentence}{advice} {explanation.action.value}"


def shut_down(connection: Connection) -> None:
    """End the reads and writes under way on ``connection`` (a close alone wakes neither)."""
    try:
        with socket.fromfd(connection.fileno(), socket.AF_INET, socket.SOCK_STREAM) as duplicate:
            duplicate.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass  # already closed or shut down by the other end


class ControllerClient:
    """The app's end: commands with replies, and callbacks for state and frames (on the reader thread)."""

    def __init__(
        self,
        address: tuple[str, int],
        authkey: bytes,
        on_state: Callable[[ControllerState], None] = lambda state: None,
        on_frame: Callable[[FrameMeta, bytes], None] = lambda meta, jpeg: None,
        on_closed: Callable[[], None] = lambda: None,
    ) -> None:
        try:
            self.connection = Client(address, authkey=authkey)
        except Exception as exc:  # ConnectionRefusedError, AuthenticationError
            raise ChannelError(f"cannot connect to the controller at {address[0]}:{address[1]}: {exc!r}") from exc
        self.on_state, self.on_frame, self.on_closed = on_state, on_frame, on_closed
        self.connection.send_bytes(encode(hello_message()))
        welcome = json.loads(self.connection.recv_bytes())
        if welcome.get("type") != "welcome":
            raise ChannelError(welcome.get("error", f"unexpected answer {welcome!r}"))
        self.state: ControllerState = from_json(ControllerState, welcome["state"], "state")
        self._replies: dict[int, dict[str, Any]] = {}  # reply messages by request, until their caller takes them
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
                    self.state = from_json(ControllerState, message["state"], "state")
                    self.on_state(self.state)
                elif kind == "frame":
                    self.on_frame(from_json(FrameMeta, message["meta"], "frame"), self.connection.recv_bytes())
                elif kind == "reply":
                    with self._reply_ready:
                        self._replies[message["id"]] = message
                        self._reply_ready.notify_all()
        except VservoError as exc:  # a message this app cannot read: the channel is of no use
            log.error("the controller sent what this app cannot read: %s", exc)
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
            self.on_closed()  # at once: the app tells its pages the controller is gone

    def call(self, command: Command, timeout_s: float = 30.0) -> Reply:
        """Send ``command`` and wait for its reply, its result typed."""
        with self._send_lock:
            self._next_id += 1
            request = self._next_id
            try:
                self.connection.send_bytes(encode({"type": "command", "id": request, **command_message(command)}))
            except OSError as exc:
                raise ChannelError(f"the controller is gone: {exc}") from exc
        message = self._wait_reply(request, command.command_name, timeout_s)
        if not message.get("ok"):
            kind = message.get("kind")
            advice = message.get("advice")
            return Reply(
                False,
                error=str(message.get("error")),
                kind=Refusal(kind) if isinstance(kind, str) and kind in tuple(Refusal) else Refusal.INTERNAL,
                advice=advice if isinstance(advice, str) else "",
            )
        try:
            return Reply(True, command.result(message.get("result")))
        except VservoError as exc:
            raise ChannelError(f"the controller's reply to {command.command_name} cannot be read: {exc}") from exc

    def _wait_reply(self, request: int, what: str, timeout_s: float = 30.0) -> dict[str, Any]:
        """The reply message to request ``request``, as it came."""
        with self._reply_ready:
            if not self._reply_ready.wait_for(lambda: request in self._replies or not self.connected, timeout_s):
                raise ChannelError(f"no reply to {what!r} within {timeout_s} s")
            if request not in self._replies:
                raise ChannelError("the controller is gone")
            return self._replies.pop(request)

    def close(self) -> None:
        # Shut the socket down: it wakes our reader blocked in recv, which closes it, and
        # tells the controller we are gone.
        shut_down(self.connection)
        self._reader.join(5.0)
