"""Fixtures shared by the tests of several layers, and the browser marker by folder.

The support modules beside this file hold what a test imports by name (tests.jrc_fixtures,
tests.chromium, ...); the fixtures here are the ones several test files asked for alike.
"""

import threading
from pathlib import Path

import pytest

from tests.chromium import headless_chromium
from tests.controller_fixtures import simulated_controller
from vservo.core.cell.config import load_cell
from vservo.core.production.storage import DEMO_JOB, Store

E2E = Path(__file__).parent / "e2e"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The tests that drive Chromium live under tests/e2e: each is marked browser, and slow too
    (alone, each starts `vservo serve` and Chromium: tens of seconds), so that
    `-m "not browser and not slow"` (the fast loop) leaves them out. Slow tests elsewhere are
    marked where they are defined."""
    for item in items:
        if E2E in item.path.parents:
            item.add_marker(pytest.mark.browser)
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="module")
def cell_config():
    """The shipped cell file (static/cell.toml), loaded once per module."""
    return load_cell()


@pytest.fixture
def controller(tmp_path):
    """A controller of the simulated shipped cell (the fast step policy, seed 3), its store in tmp_path."""
    with simulated_controller(load_cell(), tmp_path / "data") as controller:
        yield controller


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The shipped demo job, as a new store holds it."""
    store = Store(tmp_path_factory.mktemp("data"))
    try:
        return store.load_job(DEMO_JOB)
    finally:
        store.close()


@pytest.fixture(scope="module")
def chromium():
    """The system's headless Chromium for one module's browser tests: no Chromium fails them,
    it never skips them. Request it after the app it browses, so that it closes first."""
    with headless_chromium() as browser:
        yield browser


@pytest.fixture
def no_leaked_threads():
    """Fails a test that leaves an emulator, a watchdog or a host thread running."""
    before = set(threading.enumerate())
    yield
    leaked = [thread.name for thread in threading.enumerate() if thread not in before and thread.is_alive()]
    assert not leaked, f"threads left running: {leaked}"
