"""Which web pages may open the app's WebSocket: the page's own origin, and origins the operator allows.

A browser lets any web page open a WebSocket to any address, and tells the server only
which page did so, in the ``Origin`` header. Without a check, a page on another site that
the operator's browser happens to show could watch the camera and the cell, and press the
E-STOP. So the handshake is refused (HTTP 403) unless ``Origin`` is the address the page
itself was loaded from (the ``Host`` the browser asked for) or one the operator allowed
with ``vservo serve --allow-origin``. A client that sends no ``Origin`` is no browser's
page, and is refused as well.

The page's own origin alone is not enough: a foreign site can point its own name at this
PC's address once its page is loaded (DNS rebinding), and its page's ``Origin`` and the
``Host`` it asks for are then its own name. So the ``Host`` must also be a name this PC
answers to: an IP address, ``localhost``, this PC's host name, or an allowed origin's host.

viser builds its websockets server inside its own thread with no way to pass a request
check, so ``origin_checked_server`` wraps the ``websockets.asyncio.server.serve`` that
viser calls, only while a ViserServer starts (its constructor returns once it serves).
"""

from __future__ import annotations

import contextlib
import http
import ipaddress
import logging
import socket
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from urllib.parse import urlsplit

import viser
import websockets.asyncio.server
from websockets.asyncio.server import ServerConnection
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

log = logging.getLogger("vservo.app.web")


def normalise_origin(origin: str) -> str:
    """``scheme://host[:port]``, lower case, as browsers send it; ValueError naming the value otherwise."""
    parts = urlsplit(origin.strip())
    if parts.scheme not in ("http", "https") or not parts.netloc or parts.path not in ("", "/") or parts.query:
        raise ValueError(f"allowed origin {origin!r} is not of the form http://host[:port] or https://host[:port]")
    return f"{parts.scheme}://{parts.netloc}".lower()


def this_pcs_names() -> frozenset[str]:
    """The names a browser may use for this PC besides its IP addresses (lower case)."""
    return frozenset(name.lower() for name in ("localhost", socket.gethostname(), socket.getfqdn()) if name)


@dataclass(frozen=True)
class OriginPolicy:
    """The page's own origin, plus ``allowed`` (normalised origins, e.g. a reverse proxy's
    address); the page's own only under ``host_names`` (this PC's names) or an IP address."""

    allowed: frozenset[str] = frozenset()
    host_names: frozenset[str] = frozenset({"localhost"})

    @classmethod
    def allowing(cls, origins: tuple[str, ...] | list[str]) -> OriginPolicy:
        allowed = frozenset(normalise_origin(origin) for origin in origins)
        return cls(allowed, this_pcs_names() | {name for origin in allowed if (name := urlsplit(origin).hostname)})

    def names_this_pc(self, host: str) -> bool:
        """Whether a ``Host`` header (``name[:port]``) names this PC rather than a rebound foreign name."""
        name = urlsplit(f"//{host}").hostname or ""
        try:
            ipaddress.ip_address(name)
            return True
        except ValueError:
            return name.rstrip(".") in self.host_names

    def refusal(self, headers: Headers) -> str | None:
        """Why a WebSocket handshake with these headers is refused, or None to accept it."""
        origin, host = headers.get("Origin"), headers.get("Host")
        if origin is None:
            return "no Origin header (not a browser page)"
        try:
            parts = urlsplit(origin)
        except ValueError:
            return f"malformed Origin {origin!r}"
        if origin.lower() in self.allowed:
            return None
        if host is None or parts.scheme not in ("http", "https") or parts.netloc.lower() != host.lower():
            return f"Origin {origin!r} is neither this page ({host!r}) nor an allowed origin"
        if not self.names_this_pc(host):
            return f"Host {host!r} is not a name of this PC (a foreign name pointed at it?): allow it with --allow-origin"
        return None

    def check(self, connection: ServerConnection, request: Request) -> Response | None:
        """websockets' ``process_request``: a 403 for a refused WebSocket handshake, None to go on."""
        if request.headers.get("Upgrade", "").lower() != "websocket":
            return None  # the page's files: harmless to anyone, and what the browser loads first
        why = self.refusal(request.headers)
        if why is None:
            return None
        log.warning("WebSocket from %s refused: %s", _address(connection), why)
        return connection.respond(http.HTTPStatus.FORBIDDEN, f"refused: {why}\n")


def _address(connection: ServerConnection) -> str:
    try:
        return str(connection.remote_address[0])
    except (OSError, TypeError, IndexError):
        return "an unknown address"


_patching = threading.Lock()  # two apps starting at once must not wrap each other's serve


def origin_checked_server(host: str, port: int, policy: OriginPolicy) -> viser.ViserServer:
    """A ViserServer whose WebSocket handshakes pass ``policy`` first (then viser's own request handling)."""
    with _patching, _serve_checked_by(policy):
        return viser.ViserServer(host=host, port=port, verbose=False)


@contextlib.contextmanager
def _serve_checked_by(policy: OriginPolicy) -> Iterator[None]:
    original = websockets.asyncio.server.serve

    def serve(*args, process_request=None, **kwargs):  # noqa: ANN001, ANN202 (websockets' own signature)
        def checked(connection: ServerConnection, request: Request) -> Response | None:
            refused = policy.check(connection, request)
            if refused is not None or process_request is None:
                return refused
            return process_request(connection, request)

        return original(*args, process_request=checked, **kwargs)

    # websockets' serve is a class; viser calls it by the module's name, so the module's name is what is wrapped.
    setattr(websockets.asyncio.server, "serve", serve)
    try:
        yield
    finally:
        setattr(websockets.asyncio.server, "serve", original)
