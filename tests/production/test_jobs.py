"""Job files and the SQLite store: broken or foreign input gets a clear message, nothing is lost."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from vservo.core.production.assembly import Outcome
from vservo.core.production.jobs import JOB_VERSION, JobError, job_from_dict, read_job_file, write_job_file
from vservo.core.production.storage import DEMO_JOB, Store, StoreError, shipped_job_path


@pytest.fixture
def demo():
    return read_job_file(shipped_job_path(DEMO_JOB))


def test_a_job_survives_the_file_round_trip(tmp_path, demo):
    write_job_file(demo, tmp_path / "j.json")
    again = read_job_file(tmp_path / "j.json")
    assert again.as_dict() == demo.as_dict()


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d.update(format="something-else"), "not a vservo job file"),
        (lambda d: d.update(version=99), "version 99"),
        (lambda d: d.pop("bMe_place"), "bMe_place: missing"),
        (lambda d: d.update(method="magic"), "method: 'magic' is not one of"),
        (lambda d: d.update(threshold_px=-1), "threshold_px: -1 must be positive"),
        (lambda d: d["desired"].update(depth_m=float("nan")), "depth_m: nan is not a finite number"),
        (lambda d: d["desired"].update(corners_px=[[1, 2]]), "corners_px: shape (1, 2), expected (4, 2)"),
        (lambda d: d.update(start_bMe=(2 * np.eye(4)).tolist()), "start_bMe: not a rigid transform"),
        (lambda d: d.update(name="../etc"), "job name '../etc'"),
        (lambda d: d.pop("placement_tolerance_mm"), "placement_tolerance_mm: missing"),
        (lambda d: d.update(grasp_symmetry=3), "job.json: grasp_symmetry: 3 is not one of 1, 2, 4"),
        (lambda d: d.update(grasp_symmetry=True), "grasp_symmetry: True is not one of"),
        (lambda d: d.update(placement_tolerance_mm=0), "placement_tolerance_mm: 0 must be positive"),
        (lambda d: d.update(check=[1, 2]), "job.json: check: not a job"),
        (lambda d: d["check"].update(corners_px=[[1, 2]] * 3), "check: corners_px: shape (3, 2), expected (4, 2)"),
        (lambda d: d["check"].update(check_bMe=(2 * np.eye(4)).tolist()), "check: check_bMe: not a rigid transform"),
        (lambda d: d["check"].pop("check_bMe"), "check: check_bMe: missing"),
        (lambda d: d.pop("taught_model"), "taught_model: missing"),
        (lambda d: d["taught_model"]["camera"].update(fx_px=0), "taught_model: camera: fx_px: 0 must be positive"),
        (lambda d: d["taught_model"]["camera"].update(image_size_px=[640.5, 480]), "is not two positive whole numbers"),
        (
            lambda d: d["taught_model"]["camera"].update(distortion=[0, 0]),
            "taught_model: camera: distortion: shape (2,), expected (5,)",
        ),
        (lambda d: d["taught_model"].update(eMc=(2 * np.eye(4)).tolist()), "taught_model: eMc: not a rigid transform"),
        (lambda d: d["taught_model"].pop("cMl"), "taught_model: cMl: missing"),
        (lambda d: d.pop("survey_bMe"), "survey_bMe: missing"),
        (lambda d: d.update(survey_bMe=[[1, 0], [0, 1]]), "survey_bMe: shape (2, 2), expected (4, 4)"),
    ],
)
def test_a_broken_job_is_refused_naming_the_field(demo, change, message):
    data = json.loads(json.dumps(demo.as_dict()))
    change(data)
    with pytest.raises(JobError, match=message.replace("(", r"\(").replace(")", r"\)")):
        job_from_dict(data, "job.json")


def test_a_job_file_without_a_grasp_symmetry_is_of_a_square_part_and_the_key_survives_the_round_trip(demo):
    data = json.loads(json.dumps(demo.as_dict()))
    data.pop("grasp_symmetry")
    assert job_from_dict(data, "old.json").grasp_symmetry == 4
    data["grasp_symmetry"] = 1
    assert job_from_dict(json.loads(json.dumps(job_from_dict(data, "job.json").as_dict())), "again").grasp_symmetry == 1


def test_a_version_1_job_reads_as_a_job_without_a_check_view(demo):
    data = json.loads(json.dumps(demo.as_dict()))
    data["version"] = 1
    for added in ("check", "placement_tolerance_mm", "taught_model", "survey_bMe"):  # what versions 2, 3 added
        data.pop(added)
    job = job_from_dict(data, "old.json")
    assert job.check is None and job.placement_tolerance_mm == 1.0 and job.taught_model is None
    assert job.as_dict()["version"] == JOB_VERSION and job.as_dict()["check"] is None
    assert job_from_dict(job.as_dict(), "again.json").check is None


def test_a_version_2_job_reads_as_a_job_without_a_taught_model(demo):
    data = json.loads(json.dumps(demo.as_dict()))
    data["version"] = 2
    for added in ("taught_model", "survey_bMe"):  # what version 3 added
        data.pop(added)
    job = job_from_dict(data, "old.json")
    assert job.taught_model is None and job.survey_bMe is None and job.check is not None
    again = job_from_dict(job.as_dict(), "again.json")
    assert again.taught_model is None and again.as_dict()["version"] == JOB_VERSION


def test_the_taught_model_and_the_survey_pose_survive_the_file_round_trip(tmp_path, demo):
    assert demo.taught_model is not None and demo.survey_bMe is None  # the shipped demo does not locate
    survey = demo.start_bMe.copy()
    survey[2, 3] += 0.1
    write_job_file(replace(demo, survey_bMe=survey), tmp_path / "j.json")
    again = read_job_file(tmp_path / "j.json")
    assert np.array_equal(again.survey_bMe, survey)
    assert again.taught_model.as_dict() == demo.taught_model.as_dict()


def test_unreadable_job_files(tmp_path):
    with pytest.raises(JobError, match="no such job file"):
        read_job_file(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(JobError, match="bad.json: not valid JSON"):
        read_job_file(tmp_path / "bad.json")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(JobError, match="not a job"):
        read_job_file(tmp_path / "list.json")


def test_store_keeps_jobs_images_and_runs(tmp_path, demo):
    store = Store(tmp_path)
    assert [e.name for e in store.list_jobs()] == [DEMO_JOB]  # the shipped one, before any is saved
    image = np.full((480, 640), 77, np.uint8)
    store.save_job(replace(demo, name="a"), image)
    store.save_job(replace(demo, name="a", threshold_px=2.0), image + 1)  # replaced, old image removed
    assert store.load_job("a").threshold_px == 2.0
    assert int(store.job_image("a")[0, 0]) == 78
    assert len(list((tmp_path / "images").iterdir())) == 1
    assert store.job_image("a", check=True) is None  # saved without a check image
    store.save_job(replace(demo, name="a"), image, image + 2)
    assert int(store.job_image("a", check=True)[0, 0]) == 79 and int(store.job_image("a")[0, 0]) == 77
    assert len(list((tmp_path / "images").iterdir())) == 2  # the new pair; the old image removed
    store.save_job(replace(demo, name="a", threshold_px=2.5))  # no new images: both kept
    assert int(store.job_image("a", check=True)[0, 0]) == 79
    with pytest.raises(StoreError, match="check image is saved with its desired image"):
        store.save_job(replace(demo, name="b"), None, image)
    assert store.job_image(DEMO_JOB, check=True).shape == (480, 640)  # the shipped demo's
    store.delete_job("a")
    assert not list((tmp_path / "images").iterdir())
    store.save_job(replace(demo, name="a", threshold_px=2.0), image + 1)
    run = store.start_run("a", "sim")
    assert store.run(run).outcome is None
    store.finish_run(run, Outcome.PLACED, "ok", 1.5, 0.2, 3.0, [{"stage": "3", "iterations": 4}], None)
    store.close()
    again = Store(tmp_path)
    record = again.run(run)
    assert (record.outcome, record.final_error_px, record.stages) == (Outcome.PLACED, 1.5, [{"stage": "3", "iterations": 4}])
    again.close()


def test_runs_stored_as_estopped_by_older_versions_read_as_e_stopped(tmp_path):
    store = Store(tmp_path)
    old, new = store.start_run("demo", "sim"), store.start_run("demo", "sim")
    store.finish_run(new, Outcome.ESTOPPED, "e-stop pressed", None, None, 1.0, [], None)
    store.close()
    with sqlite3.connect(tmp_path / "vservo.sqlite") as db:
        db.execute("UPDATE runs SET outcome = 'estopped', reason = 'e-stop pressed' WHERE id = ?", (old,))
        assert db.execute("SELECT outcome FROM runs WHERE id = ?", (new,)).fetchone() == ("e-stopped",)
    again = Store(tmp_path)
    assert again.run(old).outcome is again.run(new).outcome is Outcome.ESTOPPED
    again.close()


def test_a_corrupt_record_is_reported_and_the_others_still_load(tmp_path, demo):
    store = Store(tmp_path)
    store.save_job(replace(demo, name="good"))
    store.save_job(replace(demo, name="bad"))
    store.close()
    with sqlite3.connect(tmp_path / "vservo.sqlite") as db:
        db.execute('UPDATE jobs SET body = \'{"format": "vservo-job", "version": 1}\' WHERE name = \'bad\'')
    store = Store(tmp_path)
    entries = {e.name: e for e in store.list_jobs()}
    assert entries["good"].problem is None
    assert "missing" in entries["bad"].problem
    with pytest.raises(JobError, match="job 'bad'"):
        store.load_job("bad")
    assert store.load_job("good").name == "good"
    store.close()


def test_a_store_from_a_newer_vservo_is_refused(tmp_path):
    Store(tmp_path).close()
    with sqlite3.connect(tmp_path / "vservo.sqlite") as db:
        db.execute("UPDATE meta SET value = '7' WHERE key = 'schema'")
    with pytest.raises(StoreError, match="schema version 7"):
        Store(tmp_path)


@pytest.mark.parametrize(
    ("key", "value", "words"),
    [
        ("approach_m", 1e9, "approach_m must be from 0.005 to 0.2 m, got 1e+09"),
        ("threshold_px", 1e12, "threshold_px must be from 0.1 to 50 px, got 1e+12"),
        ("start_bMe", [[1, 0, 0, 1e300], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "start_bMe's translation must be from -5"),
    ],
)
def test_vservo_run_refuses_a_stored_job_with_a_value_out_of_range_in_one_line(tmp_path, demo, key, value, words):
    """A job row edited past the page's ranges (an approach of 10^9 m hung a run for good, a
    start pose of 10^300 ended in an OverflowError traceback, a threshold of 10^12 px was
    reported placed) is refused by `vservo run` in one line naming the key and the range."""
    store = Store(tmp_path)
    store.save_job(replace(demo, name="edited"))
    store.close()
    db = sqlite3.connect(tmp_path / "vservo.sqlite")
    body = json.loads(db.execute("SELECT body FROM jobs WHERE name = 'edited'").fetchone()[0])
    db.execute("UPDATE jobs SET body = ? WHERE name = 'edited'", (json.dumps({**body, key: value}),))
    db.commit()
    db.close()
    run = subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "run", "--job", "edited", "--data", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2 and len(lines) == 1 and words in lines[0], run.stderr
    assert Store(tmp_path).list_runs() == []  # refused before the run began
