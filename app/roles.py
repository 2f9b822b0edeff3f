"""Who may drive the cell: one operator at a time, every other browser a read-only monitor.

The operator token is set when the app starts (``vservo serve --token-file``, the
environment's VSERVO_OPERATOR_TOKEN, ``--token`` on this PC only, or generated and
printed). A browser that enters it takes control; it keeps control until it releases it,
disconnects, or another browser enters the token (the token is the authority, so an
operator who moved to another screen is never locked out by a forgotten tab). Stopping
is never a matter of roles: the e-stop is every browser's.

Wrong tokens are counted per client address: after MAX_TOKEN_FAILURES within
FAILURE_WINDOW_S, that address's attempts are refused unchecked until the oldest failure
ages out, so guessing is slow; each failure is logged with the address.

Viser-free: the app asks ``require`` before it sends any command that moves or changes
the cell, whatever the browser's buttons showed.
"""

from __future__ import annotations

import enum
import hmac
import ipaddress
import logging
import math
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from vservo.core.errors import VservoError
from vservo.core.production.protocol.catalogue import Refusal

log = logging.getLogger("vservo.app.roles")

TOKEN_ENVIRONMENT = "VSERVO_OPERATOR_TOKEN"
MIN_NETWORK_TOKEN_LENGTH = 16  # as long as a generated one (96 random bits) when the network can guess
MAX_TOKEN_FAILURES = 5
FAILURE_WINDOW_S = 60.0


class RoleRefused(VservoError, PermissionError):
    """A browser asked for something only the operator may do; the message says what to do."""

    def __init__(self, message: str, kind: Refusal = Refusal.CONTROL) -> None:
        super().__init__(message)
        self.kind = kind  # as the page explains it (protocol/catalogue.py)


def new_token() -> str:
    """A fresh operator token: 12 random bytes, URL-safe (16 characters)."""
    return secrets.token_urlsafe(12)


class TokenSource(enum.Enum):
    GENERATED = "generated"
    ENVIRONMENT = f"${TOKEN_ENVIRONMENT}"
    FILE = "--token-file"
    COMMAND_LINE = "--token"


class TokenError(VservoError, ValueError):
    """An operator token that cannot be used; the message says where it came from and why."""


@dataclass(frozen=True)
class OperatorToken:
    value: str
    source: TokenSource


def is_loopback(host: str) -> bool:
    """True if serving on ``host`` reaches this PC only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: whatever it resolves to, assume the network


def operator_token(
    command_line: str | None, file: str | None, environment: Mapping[str, str], host: str, warn: Callable[[str], None]
) -> OperatorToken:
    """The token from --token-file, --token or the environment (else a new one), checked for ``host``.

    Beyond loopback a token must be at least MIN_NETWORK_TOKEN_LENGTH characters and not
    on the command line, where ``ps`` shows it to every user of the PC.
    """
    if file is not None:
        try:
            value = Path(file).read_text(encoding="utf-8").strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise TokenError(f"--token-file {file}: cannot read the operator token: {exc}") from None
        token = OperatorToken(value, TokenSource.FILE)
    elif command_line is not None:
        token = OperatorToken(command_line.strip(), TokenSource.COMMAND_LINE)
    elif environment.get(TOKEN_ENVIRONMENT) is not None:
        token = OperatorToken(environment[TOKEN_ENVIRONMENT].strip(), TokenSource.ENVIRONMENT)
    else:
        token = OperatorToken(new_token(), TokenSource.GENERATED)
    where = f"{token.source.value} {file}" if token.source is TokenSource.FILE else token.source.value
    if not token.value:
        raise TokenError(f"{where}: the operator token is empty")
    if is_loopback(host):
        if token.source is TokenSource.COMMAND_LINE:
            warn(f"--token is visible to every user of this PC in ps; use --token-file or ${TOKEN_ENVIRONMENT}")
        return token
    if token.source is TokenSource.COMMAND_LINE:
        raise TokenError(
            f"--host {host}: --token is visible in ps; give the token with --token-file or "
            f"${TOKEN_ENVIRONMENT} when serving beyond this PC"
        )
    if len(token.value) < MIN_NETWORK_TOKEN_LENGTH:
        raise TokenError(
            f"{where}: the operator token has {len(token.value)} characters; serving on --host {host} "
            f"needs at least {MIN_NETWORK_TOKEN_LENGTH}"
        )
    warn(
        f"serving on {host}: every computer that reaches this one sees the cell and may press the E-STOP; "
        "only the operator token guards control"
    )
    return token


class TokenAttempts:
    """Wrong operator tokens per client address within a sliding window (thread-safe)."""

    def __init__(
        self,
        max_failures: int = MAX_TOKEN_FAILURES,
        window_s: float = FAILURE_WINDOW_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.max_failures, self.window_s, self._clock = max_failures, window_s, clock
        self._failures: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def wait_s(self, source: str) -> float:
        """How long ``source`` must wait before its next attempt is checked (0: now)."""
        with self._lock:
            failures = self._recent(source)
            return 0.0 if len(failures) < self.max_failures else failures[0] + self.window_s - self._clock()

    def failed(self, source: str) -> int:
        """Count a wrong token from ``source``; its failures within the window."""
        with self._lock:
            failures = self._recent(source)
            failures.append(self._clock())
            return len(failures)

    def succeeded(self, source: str) -> None:
        with self._lock:
            self._failures.pop(source, None)

    def _recent(self, source: str) -> deque[float]:
        failures = self._failures.setdefault(source, deque())
        while failures and failures[0] + self.window_s <= self._clock():
            failures.popleft()
        return failures


class Roles:
    """The operator's seat. Thread-safe; listeners hear (old operator, new operator) on every change."""

    def __init__(self, token: str, attempts: TokenAttempts | None = None) -> None:
        if not token or not token.strip():
            raise ValueError("the operator token is empty: give one with --token-file or leave it out to generate one")
        self._token = token.strip().encode()
        self.attempts = attempts or TokenAttempts()
        self._operator: int | None = None
        self._lock = threading.Lock()
        self.listeners: list[Callable[[int | None, int | None], None]] = []

    @property
    def operator(self) -> int | None:
        """The client id of the browser holding control, or None."""
        return self._operator

    def is_operator(self, client_id: int | None) -> bool:
        return client_id is not None and client_id == self._operator

    def take(self, client_id: int, token: str, source: str | None = None) -> None:
        """Give control to ``client_id`` if ``token`` is the operator token (compared in constant time).

        ``source``: the client's address, which wrong tokens are counted against.
        """
        source = source or f"browser {client_id}"
        wait_s = self.attempts.wait_s(source)
        if wait_s > 0.0:
            raise RoleRefused(
                f"too many wrong operator tokens from this address: try again in {math.ceil(wait_s)} s", Refusal.TOKEN_LOCKOUT
            )
        if not hmac.compare_digest(token.strip().encode(), self._token):
            failures = self.attempts.failed(source)
            log.warning(
                "wrong operator token from %s (browser %d): %d of %d within %g s",
                source,
                client_id,
                failures,
                self.attempts.max_failures,
                self.attempts.window_s,
            )
            raise RoleRefused("wrong operator token: control not taken")
        self.attempts.succeeded(source)
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
            raise RoleRefused(
                f"{action}: this browser is a read-only monitor ({holder}); enter the operator token and take control first"
            )

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
