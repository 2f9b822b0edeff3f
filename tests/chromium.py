"""The browser tests' one precondition: the system's Chromium, or a failure saying how to get it."""

from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from vservo.app.browser import ChromiumMissing, launch_chromium, require_chromium


def chromium_or_fail() -> None:
    """A browser test never skips itself into green: no Chromium is a failure naming the fix."""
    try:
        require_chromium()
    except ChromiumMissing as exc:
        pytest.fail(str(exc))


@contextmanager
def headless_chromium() -> Iterator:
    """The system's Chromium, headless under Playwright, closed at the end."""
    chromium_or_fail()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        chromium = launch_chromium(playwright)
        try:
            yield chromium
        finally:
            chromium.close()
