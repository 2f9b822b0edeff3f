"""One browser's own part of the page: its controls, enabled only while it holds control.

Every panel registers the controls it adds for a browser here; a change of operator
enables them in the operator's page and disables them in every other one. Disabling is
the visible half of the roles; the other half is the server-side check in
app/commands.py, which refuses a command from a monitor even if a click arrives.

The buttons whose use depends on what the cell does (app/banner.py's ``Button``) are
registered by name: each is enabled only where this browser may press it AND it can act
now (``live_buttons`` of the phase, which the display thread passes to ``set_live``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import viser

from vservo.app.banner import Button
from vservo.app.roles import RoleRefused, Roles
from vservo.core.production.protocol import Reply
from vservo.core.production.protocol.catalogue import refusal_kind


class ClientView:
    def __init__(self, client: viser.ClientHandle) -> None:
        self.client = client
        self.client_id = client.client_id
        self.is_operator = False
        self._controls: list[Any] = []
        self._role_listeners: list[Callable[[bool], None]] = []
        self._lock = threading.Lock()
        self.handles: dict[str, Any] = {}  # panels keep this browser's displays here by name
        self._buttons: dict[Button, tuple[Any, bool]] = {}  # button -> (handle, operator only)
        self._live: frozenset[Button] = frozenset()
        self.on_detail: Callable[[str, str], None] | None = None  # a refusal's engineering line, for the Engineering fold

    def control(self, handle: Any) -> Any:
        """Register a control that only the operator may use; returns it. Button groups
        cannot be disabled in viser: a monitor's are hidden instead."""
        with self._lock:
            self._controls.append(handle)
            _enable(handle, self.is_operator)
        return handle

    def button(self, which: Button, handle: Any, operator_only: bool = True) -> Any:
        """Register one of the buttons the cell's phase enables; returns it."""
        with self._lock:
            self._buttons[which] = (handle, operator_only)
            self._apply_live()
        return handle

    def set_live(self, live: frozenset[Button]) -> None:
        """The buttons that can act now (app/banner.py's live_buttons); only changes are sent."""
        with self._lock:
            if live == self._live or self.gone:
                return
            self._live = live
            self._apply_live()

    def _apply_live(self) -> None:
        for which, (handle, operator_only) in self._buttons.items():
            disabled = not ((self.is_operator or not operator_only) and which in self._live)
            if handle.disabled != disabled:
                handle.disabled = disabled

    def on_role(self, listener: Callable[[bool], None]) -> None:
        """Call ``listener(is_operator)`` whenever this browser gains or loses control."""
        self._role_listeners.append(listener)

    @property
    def gone(self) -> bool:
        """The browser has left: viser removed its elements (it may tell us a moment later)."""
        return any(handle._impl.removed for handle in self._controls)

    def set_operator(self, is_operator: bool) -> None:
        with self._lock:
            if self.gone:
                return
            self.is_operator = is_operator
            for handle in self._controls:
                _enable(handle, is_operator)
            self._apply_live()
        for listener in list(self._role_listeners):
            listener(is_operator)

    def set_options(self, key: str, options: list[str]) -> bool:
        """Give this browser's dropdown ``handles[key]`` new options, keeping its choice if it is
        still offered (else the first); False if nothing changed."""
        dropdown = self.handles.get(key)
        if dropdown is None or tuple(dropdown.options) == tuple(options):
            return False
        current = dropdown.value
        dropdown.options = options
        dropdown.value = current if current in options else options[0]
        return True

    def allowed(self, what: str, roles: Roles) -> bool:
        """Whether this browser holds control; if not, it is told why ``what`` was refused."""
        try:
            roles.require(self.client_id, what)
        except RoleRefused as exc:
            self.refused(what, exc)
            return False
        return True

    def notify(self, title: str, body: str, error: bool = False) -> None:
        self.client.add_notification(title, body, color="red" if error else "green", auto_close_seconds=12.0 if error else 4.0)

    def report(self, what: str, success: str | None = None) -> Callable[[Reply], None]:
        """A reply handler: refusals shown in red in this browser, success (if worded) in green."""

        def done(reply: Reply) -> None:
            if not reply.ok:
                self.say_refused(what, reply.operator_words(), reply.error or "no reason given")
            elif success:
                self.notify(what, success)

        return done

    def refused(self, what: str, exc: Exception) -> None:
        """A refusal the app made itself (the role, a field out of range), explained as the controller's are."""
        self.say_refused(what, Reply(False, kind=refusal_kind(exc), advice=getattr(exc, "advice", "")).operator_words(), str(exc))

    def say_refused(self, what: str, words: str, detail: str) -> None:
        """The catalogue's sentence and action in red; the engineer's line to the Engineering fold (``on_detail``)."""
        self.notify(f"{what}: refused", words, error=True)
        if self.on_detail is not None:
            self.on_detail(what, detail)


def _enable(handle: Any, enabled: bool) -> None:
    if isinstance(handle, viser.GuiButtonGroupHandle):
        handle.visible = enabled
    else:
        handle.disabled = not enabled
