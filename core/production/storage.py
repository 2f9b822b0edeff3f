"""Jobs and runs in SQLite, images and recordings on disk beside it (docs/architecture.md, "Storage").

The data folder holds ``vservo.sqlite`` (the jobs, every assembly attempt), ``images/``
(each job's desired image, PNG, and its check view's image beside it as
``<name>.check.png``) and ``runs/`` (a recording per run). A job's row and its images are
written so that a crash leaves the old job or the new one: the images go to new files
first, the row's transaction then points at them. A row that cannot be
read (a corrupt or hand-edited record) is listed with what is wrong with it, never
silently dropped, and nothing else is lost.

The shipped demo job (static/jobs/demo.json) is available in every store under its
name until a job of that name is saved.

Recordings are kept under the cell file's ``[recordings]`` retention: after each run the
oldest are removed until the newest ``keep_runs`` remain within ``max_gb``; their runs stay
listed, marked as having had their recording removed.

One controller at a time: ``Store.for_controller`` takes an exclusive lock on the folder
(``controller.lock``, holding the owner's PID), since a second controller would mark the
first one's live run interrupted. SQLite waits BUSY_TIMEOUT_S for a lock another program
holds, then fails in one line naming the file.
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import shutil
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TextIO

import cv2
import numpy as np

from vservo.core.cell.config import RecordingRetention
from vservo.core.errors import VservoError
from vservo.core.perception.recording import write_atomic
from vservo.core.production.jobs import Job, JobError, job_from_json, read_job_file, validate_job_name
from vservo.core.production.protocol.commands import PART_ID, PART_ID_WORDS, JobEntry
from vservo.core.production.protocol.state import Outcome

SCHEMA_VERSION = 2
DEMO_JOB = "demo"
BUSY_TIMEOUT_S = 10.0  # how long a write waits for another program's lock on the database
LOCK_FILE = "controller.lock"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS jobs (
    name TEXT PRIMARY KEY,
    body TEXT NOT NULL,
    image TEXT,
    saved_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    job TEXT NOT NULL,
    backend TEXT NOT NULL,
    started_at REAL NOT NULL,
    finished_at REAL,
    outcome TEXT,
    reason TEXT,
    final_error_px REAL,
    placement_error_mm REAL,
    duration_s REAL,
    stages TEXT,
    recording TEXT,
    recording_bytes INTEGER,
    recording_removed_at REAL,
    part_id TEXT
);
"""
# How a store of an older schema is brought to SCHEMA_VERSION: version -> its statements.
_MIGRATIONS = {
    2: (
        "ALTER TABLE runs ADD COLUMN recording_bytes INTEGER",
        "ALTER TABLE runs ADD COLUMN recording_removed_at REAL",
        "ALTER TABLE runs ADD COLUMN part_id TEXT",
    ),
}


class StoreError(VservoError, RuntimeError):
    """The data folder cannot be used; the message names the file and the cause."""


@dataclass(frozen=True)
class RunRecord:
    """One assembly attempt."""

    id: int
    job: str
    backend: str
    started_at: float
    finished_at: float | None
    outcome: Outcome | None  # None while it runs (or if the process died during it)
    reason: str | None
    final_error_px: float | None
    placement_error_mm: float | None
    duration_s: float | None
    stages: list[dict]
    recording: str | None
    recording_removed_at: float | None = None  # the retention removed its recording then
    part_id: str | None = None  # the part's ID for traceability, when the run was given one


def default_data_dir() -> Path:
    """$VSERVO_DATA, else ~/.local/share/vservo (the XDG data folder)."""
    if os.environ.get("VSERVO_DATA"):
        return Path(os.environ["VSERVO_DATA"])
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base) / "vservo"


def shipped_job_path(name: str) -> Path:
    return Path(str(resources.files("vservo.static").joinpath("jobs", f"{name}.json")))


class Store:
    """The data folder. Safe to use from several threads (one connection, one lock)."""

    def __init__(self, root: str | Path, retention: RecordingRetention = RecordingRetention()) -> None:
        self.root = Path(root)
        self.images = self.root / "images"
        self.runs_dir = self.root / "runs"
        self.retention = retention
        self.path = self.root / "vservo.sqlite"
        self._owner: _FolderLock | None = None
        try:
            self.images.mkdir(parents=True, exist_ok=True)
            self.runs_dir.mkdir(exist_ok=True)
            self._db = sqlite3.connect(self.path, timeout=BUSY_TIMEOUT_S, check_same_thread=False, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.executescript(_SCHEMA)
            row = self._db.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone()
        except (OSError, sqlite3.Error) as exc:
            raise StoreError(f"{self.root}: cannot open the data folder ({exc}){_what_to_do(exc)}") from None
        self._lock = threading.Lock()
        if row is None:
            self._db.execute("INSERT INTO meta VALUES ('schema', ?)", (str(SCHEMA_VERSION),))
        elif not row[0].isdigit() or int(row[0]) > SCHEMA_VERSION:
            raise StoreError(f"{self.path}: schema version {row[0]}, this vservo uses {SCHEMA_VERSION}")
        elif int(row[0]) < SCHEMA_VERSION:
            self._migrate(int(row[0]))

    @classmethod
    def for_controller(cls, root: str | Path, retention: RecordingRetention = RecordingRetention()) -> Store:
        """The store of the one controller that runs on ``root``: refused, naming the folder
        and the other process, while another controller holds it."""
        owner = _FolderLock.take(Path(root))
        try:
            store = cls(root, retention)
        except BaseException:
            owner.release()
            raise
        store._owner = owner
        return store

    def _migrate(self, version: int) -> None:
        """Bring a store of an older schema up to date, in one transaction."""
        with self._transaction() as db:
            for step in range(version + 1, SCHEMA_VERSION + 1):
                for statement in _MIGRATIONS[step]:
                    db.execute(statement)
            db.execute("UPDATE meta SET value = ? WHERE key = 'schema'", (str(SCHEMA_VERSION),))

    def close(self) -> None:
        with self._lock:
            self._db.close()
        if self._owner is not None:
            self._owner.release()

    @contextmanager
    def _reading(self) -> Iterator[sqlite3.Connection]:
        """The connection for a query, its failures one StoreError naming the file."""
        with self._lock:
            try:
                yield self._db
            except sqlite3.Error as exc:
                raise StoreError(f"{self.path}: {exc}{_what_to_do(exc)}") from None

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        with self._reading() as db:
            db.execute("BEGIN IMMEDIATE")
            try:
                yield db
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")

    # -- jobs ------------------------------------------------------------------------

    def save_job(self, job: Job, image: np.ndarray | None = None, check_image: np.ndarray | None = None) -> None:
        """Save (or replace) a job, its desired image and the image of its check view.

        The check image is named after the desired image it goes with: a new desired
        image replaces both, a job saved without one keeps both.
        """
        if check_image is not None and image is None:
            raise StoreError(f"job {job.name!r}: a check image is saved with its desired image, not alone")
        image_name = None
        if image is not None:
            image_name = f"{job.name}-{time.time_ns()}.png"
            if check_image is not None:
                write_atomic(self.images / _check_name(image_name), _png(job, check_image, "check"))
            write_atomic(self.images / image_name, _png(job, image, "desired"))
        with self._transaction() as db:
            old = db.execute("SELECT image FROM jobs WHERE name = ?", (job.name,)).fetchone()
            db.execute(
                "INSERT OR REPLACE INTO jobs (name, body, image, saved_at) VALUES (?, ?, ?, ?)",
                (job.name, json.dumps(job.as_dict()), image_name or (old[0] if old else None), time.time()),
            )
        if image_name and old and old[0]:
            self._remove_images(old[0])

    def _remove_images(self, image_name: str) -> None:
        (self.images / image_name).unlink(missing_ok=True)
        (self.images / _check_name(image_name)).unlink(missing_ok=True)

    def load_job(self, name: str) -> Job:
        validate_job_name(name)
        with self._reading() as db:
            row = db.execute("SELECT body FROM jobs WHERE name = ?", (name,)).fetchone()
        if row is None:
            if name == DEMO_JOB:
                return read_job_file(shipped_job_path(DEMO_JOB))
            raise JobError(f"no job named {name!r} (jobs: {', '.join(e.name for e in self.list_jobs()) or 'none'})")
        return job_from_json(row[0], f"job {name!r} in {self.root / 'vservo.sqlite'}")

    def job_image(self, name: str, check: bool = False) -> np.ndarray | None:
        """The job's desired image (``check``: its check view's image), or None if it has none."""
        with self._reading() as db:
            row = db.execute("SELECT image FROM jobs WHERE name = ?", (name,)).fetchone()
        if row is None and name == DEMO_JOB:
            path = shipped_job_path(DEMO_JOB).with_suffix(".png")
        elif row is None or row[0] is None:
            return None
        else:
            path = self.images / row[0]
        if check:
            path = path.with_name(_check_name(path.name))
            if not path.exists():
                return None
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise StoreError(f"job {name!r}: its {'check' if check else 'desired'} image {path} is missing or unreadable")
        return image

    def list_jobs(self) -> list[JobEntry]:
        with self._reading() as db:
            rows = db.execute("SELECT name, body, saved_at FROM jobs ORDER BY name").fetchall()
        entries = []
        for name, body, saved_at in rows:
            try:
                job_from_json(body, f"job {name!r}")
                problem = None
            except JobError as exc:
                problem = str(exc)
            entries.append(JobEntry(name, saved_at, problem))
        if DEMO_JOB not in {e.name for e in entries}:
            entries.insert(0, JobEntry(DEMO_JOB, shipped_job_path(DEMO_JOB).stat().st_mtime, shipped=True))
        return entries

    def delete_job(self, name: str) -> None:
        with self._transaction() as db:
            row = db.execute("SELECT image FROM jobs WHERE name = ?", (name,)).fetchone()
            if row is None:
                raise JobError(f"no job named {name!r}")
            db.execute("DELETE FROM jobs WHERE name = ?", (name,))
        if row[0]:
            self._remove_images(row[0])

    # -- runs ------------------------------------------------------------------------

    def start_run(self, job: str, backend: str, part_id: str | None = None) -> int:
        with self._transaction() as db:
            cursor = db.execute(
                "INSERT INTO runs (job, backend, started_at, part_id) VALUES (?, ?, ?, ?)",
                (job, backend, time.time(), None if part_id is None else validate_part_id(part_id)),
            )
            return int(cursor.lastrowid or 0)

    def run_folder(self, run_id: int) -> Path:
        return self.runs_dir / f"{run_id:06d}"

    def finish_run(
        self,
        run_id: int,
        outcome: Outcome,
        reason: str,
        final_error_px: float | None,
        placement_error_mm: float | None,
        duration_s: float,
        stages: list[dict],
        recording: Path | None,
    ) -> None:
        """The run's end on record, then the retention applied to the recordings. ``recording``
        (its folder) is stored relative to the data folder, so the folder can be moved or
        opened from any working directory."""
        with self._transaction() as db:
            db.execute(
                "UPDATE runs SET finished_at = ?, outcome = ?, reason = ?, final_error_px = ?, placement_error_mm = ?,"
                " duration_s = ?, stages = ?, recording = ?, recording_bytes = ? WHERE id = ?",
                (
                    time.time(),
                    outcome,
                    reason,
                    _finite_or_none(final_error_px),
                    _finite_or_none(placement_error_mm),
                    duration_s,
                    json.dumps(stages),
                    self._stored_path(recording),
                    None if recording is None else _folder_bytes(Path(recording)),
                    run_id,
                ),
            )
        self.apply_retention()

    def apply_retention(self) -> list[int]:
        """Remove the oldest recordings beyond the retention's ``keep_runs`` and ``max_bytes``
        (the newest kept first); their runs stay, marked removed. The runs' ids."""
        with self._reading() as db:
            rows = db.execute(
                "SELECT id, recording, recording_bytes FROM runs WHERE recording IS NOT NULL AND outcome IS NOT NULL "
                "ORDER BY id DESC"
            ).fetchall()
        kept_bytes, removed = 0, []
        for rank, (run_id, stored, size) in enumerate(rows):
            folder = self.root / stored
            kept_bytes += _folder_bytes(folder) if size is None else size
            if rank >= self.retention.keep_runs or kept_bytes > self.retention.max_bytes:
                shutil.rmtree(folder, ignore_errors=True)
                removed.append(run_id)
        if removed:
            with self._transaction() as db:
                db.executemany(
                    "UPDATE runs SET recording = NULL, recording_removed_at = ? WHERE id = ?",
                    [(time.time(), run_id) for run_id in removed],
                )
        return removed

    def close_unfinished_runs(self) -> list[int]:
        """Mark every run without an outcome ``interrupted``, its recording linked if it left
        one: called by a controller as it starts, when no run of this data folder can still
        be under way (a run ends on record unless its process died). The runs' ids."""
        with self._transaction() as db:
            ids = [row[0] for row in db.execute("SELECT id FROM runs WHERE outcome IS NULL ORDER BY id")]
            for run_id in ids:
                folder = self.run_folder(run_id)
                db.execute(
                    "UPDATE runs SET outcome = ?, reason = ?, recording = ? WHERE id = ?",
                    (
                        Outcome.INTERRUPTED,
                        "the controller process ended during the run (found unfinished at its next start)",
                        self._stored_path(folder) if folder.is_dir() else None,
                        run_id,
                    ),
                )
        return ids

    def _stored_path(self, folder: Path | None) -> str | None:
        if folder is None:
            return None
        folder = Path(folder)
        return str(folder.relative_to(self.root)) if folder.is_relative_to(self.root) else str(folder.absolute())

    def list_runs(self, limit: int = 100) -> list[RunRecord]:
        with self._reading() as db:
            rows = db.execute("SELECT * FROM runs ORDER BY id DESC LIMIT ?", (limit,)).fetchall()
        return [self._run_record(row) for row in rows]

    def runs_between(self, since_s: float = 0.0, until_s: float = math.inf) -> list[RunRecord]:
        """The runs started from ``since_s`` until before ``until_s`` (Unix times), oldest first."""
        with self._reading() as db:
            rows = db.execute(
                "SELECT * FROM runs WHERE started_at >= ? AND started_at < ? ORDER BY id", (since_s, min(until_s, 1e300))
            ).fetchall()
        return [self._run_record(row) for row in rows]

    def run(self, run_id: int) -> RunRecord:
        with self._reading() as db:
            row = db.execute("SELECT * FROM runs WHERE id = ?", (run_id,)).fetchone()
        if row is None:
            raise StoreError(f"no run {run_id}")
        return self._run_record(row)

    def _run_record(self, row: tuple) -> RunRecord:
        """A row as a RunRecord, its recording an absolute path (rows stored before the paths
        were relative hold absolute ones, which stay as they are)."""
        recording = row[11] if row[11] is None else str(self.root.absolute() / row[11])
        return _run_record((*row[:11], recording, row[13], row[14]))


class _FolderLock:
    """An exclusive lock on a data folder's LOCK_FILE, which names the process holding it.

    An advisory ``flock``: the kernel releases it when its process ends, however it ends,
    so a controller that was killed never leaves its folder locked.
    """

    def __init__(self, file: TextIO) -> None:
        self._file = file

    @classmethod
    def take(cls, root: Path) -> _FolderLock:
        path = root / LOCK_FILE
        try:
            root.mkdir(parents=True, exist_ok=True)
            file = open(path, "a+")
        except OSError as exc:
            raise StoreError(f"{root}: cannot open the data folder ({exc})") from None
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            file.seek(0)
            holder = file.read().strip() or "unknown"
            file.close()
            raise StoreError(
                f"{root}: the data folder is in use by another vservo controller (PID {holder}); "
                "stop it first, or give this one another --data folder"
            ) from None
        file.truncate(0)
        file.write(f"{os.getpid()}\n")
        file.flush()
        return cls(file)

    def release(self) -> None:
        self._file.close()  # closing the descriptor releases the flock


def _what_to_do(exc: Exception) -> str:
    """The remedy for a database another program holds, said after its error."""
    if isinstance(exc, sqlite3.OperationalError) and ("locked" in str(exc) or "busy" in str(exc)):
        return (
            f" after {BUSY_TIMEOUT_S:g} s: another program holds the database; close it (a second vservo on this "
            "data folder, an SQLite browser) and try again"
        )
    return ""


def _folder_bytes(folder: Path) -> int:
    """The bytes of the files under ``folder`` (0 once it is gone)."""
    return sum(path.stat().st_size for path in folder.rglob("*") if path.is_file()) if folder.is_dir() else 0


def validate_part_id(part_id: object) -> str:
    """A part ID as a PLC, a scanner or an operator gives it: 1 to 64 printable characters."""
    if not isinstance(part_id, str) or not PART_ID.fullmatch(part_id):
        raise StoreError(f"part ID {part_id!r}: use {PART_ID_WORDS}")
    return part_id


def _check_name(image_name: str) -> str:
    """The check image's file name beside its desired image's: demo.png -> demo.check.png."""
    return image_name.removesuffix(".png") + ".check.png"


def _png(job: Job, image: np.ndarray, what: str) -> bytes:
    ok, png = cv2.imencode(".png", image)
    if not ok:
        raise StoreError(f"job {job.name!r}: the {what} image cannot be encoded as PNG")
    return png.tobytes()


def _finite_or_none(value: float | None) -> float | None:
    return None if value is None or not np.isfinite(value) else float(value)


def _run_record(row: tuple) -> RunRecord:
    try:
        stages = json.loads(row[10]) if row[10] else []
    except json.JSONDecodeError:
        stages = [{"stage": "unreadable stage record", "iterations": 0}]
    outcome = Outcome(row[5]) if row[5] is not None else None
    return RunRecord(
        row[0], row[1], row[2], row[3], row[4], outcome, row[6], row[7], row[8], row[9], stages, row[11], row[12], row[13]
    )
