"""The web page's guards seen from real headless Chromium against `vservo serve` as a process:
a page of another site cannot open the app's WebSocket while the app's own page can, and
wrong operator tokens count against the browser's address, so a reload does not reset them."""

from __future__ import annotations

import functools
import http.server
import threading

import pytest
import viser

from vservo.app.browser import (
    ServeProcess,
    free_port,
    open_pages,
    type_into,
)
from vservo.app.roles import MAX_TOKEN_FAILURES
from vservo.core.production.protocol.catalogue import Refusal, explain

TOKEN = "e2e-guard-operator-token"
# What a page's script gets when it opens the app's WebSocket.
OPEN_WEBSOCKET = (
    """(url) => new Promise((resolve) => {
    const socket = new WebSocket(url, ["viser-v%s"]);
    socket.onopen = () => { socket.close(); resolve("open"); };
    socket.onerror = () => resolve("refused");
})"""
    % viser.__version__
)


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    with ServeProcess.start(tmp_path_factory.mktemp("serve-data"), TOKEN, cycle_period_s=0.05) as serve:
        yield serve


@pytest.fixture
def foreign_site(tmp_path):
    """Another web site on this PC (another origin: another port), serving one empty page."""
    (tmp_path / "index.html").write_text("<html><body>another site</body></html>")
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", free_port()), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}/"
    server.shutdown()
    server.server_close()


def test_a_page_of_another_site_cannot_open_the_apps_websocket(app, chromium, foreign_site):
    websocket_url = app.url.replace("http://", "ws://")
    foreign = chromium.new_context().new_page()
    foreign.goto(foreign_site)
    assert foreign.evaluate(OPEN_WEBSOCKET, websocket_url) == "refused"
    own = open_pages(chromium, app.url, [(1200, 800)])[0]
    assert own.evaluate(OPEN_WEBSOCKET, websocket_url) == "open"
    assert "WebSocket from 127.0.0.1 refused: Origin 'http://127.0.0.1:" in app.stderr()


def test_wrong_tokens_count_against_the_address_across_reloads(app, chromium):
    page = open_pages(chromium, app.url, [(1200, 800)])[0]
    for _ in range(MAX_TOKEN_FAILURES):
        type_into(page, "Operator token", "a-wrong-guess")
        page.get_by_role("button", name="Take control").click()
    page.reload()  # a new viser client, the same address
    page.get_by_role("button", name="Take control").wait_for(timeout=90_000)
    type_into(page, "Operator token", TOKEN)
    page.get_by_role("button", name="Take control").click()
    page.get_by_text(explain(Refusal.TOKEN_LOCKOUT).sentence).first.wait_for(timeout=30_000)  # the notice
    page.get_by_text("too many wrong operator tokens from this address").first.wait_for(state="attached", timeout=10_000)
    assert app.stderr().count("wrong operator token from 127.0.0.1") == MAX_TOKEN_FAILURES
    assert page.get_by_text("this browser holds control").count() == 0
