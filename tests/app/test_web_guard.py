"""The web page's guards: WebSocket handshakes from foreign origins refused, operator tokens
rate limited per client address and logged, and the token kept off the command line and long
when the app serves beyond this PC."""

from __future__ import annotations

import http.client
import logging
import subprocess
import sys
import urllib.request

import pytest
import viser
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from vservo.app.browser import free_port
from vservo.app.roles import (
    TOKEN_ENVIRONMENT,
    RoleRefused,
    Roles,
    TokenAttempts,
    TokenError,
    TokenSource,
    operator_token,
)
from vservo.app.web_guard import OriginPolicy, normalise_origin, origin_checked_server

VISER_SUBPROTOCOL = f"viser-v{viser.__version__}"


@pytest.fixture(scope="module")
def page():
    server = origin_checked_server("127.0.0.1", free_port(), OriginPolicy.allowing(["https://proxy.example:8443"]))
    yield server.get_port()
    server.stop()


def _open(port: int, origin: str | None):
    return connect(f"ws://127.0.0.1:{port}", origin=origin, subprotocols=[VISER_SUBPROTOCOL], open_timeout=10)


def test_the_pages_own_origin_and_allowed_ones_open_the_websocket(page):
    for origin in (f"http://127.0.0.1:{page}", "https://proxy.example:8443"):
        with _open(page, origin) as websocket:
            assert websocket.subprotocol == VISER_SUBPROTOCOL
    with urllib.request.urlopen(f"http://127.0.0.1:{page}/", timeout=10) as response:
        assert response.status == 200  # the page itself is served to anyone


@pytest.mark.parametrize("origin", ["http://evil.example", "http://127.0.0.1:1", "null", None])
def test_a_foreign_origin_is_refused_at_the_handshake(page, origin, caplog):
    with caplog.at_level(logging.WARNING, logger="vservo.app.web"), pytest.raises(InvalidStatus) as refused:
        _open(page, origin)
    assert refused.value.response.status_code == 403
    assert "WebSocket from 127.0.0.1 refused" in caplog.text


def _handshake_status(port: int, host: str, origin: str) -> int:
    """A WebSocket handshake sent to 127.0.0.1 as a browser sends it for a page at ``origin``
    under the name ``host`` (what a foreign name pointed at this PC makes the browser send)."""
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        connection.putrequest("GET", "/", skip_host=True)
        for name, value in (
            ("Host", host),
            ("Origin", origin),
            ("Upgrade", "websocket"),
            ("Connection", "Upgrade"),
            ("Sec-WebSocket-Key", "dGhlIHNhbXBsZSBub25jZQ=="),
            ("Sec-WebSocket-Version", "13"),
            ("Sec-WebSocket-Protocol", VISER_SUBPROTOCOL),
        ):
            connection.putheader(name, value)
        connection.endheaders()
        return connection.getresponse().status
    finally:
        connection.close()


def test_a_foreign_name_pointed_at_this_pc_is_refused_and_this_pcs_own_names_are_not(page, caplog):
    with caplog.at_level(logging.WARNING, logger="vservo.app.web"):
        assert _handshake_status(page, f"evil.example:{page}", f"http://evil.example:{page}") == 403
    assert "is not a name of this PC" in caplog.text
    for name in ("localhost", "127.0.0.1"):
        assert _handshake_status(page, f"{name}:{page}", f"http://{name}:{page}") == 101


def test_an_allowed_origin_must_be_an_origin():
    assert normalise_origin("HTTPS://Proxy.Example:8443/") == "https://proxy.example:8443"
    with pytest.raises(ValueError, match="'proxy.example/app'"):
        normalise_origin("proxy.example/app")


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_wrong_tokens_are_rate_limited_per_address_and_logged(caplog):
    clock = Clock()
    roles = Roles("the-right-token-123", TokenAttempts(max_failures=5, window_s=60.0, clock=clock))
    refusals = []
    with caplog.at_level(logging.WARNING, logger="vservo.app.roles"):
        for guess in range(300):
            with pytest.raises(RoleRefused) as refused:
                roles.take(guess, f"guess-{guess}", "10.0.0.9")  # a new browser id each time: a page reload
            refusals.append(str(refused.value))
    assert refusals.count("wrong operator token: control not taken") == 5  # checked; the rest refused unchecked
    assert refusals[-1] == "too many wrong operator tokens from this address: try again in 60 s"
    assert caplog.text.count("wrong operator token from 10.0.0.9") == 5
    with pytest.raises(RoleRefused, match="too many"):
        roles.take(400, "the-right-token-123", "10.0.0.9")
    roles.take(401, "the-right-token-123", "10.0.0.7")  # another address is not held back
    assert roles.operator == 401
    clock.now = 60.0
    roles.take(402, "the-right-token-123", "10.0.0.9")
    assert roles.operator == 402


def _warnings() -> tuple[list[str], callable]:
    lines: list[str] = []
    return lines, lines.append


def test_the_token_comes_from_a_file_the_environment_or_loopbacks_command_line(tmp_path):
    lines, warn = _warnings()
    path = tmp_path / "token"
    path.write_text("from-the-file-0123456789\n")
    assert operator_token(None, str(path), {}, "0.0.0.0", warn).value == "from-the-file-0123456789"
    environment = {TOKEN_ENVIRONMENT: "from-the-environment-01"}
    assert operator_token(None, None, environment, "0.0.0.0", warn).source is TokenSource.ENVIRONMENT
    assert all("beyond" not in line and "serving on 0.0.0.0" in line for line in lines)
    lines.clear()
    assert operator_token("hunter2", None, {}, "127.0.0.1", warn).value == "hunter2"
    assert lines == ["--token is visible to every user of this PC in ps; use --token-file or $VSERVO_OPERATOR_TOKEN"]
    assert operator_token(None, None, {}, "localhost", warn).source is TokenSource.GENERATED


@pytest.mark.parametrize(
    "token, file_text, environment, message",
    [
        ("hunter2", None, {}, "--host 0.0.0.0: --token is visible in ps"),
        (None, "hunter2\n", {}, "the operator token has 7 characters; serving on --host 0.0.0.0 needs at least 16"),
        (None, None, {TOKEN_ENVIRONMENT: "short"}, "$VSERVO_OPERATOR_TOKEN: the operator token has 5 characters"),
        (None, "\n", {}, "the operator token is empty"),
    ],
)
def test_a_token_unfit_for_the_network_is_refused(tmp_path, token, file_text, environment, message):
    path = None
    if file_text is not None:
        path = tmp_path / "token"
        path.write_text(file_text)
    with pytest.raises(TokenError) as refused:
        operator_token(token, None if path is None else str(path), environment, "0.0.0.0", lambda line: None)
    assert message in str(refused.value)
    if path is not None:
        assert str(path) in str(refused.value)


@pytest.mark.slow
def test_serve_beyond_loopback_with_a_short_token_refuses_in_one_line(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "serve", "--host", "0.0.0.0", "--token", "hunter2", "--data", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    assert result.stderr.splitlines() == [
        "vservo serve: error: --host 0.0.0.0: --token is visible in ps; give the "
        "token with --token-file or $VSERVO_OPERATOR_TOKEN when serving beyond this PC"
    ]
    missing = subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "serve", "--token-file", str(tmp_path / "none"), "--data", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert missing.returncode == 2 and f"--token-file {tmp_path / 'none'}: cannot read" in missing.stderr
