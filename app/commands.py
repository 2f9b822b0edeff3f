"""The browsers' commands to the controller, checked and carried out off viser's threads.

A button's callback runs in viser's thread pool and must return at once; a command may
take seconds (a jog on the real arm). ``CommandQueue.submit`` checks the role there and
then hands the command to one worker thread that sends it over the channel and reports
the reply to the browser that asked. Commands run one at a time in the order given.
The e-stop never queues: it is sent from its own thread the moment it is pressed, by any
browser (the channel carries it out ahead of a long move, too).

Viser-free: ``call`` is the channel's ControllerClient.call, ``Reply`` its answer. The
commands are the protocol's dataclasses: a query (``Query``) and the e-stop are anyone's.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass

from vservo.app.roles import RoleRefused, Roles
from vservo.core.production.protocol import ChannelError, Command, Estop, Query, Reply
from vservo.core.production.protocol.catalogue import Refusal

log = logging.getLogger("vservo.app")

Call = Callable[[Command, float], Reply]  # the command and how long to wait for its reply (s)
Done = Callable[[Reply], None]


@dataclass(frozen=True)
class _Request:
    client_id: int | None
    command: Command
    done: Done

    @property
    def what(self) -> str:
        return self.command.command_name


class CommandQueue:
    def __init__(self, call: Call, roles: Roles, timeout_s: float = 120.0) -> None:
        self._call = call
        self.roles = roles
        self.timeout_s = timeout_s
        self._requests: queue.Queue[_Request | None] = queue.Queue()
        self._worker = threading.Thread(target=self._work, name="app-commands", daemon=True)
        self._worker.start()

    def submit(self, client_id: int | None, command: Command, done: Done = lambda reply: None) -> None:
        """Queue ``command`` for the controller if this browser may send it; RoleRefused otherwise."""
        if isinstance(command, Estop):
            self.estop(client_id, done)
            return
        if not isinstance(command, Query):
            self.roles.require(client_id, command.command_name.replace("_", " "))
        self._requests.put(_Request(client_id, command, done))

    def estop(self, client_id: int | None, done: Done = lambda reply: None) -> None:
        """Stop the cell now: from any browser, never behind another command."""
        log.warning("e-stop pressed in browser %s", client_id)
        threading.Thread(target=self._send, args=(_Request(client_id, Estop(), done),), name="app-estop", daemon=True).start()

    def reconnect(self, call: Call) -> None:
        """Send the next commands with ``call``: a new controller's channel in place of a dead one's."""
        self._call = call

    def call_now(self, query: Query) -> Reply:
        """A read-only query answered in the caller's thread (the app's own refreshes, not a browser's)."""
        if not isinstance(query, Query):
            raise RoleRefused(f"{query.command_name} is not a query")
        return self._call(query, self.timeout_s)

    def close(self) -> None:
        self._requests.put(None)
        self._worker.join(5.0)

    def _work(self) -> None:
        while (request := self._requests.get()) is not None:
            if not isinstance(request.command, Query) and not self.roles.is_operator(request.client_id):
                # Control changed hands while this waited in the queue: the new operator did not ask for it.
                released = f"{request.what}: control was released before it was sent"
                request.done(Reply(False, error=released, kind=Refusal.CONTROL))
                continue
            self._send(request)

    def _send(self, request: _Request) -> None:
        try:
            reply = self._call(request.command, self.timeout_s)
        except ChannelError as exc:
            reply = Reply(False, error=f"{request.what}: {exc}", kind=Refusal.CHANNEL)
        try:
            request.done(reply)
        except Exception:  # a browser that left meanwhile must not stop the worker
            log.exception("reporting the reply to %s failed", request.what)
