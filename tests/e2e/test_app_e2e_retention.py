"""Recordings under the cell file's retention, as the data folder and the History show them.

Three `vservo run`s of the demo job, as real processes, on a cell file whose `[recordings]`
keeps one run's recording: the oldest two recordings are gone from the disk, the newest is
there; then `vservo serve` on the same cell file and data folder, and the History in headless
Chromium lists the three runs, the oldest two with "recording removed".
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.chromium import chromium_or_fail, headless_chromium
from vservo.app.browser import ServeProcess, open_pages

SHIPPED_CELL = Path(__file__).resolve().parents[2] / "static" / "cell.toml"
TOKEN = "e2e-retention-token"
RUNS, KEEP = 3, 1


def _cell_keeping(folder: Path, keep_runs: int) -> Path:
    """The shipped cell file with a [recordings] table that keeps ``keep_runs`` runs' recordings."""
    text = SHIPPED_CELL.read_text()
    assert "[recordings]" not in text  # the table below is the file's only one
    cell = folder / "keep.toml"
    cell.write_text(f"{text}\n[recordings]\nkeep_runs = {keep_runs}\nmax_gb = 1\n")
    return cell


def test_runs_beyond_keep_runs_lose_their_recordings_and_the_history_says_recording_removed(tmp_path):
    chromium_or_fail()
    cell, data = _cell_keeping(tmp_path, KEEP), tmp_path / "data"
    for _ in range(RUNS):
        done = subprocess.run(
            [sys.executable, "-m", "vservo.app.cli", "--cell", str(cell), "run", "--job", "demo", "--data", str(data)],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr
    assert sorted(path.name for path in (data / "runs").iterdir()) == [f"{RUNS:06d}"]  # the newest run's alone

    with ServeProcess.start(data, TOKEN, cycle_period_s=0.0, cell=str(cell)) as serve, headless_chromium() as chromium:
        page = open_pages(chromium, serve.url, [(1400, 900)])[0]
        page.get_by_role("tab", name="History").click()
        rows = page.locator("tr", has_text="demo")
        page.locator("tr", has_text="recording removed").nth(RUNS - KEEP - 1).wait_for(timeout=30_000)
        table = {row.locator("td").first.inner_text().strip(): row.inner_text() for row in rows.all()}
    assert sorted(table) == [str(run) for run in range(1, RUNS + 1)], table
    assert all("recording removed" in table[str(run)] for run in range(1, RUNS - KEEP + 1)), table
    assert "kept" in table[str(RUNS)] and "recording removed" not in table[str(RUNS)], table
