"""Waiting in tests for something another thread or process brings about."""

import time
from collections.abc import Callable


def wait_until(check: Callable[[], bool], what: str, timeout_s: float = 30.0, poll_s: float = 0.1) -> None:
    """Poll ``check`` every ``poll_s`` until it holds; an AssertionError naming ``what``
    after ``timeout_s`` (a liveness bound, not a timing)."""
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s} s")
        time.sleep(poll_s)
