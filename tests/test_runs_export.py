"""Results for traceability: a part ID on every run, and `vservo runs` exporting the runs
with their figures. Real `vservo run` processes on the simulated cell, a real SQLite store."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys

from vservo.core.production.storage import Store


def vservo(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", *args], capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL
    )


def test_runs_carry_their_part_ids_and_export_as_csv_and_json(tmp_path):
    data = str(tmp_path / "data")
    for seed, part_id in (("1", "P-0001"), ("2", "lot 7 / part 12")):
        run = vservo("run", "--job", "demo", "--data", data, "--seed", seed, "--part-id", part_id, "--json")
        assert run.returncode == 0, run.stderr
        assert json.loads(run.stdout)["part_id"] == part_id
    exported = vservo("runs", "--data", data, "--csv")
    assert exported.returncode == 0, exported.stderr
    rows = list(csv.DictReader(io.StringIO(exported.stdout)))
    assert [row["part_id"] for row in rows] == ["P-0001", "lot 7 / part 12"]
    assert [row["outcome"] for row in rows] == ["placed", "placed"]
    store = Store(data)
    stored = {run.id: run for run in store.list_runs()}
    store.close()
    for row in rows:  # the figures are the stored ones
        assert float(row["placement_error_mm"]) == stored[int(row["id"])].placement_error_mm
        assert row["started_at"].endswith("+00:00")
    as_json = json.loads(vservo("runs", "--data", data, "--json").stdout)
    assert [run["part_id"] for run in as_json] == ["P-0001", "lot 7 / part 12"]
    assert json.loads(vservo("runs", "--data", data, "--json", "--since", "2999-01-01").stdout) == []
    assert json.loads(vservo("runs", "--data", data, "--json", "--until", "2000-01-01").stdout) == []


def test_a_bad_part_id_or_date_is_refused_in_one_line_and_starts_nothing(tmp_path):
    data = str(tmp_path / "data")
    bad = vservo("run", "--job", "demo", "--data", data, "--part-id", "tab\there")
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "part ID" in bad.stderr, bad.stderr
    assert Store(data).list_runs() == []
    date = vservo("runs", "--data", data, "--since", "yesterday")
    assert date.returncode == 2 and "--since" in date.stderr and "ISO 8601" in date.stderr, date.stderr
