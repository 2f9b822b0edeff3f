"""A progress bar on standard error for long work (studies, Monte Carlo, training)."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """``[#####.....] 7/16 12s task 3 2.5d``: redrawn in place on a terminal, a line per
    tenth of the work otherwise (so logs and CI output stay short)."""

    WIDTH = 30

    def __init__(self, total: int, label: str, stream: TextIO | None = None) -> None:
        self.total, self.label, self.done = max(total, 1), label, 0
        self.stream = stream or sys.stderr
        self.interactive = self.stream.isatty()
        self.started = time.monotonic()
        self._last_tenth = -1

    def advance(self, note: str = "") -> None:
        self.done += 1
        filled = self.WIDTH * self.done // self.total
        bar = "#" * filled + "." * (self.WIDTH - filled)
        line = f"{self.label} [{bar}] {self.done}/{self.total} {time.monotonic() - self.started:.0f}s {note}"
        if self.interactive:
            self.stream.write("\r" + line[:120].ljust(120))
        elif (tenth := 10 * self.done // self.total) != self._last_tenth:
            self._last_tenth = tenth
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.interactive:
            self.stream.write("\n")
            self.stream.flush()
