"""The browser tests' one precondition: the system's Chromium, or a failure saying how to get it."""

import pytest

from vservo.app.browser import ChromiumMissing, require_chromium


def chromium_or_fail() -> None:
    """A browser test never skips itself into green: no Chromium is a failure naming the fix."""
    try:
        require_chromium()
    except ChromiumMissing as exc:
        pytest.fail(str(exc))
