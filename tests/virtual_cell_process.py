"""`vservo virtual-cell` as a child process, for the tests that drive the product on it."""

import json
import select
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


class VirtualCellProcess:
    """`vservo virtual-cell` in a child process: the devices it announced, and its events."""

    def __init__(self, *args: str) -> None:
        self.stderr = tempfile.TemporaryFile("w+")  # a file, not a pipe: nothing can block the cell on it
        self.process = subprocess.Popen(
            [sys.executable, "-m", "vservo.app.cli", "virtual-cell", *args],
            stdout=subprocess.PIPE,
            stderr=self.stderr,
            text=True,
            cwd=ROOT,
        )
        line = self.process.stdout.readline()
        if not line:
            raise AssertionError(f"the virtual cell did not start: {self.log()}")
        self.addresses = json.loads(line)

    def log(self) -> str:
        self.stderr.seek(0)
        return self.stderr.read()

    def next_event(self, timeout_s: float = 60.0) -> dict:
        """The next JSON line it prints (a released part)."""
        if not select.select([self.process.stdout], [], [], timeout_s)[0]:
            raise AssertionError(f"no event from the virtual cell within {timeout_s} s; its log: {self.log()[-2000:]}")
        return json.loads(self.process.stdout.readline())

    def stop(self) -> int:
        """SIGTERM; its exit code."""
        self.process.send_signal(signal.SIGTERM)
        try:
            return self.process.wait(timeout=20)
        finally:
            self.process.stdout.close()
            self.stderr.close()


def long_servo_cell_args(tmp_path: Path, seed: int = 4) -> tuple[str, ...]:
    """`vservo virtual-cell` arguments for a cell in tmp_path on the thesis's step policy: a
    servo long enough to stop, kill or unplug something in the middle of."""
    from tests.jrc_fixtures import thesis_policy_cell_file
    from vservo.app.browser import free_port

    return (
        "--seed",
        str(seed),
        "--jrc-link",
        str(tmp_path / "jrc"),
        "--camera-port",
        str(free_port()),
        "--fixture-port",
        str(free_port()),
        "--out",
        str(tmp_path / "cell.toml"),
        "--cell",
        thesis_policy_cell_file(tmp_path),
    )
