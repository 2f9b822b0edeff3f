"""Recording a run and playing it back: exact frames, JSON-able cycles, crash tolerance."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import numpy as np
import pytest

from vservo.core.geometry.spatial import Pose6
from vservo.core.perception.camera_source import CameraSourceError, Frame, FrameSource, SourceLost
from vservo.core.perception.recording import (
    FORMAT_VERSION,
    PlaybackSource,
    RecorderThread,
    Recording,
    RecordingError,
    RunRecorder,
    to_jsonable,
    write_atomic,
)
from vservo.core.servo.laws.base import ControlOutput, Failure

SIZE = (40, 30)  # width, height
META = {"cell": "pedestal", "camera": {"index": 0, "model": "mono"}, "fx": np.float64(800.0)}


class Stage(Enum):
    COARSE = "coarse"
    FINE = "fine"


@dataclass(frozen=True)
class Twist:
    v: np.ndarray
    w: np.ndarray


def make_frames(n: int, seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    return [Frame(rng.integers(0, 256, (SIZE[1], SIZE[0]), dtype=np.uint8), 10.0 + 0.04 * i, 5 + i) for i in range(n)]


def cycle(i: int) -> dict:
    return {
        "iteration": i,
        "time_s": np.float64(0.04 * i),
        "corners_px": np.array([[1.0, 2.0], [np.nan, np.nan]]),
        "command": Twist(np.array([0.0, 0.0, 0.01]), np.zeros(3)),
        "stage": Stage.COARSE,
        "error_px": float("nan"),
    }


def write_run(folder: Path, n: int = 4, skip: set[int] = frozenset()) -> list[Frame]:
    """n cycles; the cycles in ``skip`` have no new frame. Returns the frames recorded."""
    frames = make_frames(n)
    recorded = []
    with RunRecorder(folder, META) as recorder:
        for i in range(n):
            frame = None if i in skip else frames[i]
            recorder.record(frame, cycle(i))
            if frame is not None:
                recorded.append(frame)
    return recorded


def test_round_trip_frames_and_cycles(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    recorded = write_run(folder, n=5, skip={2})
    recording = Recording.open(folder)

    assert recording.meta["version"] == FORMAT_VERSION
    assert recording.description == {"cell": "pedestal", "camera": {"index": 0, "model": "mono"}, "fx": 800.0}
    assert recording.image_size == SIZE
    assert recording.summary["cycles"] == 5 and recording.summary["frames"] == 4
    assert recording.complete and not recording.truncated_last_line

    assert len(recording.cycles) == 5
    first = recording.cycles[0]
    assert first["iteration"] == 0
    assert first["corners_px"] == [[1.0, 2.0], [None, None]]
    assert first["command"] == {"v": [0.0, 0.0, 0.01], "w": [0.0, 0.0, 0.0]}
    assert first["stage"] == "coarse"
    assert first["error_px"] is None
    assert first["frame"] == {"file": "frames/000000.png", "timestamp_s": 10.0, "index": 5}
    assert recording.cycles[2]["frame"] is None
    assert recording.cycles[3]["frame"]["file"] == "frames/000002.png"

    assert [p.name for p in recording.frame_paths] == ["000000.png", "000001.png", "000002.png", "000003.png"]
    played = list(recording.frames())
    assert len(played) == len(recorded) == 4
    for got, want in zip(played, recorded):
        np.testing.assert_array_equal(got.image, want.image)  # lossless
        assert got.timestamp_s == want.timestamp_s and got.index == want.index
    assert recording.frame_of(recording.cycles[2]) is None
    np.testing.assert_array_equal(recording.frame_of(recording.cycles[4]).image, recorded[3].image)


def test_a_recorder_thread_writes_the_cycles_in_order_and_a_failed_write_stops_it(tmp_path: Path) -> None:
    frames = make_frames(6)
    recorder = RecorderThread(RunRecorder(tmp_path / "run", META))
    for i in range(4):
        recorder.record(None if i == 2 else frames[i], cycle(i))
    recorder.close({"placed": True})
    recording = Recording.open(tmp_path / "run")
    assert [line["iteration"] for line in recording.cycles] == [0, 1, 2, 3]
    assert recording.summary["frames"] == 3 and recording.summary["outcome"] == {"placed": True}
    np.testing.assert_array_equal(recording.frame_of(recording.cycles[1]).image, frames[1].image)

    recorder = RecorderThread(RunRecorder(tmp_path / "failing", META))
    recorder.record(frames[0], cycle(0))
    recorder.record(frames[1], {"iteration": 1, "command": object()})  # a value JSON cannot hold: the write fails
    with pytest.raises(RecordingError, match="recording stopped at cycle 2: .*cannot store a object"):
        for i in range(2, 200):  # raised by a record once the writer met it
            recorder.record(frames[i % 6], cycle(i))
    with pytest.raises(RecordingError, match="recording stopped at cycle 2"):
        recorder.close({"placed": True})
    recording = Recording.open(tmp_path / "failing")
    assert len(recording.cycles) == 1 and recording.summary["outcome"]["aborted"].startswith("recording stopped at cycle 2")


def test_cycle_lines_are_strict_json(tmp_path: Path) -> None:
    write_run(tmp_path / "run", n=2)
    for line in (tmp_path / "run" / "cycles.jsonl").read_text().splitlines():
        json.loads(line, parse_constant=pytest.fail)  # no NaN / Infinity tokens


def test_to_jsonable() -> None:
    output = ControlOutput(np.zeros(6), "ibvs", float("nan"), 2.5, failure=Failure.NO_PROGRESS)
    assert to_jsonable(output) == {
        "cVc": [0.0] * 6,
        "stage": "ibvs",
        "error_px": None,
        "stage_error": 2.5,
        "converged": False,
        "failure": "no_progress",
        "note": "",
        "distance_m": None,
    }
    assert to_jsonable(Pose6(1, 2, 3, 0.1, 0.2, 0.3))["theta"] == 0.2
    assert to_jsonable({"a": (np.int64(3), np.bool_(True), math.inf, np.float32(0.5)), 7: None}) == {
        "a": [3, True, None, 0.5],
        "7": None,
    }
    assert type(to_jsonable(np.int32(4))) is int
    assert to_jsonable(np.array([[1, 2]], dtype=np.uint8)) == [[1, 2]]
    with pytest.raises(TypeError, match=r"value\['x'\]\[1\]: cannot store a object"):
        to_jsonable({"x": [1, object()]})
    with pytest.raises(TypeError, match="keys are strings"):
        to_jsonable({(1, 2): 3})


def test_meta_write_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    folder = tmp_path / "run"
    recorder = RunRecorder(folder, META)
    recorder.record(make_frames(1)[0], cycle(0))
    before = (folder / "meta.json").read_bytes()

    def failing_replace(src, dst):
        raise OSError("disk pulled")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(RecordingError, match="meta.json.*disk pulled"):
        recorder.close({"converged": True})
    monkeypatch.undo()

    assert (folder / "meta.json").read_bytes() == before  # the old meta, whole
    assert json.loads(before)["summary"] is None
    assert sorted(p.name for p in folder.iterdir()) == ["cycles.jsonl", "frames", "meta.json"]  # no temporary left
    assert Recording.open(folder).summary is None  # readable: a run that did not close


def test_write_atomic_keeps_old_content(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "file.bin"
    write_atomic(path, b"old")
    monkeypatch.setattr(os, "replace", lambda src, dst: (_ for _ in ()).throw(OSError("boom")))
    with pytest.raises(OSError, match="boom"):
        write_atomic(path, b"new content")
    assert path.read_bytes() == b"old"
    assert list(tmp_path.iterdir()) == [path]


def test_summary_records_outcome_and_abort(tmp_path: Path) -> None:
    with RunRecorder(tmp_path / "ok", META) as recorder:
        recorder.record(None, {"iteration": 0})
        recorder.close({"converged": True, "failure": None})
    summary = Recording.open(tmp_path / "ok").summary
    assert summary["outcome"] == {"converged": True, "failure": None}
    assert summary["frames"] == 0 and summary["first_frame_time_s"] is None

    with pytest.raises(KeyboardInterrupt):
        with RunRecorder(tmp_path / "aborted", META) as recorder:
            recorder.record(make_frames(1)[0], {"iteration": 0})
            raise KeyboardInterrupt("operator stop")
    summary = Recording.open(tmp_path / "aborted").summary
    assert summary["aborted"] == "KeyboardInterrupt: operator stop"
    assert summary["frames"] == 1


def test_refuses_to_overwrite(tmp_path: Path) -> None:
    write_run(tmp_path / "run", n=1)
    with pytest.raises(RecordingError, match="not empty"):
        RunRecorder(tmp_path / "run", META)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("keep me")
    with pytest.raises(RecordingError, match="not empty"):
        RunRecorder(tmp_path / "other", META)
    assert (tmp_path / "other" / "notes.txt").read_text() == "keep me"
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(RecordingError, match="not a folder"):
        RunRecorder(tmp_path / "a_file", META)
    (tmp_path / "empty").mkdir()
    RunRecorder(tmp_path / "empty", META).close()  # an empty folder is fine


def test_recorder_rejects_bad_input(tmp_path: Path) -> None:
    with RunRecorder(tmp_path / "run", META) as recorder:
        with pytest.raises(ValueError, match="'frame'"):
            recorder.record(None, {"frame": 3})
        with pytest.raises(TypeError, match=r"cycle\['bad'\]"):
            recorder.record(make_frames(1)[0], {"bad": object()})
        assert recorder.frame_count == 0 and not any((tmp_path / "run" / "frames").iterdir())  # no orphan frame
        recorder.record(make_frames(1)[0], {})
        small = Frame(np.zeros((3, 4), np.uint8), 0.0, 9)
        with pytest.raises(RecordingError, match="4x3.*40x30"):
            recorder.record(small, {})
    with pytest.raises(RecordingError, match="closed"):
        recorder.record(None, {})
    with pytest.raises(TypeError):
        RunRecorder(tmp_path / "other", meta=["not", "a", "dict"])


def test_corrupt_middle_line_names_its_number(tmp_path: Path) -> None:
    write_run(tmp_path / "run", n=4)
    path = tmp_path / "run" / "cycles.jsonl"
    lines = path.read_text().splitlines(keepends=True)
    lines[2] = lines[2][:1] + "#garbage#" + lines[2][1:]  # outside any string
    path.write_text("".join(lines))
    with pytest.raises(RecordingError, match=r"cycles\.jsonl' line 3: not valid JSON"):
        Recording.open(tmp_path / "run")


def test_corrupt_complete_last_line_is_an_error(tmp_path: Path) -> None:
    write_run(tmp_path / "run", n=3)
    path = tmp_path / "run" / "cycles.jsonl"
    path.write_text(path.read_text() + '{"iteration": 3,\n')
    with pytest.raises(RecordingError, match="line 4"):
        Recording.open(tmp_path / "run")


def test_blank_line_is_an_error(tmp_path: Path) -> None:
    write_run(tmp_path / "run", n=3)
    path = tmp_path / "run" / "cycles.jsonl"
    lines = path.read_text().splitlines(keepends=True)
    path.write_text(lines[0] + "\n" + "".join(lines[1:]))
    with pytest.raises(RecordingError, match="line 2"):
        Recording.open(tmp_path / "run")


def test_truncated_last_line_is_tolerated_and_flagged(tmp_path: Path) -> None:
    write_run(tmp_path / "run", n=4)
    path = tmp_path / "run" / "cycles.jsonl"
    data = path.read_bytes()
    path.write_bytes(data[:-25])  # a crash in the middle of appending the 4th line
    recording = Recording.open(tmp_path / "run")
    assert recording.truncated_last_line and not recording.complete
    assert [c["iteration"] for c in recording.cycles] == [0, 1, 2]
    assert len(list(recording.frames())) == 3


def test_last_line_missing_only_its_newline_is_kept(tmp_path: Path) -> None:
    write_run(tmp_path / "run", n=3)
    path = tmp_path / "run" / "cycles.jsonl"
    path.write_bytes(path.read_bytes()[:-1])
    recording = Recording.open(tmp_path / "run")
    assert len(recording.cycles) == 3 and not recording.truncated_last_line


def test_missing_frame_is_named(tmp_path: Path) -> None:
    write_run(tmp_path / "run", n=3)
    (tmp_path / "run" / "frames" / "000001.png").unlink()
    with pytest.raises(RecordingError, match=r"line 2: frame .*frames/000001\.png' is missing"):
        Recording.open(tmp_path / "run")


def test_bad_frame_reference_is_an_error(tmp_path: Path) -> None:
    write_run(tmp_path / "run", n=2)
    path = tmp_path / "run" / "cycles.jsonl"
    path.write_text(path.read_text().replace("frames/000001.png", "../../etc/passwd"))
    with pytest.raises(RecordingError, match="line 2: bad frame reference"):
        Recording.open(tmp_path / "run")


def test_meta_problems(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="does not exist"):
        Recording.open(tmp_path / "nothing")
    write_run(tmp_path / "run", n=1)
    meta_path = tmp_path / "run" / "meta.json"
    meta = json.loads(meta_path.read_text())

    meta_path.write_text(json.dumps({**meta, "version": 99}))
    with pytest.raises(RecordingError, match="meta.json.*version 99 is not supported"):
        Recording.open(tmp_path / "run")
    meta_path.write_text('{"format": "vservo-rec')
    with pytest.raises(RecordingError, match="meta.json.*not valid JSON"):
        Recording.open(tmp_path / "run")
    meta_path.unlink()
    with pytest.raises(RecordingError, match="meta.json.*missing"):
        Recording.open(tmp_path / "run")


def test_playback_yields_frames_in_order_then_source_lost(tmp_path: Path) -> None:
    recorded = write_run(tmp_path / "run", n=4, skip={1})
    with PlaybackSource(Recording.open(tmp_path / "run")) as source:
        assert isinstance(source, FrameSource)
        assert source.image_size == SIZE
        played = [source.read() for _ in range(3)]
        with pytest.raises(SourceLost, match="end of recording.*3 frames"):
            source.read()
        with pytest.raises(SourceLost):
            source.read()
    assert [f.timestamp_s for f in played] == [f.timestamp_s for f in recorded]
    assert [f.index for f in played] == [5, 7, 8]
    for got, want in zip(played, recorded):
        np.testing.assert_array_equal(got.image, want.image)
    with pytest.raises(CameraSourceError, match="closed"):
        source.read()


def test_realtime_playback_paces_frames(tmp_path: Path) -> None:
    write_run(tmp_path / "run", n=3)  # recorded 0.04 s apart
    now = [50.0]
    sleeps: list[float] = []

    def sleep(seconds: float) -> None:
        sleeps.append(seconds)
        now[0] += seconds

    source = PlaybackSource(Recording.open(tmp_path / "run"), realtime=True, sleep=sleep, clock=lambda: now[0])
    source.read()
    now[0] += 0.01  # the consumer took 10 ms
    source.read()
    now[0] += 0.05  # late: no wait
    source.read()
    assert sleeps == pytest.approx([0.03])
