"""The data folder under load and over time (docs/reliability.md): one controller per
folder, a database another program holds, recordings under the cell file's retention.
Real processes, a real SQLite lock, real runs on the simulated cell."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

from vservo.core.cell.config import ConfigError, RecordingRetention, load_cell, parse_cell, read_cell_bytes
from vservo.core.production import storage
from vservo.core.production.assembly import Outcome
from vservo.core.production.cell_controller import CellController
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.production.storage import Store, StoreError


def vservo(*args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        stdin=subprocess.DEVNULL,
    )


def test_a_second_controller_on_a_data_folder_is_refused_naming_the_folder_and_the_pid(tmp_path):
    """A controller process holds the folder; `vservo run` on it is refused in one line
    naming the folder and that process, and leaves the first one's runs alone."""
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            textwrap.dedent(f"""
                import sys
                from vservo.core.production.storage import Store
                store = Store.for_controller({str(tmp_path)!r})
                store.start_run("demo", "sim")  # a live run, which a second controller would mark interrupted
                print("holding", flush=True)
                sys.stdin.read()
            """),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "holding"
        result = vservo("run", "--job", "demo", "--data", str(tmp_path))
        assert result.returncode == 2
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1, result.stderr
        assert str(tmp_path) in lines[0] and f"PID {holder.pid}" in lines[0]
        assert Store(tmp_path).list_runs()[0].outcome is None  # the holder's run is still live
    finally:
        holder.stdin.close()
        holder.wait(30)
    # The holder is gone: its lock went with it.
    Store.for_controller(tmp_path).close()


def test_a_database_locked_by_another_program_fails_in_one_line_after_the_busy_timeout(tmp_path, monkeypatch):
    monkeypatch.setattr(storage, "BUSY_TIMEOUT_S", 0.2)
    store = Store(tmp_path)
    other = sqlite3.connect(tmp_path / "vservo.sqlite", isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    try:
        with pytest.raises(StoreError) as refused:
            store.start_run("demo", "sim")
        message = str(refused.value)
        assert "\n" not in message and str(tmp_path / "vservo.sqlite") in message
        assert "another program holds the database" in message
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert store.start_run("demo", "sim") == 1  # the lock gone, the store works on
    store.close()


def test_vservo_run_on_a_locked_database_says_one_line_naming_the_file(tmp_path):
    Store(tmp_path).close()
    other = sqlite3.connect(tmp_path / "vservo.sqlite", isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    try:
        result = vservo("run", "--job", "demo", "--data", str(tmp_path))
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "vservo.sqlite" in lines[0] and "Traceback" not in result.stderr, result.stderr


def test_a_store_of_the_first_schema_is_migrated_and_keeps_its_runs(tmp_path):
    old = sqlite3.connect(tmp_path / "vservo.sqlite", isolation_level=None)
    old.executescript(
        """
        CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
        CREATE TABLE jobs (name TEXT PRIMARY KEY, body TEXT NOT NULL, image TEXT, saved_at REAL NOT NULL);
        CREATE TABLE runs (id INTEGER PRIMARY KEY AUTOINCREMENT, job TEXT NOT NULL, backend TEXT NOT NULL,
            started_at REAL NOT NULL, finished_at REAL, outcome TEXT, reason TEXT, final_error_px REAL,
            placement_error_mm REAL, duration_s REAL, stages TEXT, recording TEXT);
        INSERT INTO meta VALUES ('schema', '1');
        INSERT INTO runs (job, backend, started_at, outcome) VALUES ('demo', 'sim', 1.0, 'placed');
        """
    )
    old.close()
    store = Store(tmp_path)
    (run,) = store.list_runs()
    assert run.outcome is Outcome.PLACED and run.recording_removed_at is None
    store.close()
    assert sqlite3.connect(tmp_path / "vservo.sqlite").execute("SELECT value FROM meta").fetchone() == ("2",)


def test_the_retention_keeps_the_newest_runs_recordings_and_marks_the_rest_removed(tmp_path):
    """Five real runs of the demo on the simulated cell, the retention keeping two: the
    three oldest recordings are gone from the disk, their runs still listed and marked."""
    store = Store(tmp_path, RecordingRetention(keep_runs=2, max_bytes=10**12))
    controller = CellController(simulated_rig(load_cell(), seed=3), store, seed=3)
    for _ in range(5):
        controller.present_part()
        controller.start("demo")
        controller.wait()
    controller.close()
    runs = store.list_runs()  # newest first
    assert [run.outcome for run in runs] == [Outcome.PLACED] * 5
    assert all(run.recording is not None and Path(run.recording).is_dir() for run in runs[:2])
    assert all(run.recording is None and run.recording_removed_at is not None for run in runs[2:])
    assert sorted(path.name for path in (tmp_path / "runs").iterdir()) == [f"{run.id:06d}" for run in reversed(runs[:2])]
    store.close()


def test_the_retention_bounds_the_recordings_bytes(tmp_path):
    """Recordings of 1000 bytes each under a 2500-byte bound: the newest two stay."""
    store = Store(tmp_path, RecordingRetention(keep_runs=100, max_bytes=2500))
    for _ in range(4):
        run_id = store.start_run("demo", "sim")
        folder = store.run_folder(run_id)
        folder.mkdir()
        (folder / "frames.bin").write_bytes(bytes(1000))
        store.finish_run(run_id, Outcome.PLACED, "placed", 0.1, 0.01, 1.0, [], folder)
    kept = [run.id for run in store.list_runs() if run.recording is not None]
    assert kept == [4, 3]
    assert sorted(path.name for path in (tmp_path / "runs").iterdir()) == ["000003", "000004"]
    store.close()


@pytest.mark.parametrize(
    ("line", "names"),
    [("keep_runs = 0", "recordings.keep_runs = 0"), ("max_gb = -1", "recordings.max_gb = -1"), ("max_gb = 1e300", "1e+300")],
)
def test_a_retention_out_of_range_is_refused_naming_the_key(line, names):
    text = read_cell_bytes()[0].decode() + f"\n[recordings]\n{line}\n"
    with pytest.raises(ConfigError, match=names.replace("+", r"\+")):
        parse_cell(tomllib.loads(text), "cell.toml")
