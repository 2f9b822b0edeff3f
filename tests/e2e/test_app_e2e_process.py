"""The app process stays light: `vservo serve`, a real process driven by a real page, never
imports the controller (its module, the server's end of the channel): the page and its
commands go through the channel's protocol alone (core/production/protocol/).

What the process imported is read from its own interpreter: started with ``-X importtime``,
Python writes a line on standard error for every module the process imports. (The
controller it starts is a process of its own, started without that option: its imports,
the controller's module among them, write no such line.)
"""

from __future__ import annotations

import pytest

from tests.chromium import chromium_or_fail, headless_chromium
from vservo.app.browser import ServeProcess, open_pages, take_control, wait_for_status

TOKEN = "light-app-token"
CONTROLLER_MODULES = ("vservo.core.production.cell_controller", "vservo.core.production.channel")


def imported(stderr: str) -> set[str]:
    """The modules an interpreter started with -X importtime imported, from its standard error."""
    lines = [line for line in stderr.splitlines() if line.startswith("import time:") and "|" in line]
    return {line.rsplit("|", 1)[1].strip() for line in lines[1:]}  # the first is the table's header


@pytest.fixture(scope="module")
def serve_stderr(tmp_path_factory):
    """The standard error of a `vservo serve` whose page was opened, taken control of and used."""
    chromium_or_fail()
    with ServeProcess.start(tmp_path_factory.mktemp("serve-data"), TOKEN, python_options=("-X", "importtime")) as serve:
        with headless_chromium() as chromium:
            (page,) = open_pages(chromium, serve.url, [(1400, 900)])
            take_control(page, TOKEN)
            page.get_by_role("button", name="Present part", exact=True).click()
            wait_for_status(page, r"a new part is on the table")
            page.get_by_role("tab", name="Teach").click()
            page.get_by_role("button", name="Begin teaching", exact=True).click()
            wait_for_status(page, r"Teaching")
            page.get_by_role("button", name="Cancel teaching", exact=True).click()
            wait_for_status(page, r"teaching cancelled")
        assert serve.stop() == 0
        return serve.stderr()


def test_the_serving_process_never_imports_the_controller(serve_stderr):
    modules = imported(serve_stderr)
    # The log is the serving process's own: its app, the page's server, the protocol it speaks.
    assert {"vservo.app.server", "viser", "vservo.core.production.protocol.client"} <= modules
    assert not modules & set(CONTROLLER_MODULES), sorted(modules & set(CONTROLLER_MODULES))
