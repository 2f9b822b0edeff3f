"""Who may drive the cell: one operator at a time, every other browser a read-only monitor.

The operator token is set when the app starts (``vservo serve --token``, or generated and
printed). A browser that enters it takes control; it keeps control until it releases it,
disconnects, or another browser enters the token (the token is the authority, so an
operator who moved to another screen is never locked out by a forgotten tab). Stopping
is never a matter of roles: the e-stop is every browser's.

Viser-free: the app asks ``require`` before it sends any command that moves or changes
the cell, whatever the browser's buttons showed.
"""

from __future__ import annotations

import hmac
import secrets
import threading
from collections.abc import Callable

TOKEN_ENVIRONMENT = "VSERVO_OPERATOR_TOKEN"


class RoleRefused(PermissionError):
    """A browser asked for something only the operator may do; the message says what to do."""


def new_token() -> str:
    """A fresh operator token: 12 random bytes, URL-safe (16 characters)."""
    return secrets.token_urlsafe(12)


class Roles:
    """The operator's seat. Thread-safe; listeners hear (old operator, new operator) on every change."""

    def __init__(self, token: str) -> None:
        if not token or not token.strip():
            raise ValueError("the operator token is empty: give one with --token or leave it out to generate one")
        self._token = token.strip().encode()
        self._operator: int | None = None
        self._lock = threading.Lock()
        self.listeners: list[Callable[[int | None, int | None], None]] = []

    @property
    def operator(self) -> int | None:
        """The client id of the browser holding control, or None."""
        return self._operator

    def is_operator(self, client_id: int | None) -> bool:
        return client_id is not None and client_id == self._operator

    def take(self, client_id: int, token: str) -> None:
        """Give control to ``client_id`` if ``token`` is the operator token (compared in constant time)."""
        if not hmac.compare_digest(token.strip().encode(), self._token):
            raise RoleRefused("wrong operator token: control not taken")
        self._set(client_id, only_if=None, any_holder=True)

    def release(self, client_id: int) -> bool:
        """Give control up; False if ``client_id`` did not hold it."""
        return self._set(None, only_if=client_id)

    def disconnected(self, client_id: int) -> bool:
        """A browser went away: its control, if it held it, is released."""
        return self.release(client_id)

    def require(self, client_id: int | None, action: str) -> None:
        """Raise RoleRefused unless ``client_id`` holds control."""
        if not self.is_operator(client_id):
            holder = "another browser holds control" if self._operator is not None else "no browser holds control"
            raise RoleRefused(f"{action}: this browser is a read-only monitor ({holder}); enter the operator token "
                              "and take control first")

    def _set(self, new: int | None, only_if: int | None, any_holder: bool = False) -> bool:
        with self._lock:
            old = self._operator
            if not any_holder and old != only_if:
                return False
            if old == new:
                return True
            self._operator = new
        for listener in list(self.listeners):
            listener(old, new)
        return True
