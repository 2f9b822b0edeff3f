"""The browsers' commands to the controller, checked and carried out off viser's threads.

A button's callback runs in viser's thread pool and must return at once; a command may
take seconds (a jog on the real arm). ``CommandQueue.submit`` checks the role there and
then hands the command to one worker thread that sends it over the channel and reports
the reply to the browser that asked. Commands run one at a time in the order given.
The e-stop never queues: it is sent from its own thread the moment it is pressed, by any
browser (the channel carries it out ahead of a long move, too).

Viser-free: ``call`` is the channel's ControllerClient.call, ``Reply`` its answer.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from vservo.app.roles import RoleRefused, Roles
from vservo.core.production.channel import ChannelError, Reply

log = logging.getLogger("vservo.app")

# Commands any browser may send: reading, and stopping.
READ_ONLY = frozenset({"list_jobs", "list_runs", "get_job"})
ESTOP = "estop"

Call = Callable[..., Reply]
Done = Callable[[Reply], None]


@dataclass(frozen=True)
class _Request:
    client_id: int | None
    name: str
    args: dict[str, Any]
    done: Done


class CommandQueue:
    def __init__(self, call: Call, roles: Roles, timeout_s: float = 120.0) -> None:
        self._call = call
        self.roles = roles
        self.timeout_s = timeout_s
        self._requests: queue.Queue[_Request | None] = queue.Queue()
        self._worker = threading.Thread(target=self._work, name="app-commands", daemon=True)
        self._worker.start()

    def submit(self, client_id: int | None, command: str, done: Done = lambda reply: None, **args: Any) -> None:
        """Queue ``command`` for the controller if this browser may send it; RoleRefused otherwise."""
        if command == ESTOP:
            self.estop(client_id, done)
            return
        if command not in READ_ONLY:
            self.roles.require(client_id, command.replace("_", " "))
        self._requests.put(_Request(client_id, command, args, done))

    def estop(self, client_id: int | None, done: Done = lambda reply: None) -> None:
        """Stop the cell now: from any browser, never behind another command."""
        log.warning("e-stop pressed in browser %s", client_id)
        threading.Thread(target=self._send, args=(_Request(client_id, ESTOP, {}, done),), name="app-estop", daemon=True).start()

    def call_now(self, command: str, **args: Any) -> Reply:
        """A read-only query answered in the caller's thread (the app's own refreshes, not a browser's)."""
        if command not in READ_ONLY:
            raise RoleRefused(f"{command} is not a query")
        return self._call(command, timeout_s=self.timeout_s, **args)

    def close(self) -> None:
        self._requests.put(None)
        self._worker.join(5.0)

    def _work(self) -> None:
        while (request := self._requests.get()) is not None:
            if request.name not in READ_ONLY and not self.roles.is_operator(request.client_id):
                # Control changed hands while this waited in the queue: the new operator did not ask for it.
                request.done(Reply(False, error=f"{request.name}: control was released before it was sent"))
                continue
            self._send(request)

    def _send(self, request: _Request) -> None:
        try:
            reply = self._call(request.name, timeout_s=self.timeout_s, **request.args)
        except ChannelError as exc:
            reply = Reply(False, error=f"{request.name}: {exc}")
        try:
            request.done(reply)
        except Exception:  # a browser that left meanwhile must not stop the worker
            log.exception("reporting the reply to %s failed", request.name)
