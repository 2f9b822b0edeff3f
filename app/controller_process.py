"""The controller as its own process, started and stopped by the app.

``vservo serve`` runs ``python -m vservo.app.cli controller`` with a fresh random channel key
in its environment (never on the command line, where ``ps`` would show it), reads the
one JSON line with the channel's address, and connects. Stopping sends SIGTERM: the
controller holds the robot if a run is under way, closes its devices and exits.
If the app dies instead, the controller notices its last app leaving and holds the
robot itself (core/production/channel.py).
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from vservo.core.errors import VservoError
from vservo.core.production.protocol import KEY_ENVIRONMENT, new_key

START_TIMEOUT_S = 60.0  # loading the arm model and the camera takes seconds on a loaded machine


class ControllerStartError(VservoError, RuntimeError):
    """The controller process did not come up; the message carries its last words."""


class ControllerProcess:
    def __init__(self, process: subprocess.Popen, address: tuple[str, int], key: bytes) -> None:
        self.process = process
        self.address = address
        self.key = key

    @classmethod
    def start(
        cls,
        *,
        backend: str,
        data: Path,
        seed: int | None,
        cycle_period_s: float,
        cell: str | None = None,
        time_scale: float | None = None,
        log_options: Sequence[str] = (),
    ) -> ControllerProcess:
        """The controller process; ``time_scale``: the simulated cell's pace (None: as fast as it computes)."""
        key = new_key()
        command = [
            sys.executable,
            "-m",
            "vservo.app.cli",
            *(["--cell", cell] if cell else []),
            "controller",
            "--exit-with-parent",
            "--backend",
            backend,
            "--data",
            str(data),
            "--cycle-period",
            str(cycle_period_s),
            "--time-scale",
            str(time_scale or 0.0),
            *(["--seed", str(seed)] if seed is not None else []),
            *log_options,
        ]
        # Its log goes to our standard error, as the operator's terminal shows the app's.
        process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env={**os.environ, KEY_ENVIRONMENT: key.hex()})
        line = _first_line(process, START_TIMEOUT_S)
        try:
            address = json.loads(line)["controller"]
            return cls(process, (address["host"], int(address["port"])), key)
        except (ValueError, KeyError, TypeError):
            process.terminate()
            process.wait(30)
            raise ControllerStartError(
                f"the controller process did not start (exit code {process.returncode}; "
                f"its error is above): {line.strip() or 'no address line'}"
            ) from None

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    def exit_code(self, timeout_s: float) -> int | None:
        """Its exit code once it has exited, waiting up to ``timeout_s``; None while it runs."""
        try:
            return self.process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def stop(self, timeout_s: float = 30.0) -> int | None:
        """SIGTERM (the controller holds the robot and exits), SIGKILL if it does not within the timeout."""
        if self.alive:
            self.process.terminate()
            try:
                self.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(10.0)
        if self.process.stdout is not None:
            self.process.stdout.close()
        return self.process.returncode


def _first_line(process: subprocess.Popen, timeout_s: float) -> str:
    """The controller's first stdout line; '' if it exits or stays silent past the timeout."""
    stdout = process.stdout
    assert stdout is not None  # piped
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ready, _, _ = select.select([stdout], [], [], 0.2)
        if ready:
            return stdout.readline()
        if process.poll() is not None:
            return ""
    return ""
