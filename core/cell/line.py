"""The cell file's ``[line]`` tables: what the cell offers the production line besides the page.

- ``[line.opcua]``: the OPC UA server the controller process runs for the plant's MES or
  SCADA (core/production/opcua_server.py): where it listens, who may connect, whether an
  anonymous client may read;
- ``[line.metrics]``: the Prometheus metrics endpoint of the controller process
  (core/production/metrics.py).

Both listen on the loopback interface unless the file names another; both are off unless
``enabled = true``. A user's password is kept as a salted PBKDF2-SHA256 hash
(``vservo password-hash`` makes one); a plain ``password`` is accepted for a test bench,
never on an interface beyond loopback without the server's certificate, where it would
cross the network in clear.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import re
import secrets
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any, Protocol

from vservo.core.errors import VservoError

PORTS = (0, 65535)  # 0: any free port (a test's), announced by the controller
DEFAULT_OPCUA_PORT = 4840  # IANA's port for OPC UA over TCP
DEFAULT_METRICS_PORT = 9464
LOOPBACK = "127.0.0.1"
USER_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.@-]{0,63}$")
USER_NAME_WORDS = "1 to 64 letters, digits, '_', '.', '@' or '-', starting with a letter or digit"
HASH_SCHEME = "pbkdf2-sha256"
HASH_ITERATIONS = 200_000
MIN_HASH_ITERATIONS = 10_000
MIN_PASSWORD_CHARS = 8


class Table(Protocol):
    """What these parsers need of the cell file's table reader (core/cell/config.py's ``_Table``)."""

    _data: dict[str, Any]

    def fail(self, key: str, value: Any, why: str) -> VservoError: ...

    def integer(self, key: str, default: int | None = None) -> int: ...

    def text(self, key: str, default: str | None = None) -> str: ...

    def flag(self, key: str, default: bool) -> bool: ...

    def choice(self, key: str, options: Sequence[str], default: str | None = None) -> str: ...

    def table(self, key: str) -> Table: ...

    def finish(self) -> None: ...


class PasswordError(VservoError, ValueError):
    """A password hash that cannot be read, or a password too short to hash."""


@dataclass(frozen=True)
class PasswordHash:
    """A salted PBKDF2-SHA256 hash of a password, written ``pbkdf2-sha256$ITERATIONS$SALT$HASH`` (hex)."""

    iterations: int
    salt: bytes
    digest: bytes

    @classmethod
    def of(cls, password: str, iterations: int = HASH_ITERATIONS) -> PasswordHash:
        if len(password) < MIN_PASSWORD_CHARS:
            raise PasswordError(f"a password has at least {MIN_PASSWORD_CHARS} characters, got {len(password)}")
        salt = secrets.token_bytes(16)
        return cls(iterations, salt, _pbkdf2(password, salt, iterations))

    @classmethod
    def parse(cls, text: str) -> PasswordHash:
        parts = text.split("$")
        try:
            if len(parts) != 4 or parts[0] != HASH_SCHEME:
                raise ValueError
            iterations, salt, digest = int(parts[1]), bytes.fromhex(parts[2]), bytes.fromhex(parts[3])
        except ValueError:
            raise PasswordError(
                f"must be {HASH_SCHEME}$ITERATIONS$SALT$HASH (hex), as `vservo password-hash` prints it"
            ) from None
        if iterations < MIN_HASH_ITERATIONS or len(salt) < 8 or len(digest) != 32:
            raise PasswordError(f"needs at least {MIN_HASH_ITERATIONS} iterations, a salt of 8 bytes or more and a 32-byte hash")
        return cls(iterations, salt, digest)

    def text(self) -> str:
        return f"{HASH_SCHEME}${self.iterations}${self.salt.hex()}${self.digest.hex()}"

    def matches(self, password: str) -> bool:
        return hmac.compare_digest(_pbkdf2(password, self.salt, self.iterations), self.digest)


def _pbkdf2(password: str, salt: bytes, iterations: int) -> bytes:
    return hashlib.pbkdf2_hmac("sha256", password.encode("utf-8"), salt, iterations)


class AnonymousAccess(StrEnum):
    """What a client that gives no user name may do."""

    READ_ONLY = "read-only"  # browse, read and subscribe; never write nor call a method
    OFF = "off"  # refused at the session's activation


@dataclass(frozen=True)
class LineUser:
    """A user of the OPC UA server: may read, and call Start, Hold and Reset."""

    name: str
    password: PasswordHash


@dataclass(frozen=True)
class OpcUaConfig:
    """[line.opcua]: the OPC UA server (off unless enabled)."""

    enabled: bool = False
    host: str = LOOPBACK
    port: int = DEFAULT_OPCUA_PORT
    anonymous: AnonymousAccess = AnonymousAccess.READ_ONLY
    users: tuple[LineUser, ...] = ()
    certificate: Path | None = None  # PEM or DER; with it the server offers Basic256Sha256 sign and encrypt only
    private_key: Path | None = None

    @property
    def endpoint(self) -> str:
        return endpoint_url(self.host, self.port)


def endpoint_url(host: str, port: int) -> str:
    return f"opc.tcp://{host}:{port}/vservo/"


@dataclass(frozen=True)
class MetricsConfig:
    """[line.metrics]: the Prometheus metrics endpoint (off unless enabled)."""

    enabled: bool = False
    host: str = LOOPBACK
    port: int = DEFAULT_METRICS_PORT


@dataclass(frozen=True)
class LineConfig:
    """[line]: what the cell offers the production line."""

    opcua: OpcUaConfig = field(default_factory=OpcUaConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)


def _host(t: Table) -> str:
    """An interface's IP address to listen on; loopback unless the file names another."""
    host = t.text("host", LOOPBACK)
    try:
        ipaddress.ip_address(host)
    except ValueError:
        raise t.fail("host", host, "must be an IP address to listen on (127.0.0.1: this PC only; 0.0.0.0: every interface)")
    return host


def _port(t: Table, default: int) -> int:
    port = t.integer("port", default)
    if not PORTS[0] <= port <= PORTS[1]:
        raise t.fail("port", port, f"must be a TCP port from {PORTS[0]} (any free one) to {PORTS[1]}")
    return port


def _is_loopback(host: str) -> bool:
    return ipaddress.ip_address(host).is_loopback


def _user(name: str, t: Table) -> tuple[LineUser, bool]:
    """One [line.opcua.users.NAME] table, and whether its password was given in clear."""
    given = [key for key in ("password_hash", "password") if key in t._data]
    if len(given) != 1:
        raise t.fail("password_hash", None, "give exactly one of password_hash (as `vservo password-hash` prints it) or password")
    if given[0] == "password_hash":
        text = t.text("password_hash")
        try:
            password = PasswordHash.parse(text)
        except PasswordError as exc:
            raise t.fail("password_hash", text[:24] + "...", str(exc)) from None
    else:
        try:
            password = PasswordHash.of(t.text("password"), iterations=MIN_HASH_ITERATIONS)
        except PasswordError as exc:
            raise t.fail("password", "***", str(exc)) from None
    t.finish()
    return LineUser(name, password), given[0] == "password"


def _users(t: Table) -> tuple[tuple[LineUser, ...], bool]:
    """[line.opcua.users]: one table per user, named by the user's name."""
    table = t.table("users")
    users, in_clear = [], False
    for name in list(table._data):
        if not USER_NAME.match(name):
            raise table.fail(name, "{...}", f"a user's name must be {USER_NAME_WORDS}")
        user, clear = _user(name, table.table(name))
        users.append(user)
        in_clear |= clear
    table.finish()
    return tuple(users), in_clear


def _file(t: Table, key: str, base_dir: Path | None) -> Path | None:
    if key not in t._data:
        return None
    path = Path(t.text(key))
    path = path if path.is_absolute() or base_dir is None else base_dir / path
    if not path.is_file():
        raise t.fail(key, str(path), "no such file")
    return path


def parse_opcua(t: Table, base_dir: Path | None = None) -> OpcUaConfig:
    """[line.opcua], every key checked; a server no client could use is refused."""
    enabled = t.flag("enabled", False)
    host = _host(t)
    port = _port(t, DEFAULT_OPCUA_PORT)
    anonymous = AnonymousAccess(t.choice("anonymous", tuple(AnonymousAccess), AnonymousAccess.READ_ONLY))
    users, in_clear = _users(t)
    certificate, private_key = _file(t, "certificate", base_dir), _file(t, "private_key", base_dir)
    if (certificate is None) != (private_key is None):
        raise t.fail("certificate", str(certificate or private_key), "certificate and private_key go together")
    t.finish()
    if enabled and not users and anonymous is AnonymousAccess.OFF:
        raise t.fail("anonymous", anonymous.value, "with no [line.opcua.users.NAME] no client could connect")
    if enabled and users and not _is_loopback(host) and certificate is None:
        raise t.fail(
            "host",
            host,
            "beyond loopback the users' passwords would cross the network in clear: give certificate and private_key",
        )
    if enabled and in_clear and not _is_loopback(host):
        raise t.fail("host", host, "a plain password is for a loopback test bench: give password_hash beyond it")
    return OpcUaConfig(enabled, host, port, anonymous, users, certificate, private_key)


def parse_metrics(t: Table) -> MetricsConfig:
    """[line.metrics]: enabled, host, port."""
    metrics = MetricsConfig(t.flag("enabled", False), _host(t), _port(t, DEFAULT_METRICS_PORT))
    t.finish()
    return metrics


def parse_line(t: Table, base_dir: Path | None = None) -> LineConfig:
    """[line] and its tables."""
    line = LineConfig(parse_opcua(t.table("opcua"), base_dir), parse_metrics(t.table("metrics")))
    t.finish()
    return line
