"""Where a study snapshot came from: the code's commit, the cell file's hash, the date and
the command that makes it again.

A committed snapshot (static/study/) is only worth its numbers if a reader can tell which
code and which cell produced them; tests/study/test_study.py re-runs it against this record.
"""

from __future__ import annotations

import hashlib
import shlex
import subprocess
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from vservo.core.sim import Arm

UNKNOWN = "unknown"


@dataclass(frozen=True)
class Provenance:
    commit: str  # git rev-parse HEAD, "-dirty" appended when tracked files were changed; or "unknown"
    cell: str  # the cell file's name as the study read it
    cell_sha256: str
    date: str  # UTC, ISO 8601 to the second
    command: str  # the command line that makes the same snapshot

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _git(*args: str) -> str:
    """One git command run beside this module's source; raises when git cannot answer."""
    here = Path(__file__).resolve()
    return subprocess.run(["git", *args], cwd=here.parent, capture_output=True, text=True, check=True, timeout=30).stdout.strip()


def source_commit() -> str:
    """The commit of the code that runs, with "-dirty" when tracked files differ from it.

    An installed copy (no git, or a folder that is not a checkout of vservo) gives
    "unknown": the module must be tracked by the repository git finds, so a virtual
    environment that happens to sit inside some other checkout does not lend its commit.
    """
    try:
        _git("ls-files", "--error-unmatch", Path(__file__).name)
        commit = _git("rev-parse", "HEAD")
        dirty = _git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return UNKNOWN
    return f"{commit}-dirty" if dirty else commit


def reproduce_command(out: Path, cell_path: str | Path | None, montecarlo_n: int, seed: int, arm: Arm = Arm.UPJ) -> str:
    """The ``vservo reproduce`` command line that makes a snapshot with these arguments."""
    args = ["vservo", "reproduce", "--out", str(out), "--montecarlo", str(montecarlo_n), "--seed", str(seed)]
    if arm is not Arm.UPJ:  # the arm is the default: a snapshot of the thesis's cell keeps its command
        args += ["--arm", arm.value]
    if cell_path is not None:
        args += ["--cell", str(cell_path)]
    return shlex.join(args)


def record(cell_source: str, cell_bytes: bytes, command: str) -> Provenance:
    """The provenance of a snapshot made now, from this code and this cell file."""
    return Provenance(
        commit=source_commit(),
        cell=cell_source,
        cell_sha256=hashlib.sha256(cell_bytes).hexdigest(),
        date=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        command=command,
    )
