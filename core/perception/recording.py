"""Recording a servo run to disk and playing it back.

A recording is a folder::

    meta.json      format and version, creation time, the caller's description of the
                   cell and source, the image size, and a summary written at close
    frames/        000000.png, 000001.png, ... lossless monochrome PNGs, in recording order
    cycles.jsonl   one JSON object per cycle, one line each, in the order recorded

Each cycle line is the caller's dict (iteration, time, features, command, stage,
verdict, ...) made JSON-able by ``to_jsonable``, plus the key ``"frame"`` the recorder
adds: ``{"file": "frames/000003.png", "timestamp_s": ..., "index": ...}`` for the frame
recorded with that cycle (its source's timestamp and frame counter), or null for a cycle
that had no new frame. Non-finite floats are written as null: JSON has no NaN.

Crash safety: every PNG and meta.json is written to a temporary file and moved into
place with ``os.replace``, so a reader sees the old file or the new one, never half of
one. Cycle lines are appended with one write each and flushed, so a crash of the
process leaves every complete line readable; at worst the last line is cut short
(``Recording.truncated_last_line``). ``fsync=True`` also survives a crash of the
machine, at the cost of a disk sync per cycle.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import queue
import re
import threading
import time
from collections.abc import Callable, Generator, Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from enum import Enum
from pathlib import Path, PurePath
from typing import Any, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from vservo.core.errors import VservoError
from vservo.core.perception.camera_source import BaseSource, Frame, Size, SourceLost

log = logging.getLogger("vservo.recording")

FORMAT_NAME = "vservo-recording"
FORMAT_VERSION = 1
SUPPORTED_VERSIONS = (1,)

META_FILE = "meta.json"
CYCLES_FILE = "cycles.jsonl"
FRAMES_DIR = "frames"
FRAME_KEY = "frame"  # the key the recorder adds to every cycle line

_FRAME_FILE = re.compile(r"frames/[0-9]{6,}\.png")
_PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1]  # fast: the recorder runs beside the loop
# Cycles a RecorderThread holds before record() waits for the disk: a few seconds of frames.
RECORDER_QUEUE_CYCLES = 64


class RecordingError(VservoError, RuntimeError):
    """A recording that cannot be written as asked, or read back as it is on disk."""


def to_jsonable(value: Any, _where: str = "value") -> Any:
    """``value`` as plain JSON types: dict (str keys), list, str, int, float, bool, None.

    numpy arrays become nested lists, numpy scalars Python numbers; NaN and +-inf become
    None (JSON has no non-finite numbers, and a missing feature is NaN in vservo);
    dataclasses become dicts of their fields, named tuples (Pose6) dicts, other tuples
    lists; enums their value; paths strings. Mapping keys must be strings (ints, floats,
    bools and enums are turned into strings as json would). Anything else raises
    TypeError naming where in ``value`` it sits.
    """
    if value is None or isinstance(value, str):
        return value
    if isinstance(value, Enum):
        return to_jsonable(value.value, _where)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "biuf":
            raise TypeError(f"{_where}: cannot store a numpy array of {value.dtype} as JSON")
        return to_jsonable(value.tolist(), _where)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name), f"{_where}.{f.name}") for f in dataclasses.fields(value)}
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        return {name: to_jsonable(item, f"{_where}.{name}") for name, item in zip(value._fields, value)}
    if isinstance(value, Mapping):
        out: dict[str, Any] = {}
        for key, item in value.items():
            if isinstance(key, Enum):
                key = key.value
            if isinstance(key, (bool, np.bool_)):
                key = "true" if key else "false"
            elif isinstance(key, (int, float, np.integer, np.floating)):
                key = str(key)
            if not isinstance(key, str):
                raise TypeError(f"{_where}: JSON object keys are strings, got the key {key!r}")
            out[key] = to_jsonable(item, f"{_where}[{key!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [to_jsonable(item, f"{_where}[{i}]") for i, item in enumerate(value)]
    if isinstance(value, PurePath):
        return str(value)
    raise TypeError(f"{_where}: cannot store a {type(value).__name__} as JSON")


def _dumps(value: Any) -> str:
    return json.dumps(value, allow_nan=False, ensure_ascii=False, separators=(",", ":"))


def _utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def write_atomic(path: Path, data: bytes, fsync: bool = True) -> None:
    """Write ``data`` to ``path`` so that ``path`` holds either its old content or all of ``data``.

    The bytes go to a temporary file next to ``path`` (same file system), which then
    replaces ``path`` with ``os.replace``; if anything fails the temporary file is removed
    and ``path`` is untouched.
    """
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


class RunRecorder:
    """Records one run into a new folder: frames, one line per cycle, and meta.json.

    folder: created if needed; an existing folder must be empty (a recording is never
      overwritten or appended to).
    meta: the caller's description of the run (cell, source, control law, settings), any
      ``to_jsonable`` value; stored as ``description`` in meta.json.
    fsync: sync each cycle line and frame to disk (see the module docstring).

    ``record(frame, cycle)`` once per cycle; ``close(outcome)`` writes the summary. As a
    context manager, an exception that ends the run is noted in the summary as ``aborted``.
    """

    def __init__(self, folder: str | Path, meta: Mapping[str, Any], *, fsync: bool = False) -> None:
        self.folder = Path(folder)
        if not isinstance(meta, Mapping):
            raise TypeError(f"meta is a dict describing the run, got {type(meta).__name__}")
        description = to_jsonable(meta, "meta")
        if self.folder.exists():
            if not self.folder.is_dir():
                raise RecordingError(f"cannot record into {str(self.folder)!r}: it is a file, not a folder")
            if any(self.folder.iterdir()):
                raise RecordingError(
                    f"refusing to record into {str(self.folder)!r}: the folder is not empty "
                    "(a recording is never overwritten; choose a new folder)"
                )
        (self.folder / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        self.fsync = fsync
        self._meta: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "created_utc": _utc_now(),
            "description": description,
            "image_size": None,
            "summary": None,
        }
        self._write_meta()
        # "x": exclusive creation, so two recorders can never share a folder.
        self._cycles = open(self.folder / CYCLES_FILE, "x", encoding="utf-8", newline="\n")
        self.frame_count = 0
        self.cycle_count = 0
        self._first_time_s: float | None = None
        self._last_time_s: float | None = None
        self._closed = False

    def __repr__(self) -> str:
        return f"RunRecorder({str(self.folder)!r})"

    def __enter__(self) -> RunRecorder:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None:
        if self._closed:
            return
        if exc_type is None:
            self.close()
        else:
            self._close({"aborted": f"{exc_type.__name__}: {exc}"})

    @property
    def image_size(self) -> Size | None:
        size = self._meta["image_size"]
        return None if size is None else (size[0], size[1])

    def _write_meta(self) -> None:
        path = self.folder / META_FILE
        try:
            write_atomic(path, (json.dumps(self._meta, indent=2, allow_nan=False, ensure_ascii=False) + "\n").encode())
        except OSError as exc:
            raise RecordingError(f"cannot write {str(path)!r}: {exc}") from exc

    def record(self, frame: Frame | None, cycle: Mapping[str, Any]) -> None:
        """Append one cycle, with the frame it saw (None for a cycle without a new frame)."""
        if self._closed:
            raise RecordingError(f"{self!r} is closed")
        if not isinstance(cycle, Mapping):
            raise TypeError(f"a cycle is a dict of JSON-able values, got {type(cycle).__name__}")
        if FRAME_KEY in cycle:
            raise ValueError(f"the cycle key {FRAME_KEY!r} is the recorder's own (the frame reference); rename it")
        line = to_jsonable(cycle, "cycle")  # before writing anything: a bad value leaves no orphan frame
        line[FRAME_KEY] = None if frame is None else self._write_frame(frame)
        text = _dumps(line) + "\n"
        self._cycles.write(text)
        self._cycles.flush()
        if self.fsync:
            os.fsync(self._cycles.fileno())
        self.cycle_count += 1

    def _write_frame(self, frame: Frame) -> dict[str, Any]:
        if not isinstance(frame, Frame):
            raise TypeError(f"record() takes a Frame or None, got {type(frame).__name__}")
        size = frame.size
        if self.image_size is None:
            self._meta["image_size"] = list(size)
            self._write_meta()
        elif size != self.image_size:
            raise RecordingError(
                f"frame {frame.index} is {size[0]}x{size[1]}, the recording's frames {self.image_size[0]}x{self.image_size[1]}"
            )
        name = f"{FRAMES_DIR}/{self.frame_count:06d}.png"
        ok, png = cv2.imencode(".png", frame.image, _PNG_PARAMS)
        if not ok:
            raise RecordingError(f"OpenCV could not encode frame {frame.index} as PNG")
        try:
            write_atomic(self.folder / name, png.tobytes(), fsync=self.fsync)
        except OSError as exc:
            raise RecordingError(f"cannot write {str(self.folder / name)!r}: {exc}") from exc
        self.frame_count += 1
        timestamp = float(frame.timestamp_s)
        if self._first_time_s is None:
            self._first_time_s = timestamp
        self._last_time_s = timestamp
        return {"file": name, "timestamp_s": timestamp, "index": int(frame.index)}

    def close(self, outcome: Mapping[str, Any] | None = None) -> None:
        """Finish the recording: meta.json gets its summary (with ``outcome``, if given). Idempotent."""
        if self._closed:
            return
        self._close({} if outcome is None else {"outcome": to_jsonable(outcome, "outcome")})

    def _close(self, extra: dict[str, Any]) -> None:
        self._closed = True
        self._cycles.close()
        self._meta["summary"] = {
            "closed_utc": _utc_now(),
            "cycles": self.cycle_count,
            "frames": self.frame_count,
            "first_frame_time_s": self._first_time_s,
            "last_frame_time_s": self._last_time_s,
            **extra,
        }
        self._write_meta()


class RecorderThread:
    """A RunRecorder written from a thread of its own: ``record`` hands the cycle over and
    returns, so a loop servoing at the camera's rate does not wait for the PNG encoding and
    the disk (OpenCV encodes without Python's lock, on another core). The cycles are written
    in the order recorded. A write that fails stops the writing; ``record`` and ``close`` then
    raise its error, saying at which cycle the recording stopped. A crash of the process loses
    the cycles still queued (the disk keeps up: a frame or two)."""

    def __init__(self, recorder: RunRecorder) -> None:
        self.recorder = recorder
        self.folder = recorder.folder
        self.failure: Exception | None = None  # the write that stopped the recording
        self._queue: queue.Queue[tuple[Frame | None, Mapping[str, Any]] | None] = queue.Queue(RECORDER_QUEUE_CYCLES)
        self._closed = False
        self._writer = threading.Thread(target=self._write, name=f"recorder {recorder.folder.name}", daemon=True)
        self._writer.start()

    def __repr__(self) -> str:
        return f"RecorderThread({str(self.folder)!r})"

    def _write(self) -> None:
        while (item := self._queue.get()) is not None:
            if self.failure is None:
                try:
                    self.recorder.record(*item)
                except Exception as exc:  # the disk, or a value JSON cannot hold: kept for the caller
                    if not isinstance(exc, (RecordingError, OSError)):
                        log.exception("%r: a cycle could not be recorded", self)
                    count = self.recorder.cycle_count
                    self.failure = RecordingError(f"recording stopped at cycle {count + 1}: {exc}")
                    self.failure.__cause__ = exc

    def record(self, frame: Frame | None, cycle: Mapping[str, Any]) -> None:
        """Queue one cycle (RunRecorder.record); raises the failure of an earlier write."""
        if self.failure is not None:
            raise self.failure
        if self._closed:
            raise RecordingError(f"{self!r} is closed")
        self._queue.put((frame, cycle))

    def close(self, outcome: Mapping[str, Any] | None = None) -> None:
        """Write what is queued, then close the recording (RunRecorder.close) with ``outcome``,
        or after a failed write as aborted, and raise that write's failure. Idempotent."""
        if not self._closed:
            self._closed = True
            self._queue.put(None)
            self._writer.join()
        if self.failure is None:
            self.recorder.close(outcome)
            return
        try:
            self.recorder.close({"aborted": str(self.failure)})
        finally:
            raise self.failure


@dataclass(frozen=True)
class Recording:
    """A recording read back from its folder: ``Recording.open(folder)``.

    meta: the whole meta.json (``description`` is what the recorder's caller gave;
      ``summary`` is None when the run never closed its recorder, e.g. it crashed).
    cycles: one dict per cycle line, in order, each with its ``"frame"`` reference.
    frame_paths: the frame files the cycles reference, in order.
    truncated_last_line: the last line of cycles.jsonl was cut short and is left out.

    A last line without its newline that is not valid JSON is what a crash while
    appending leaves behind: the recorder writes each line in one go ending with "\\n",
    so everything before it is complete and only that cycle is lost. It is dropped and
    flagged, not an error, so a crashed run can still be replayed up to its end. A bad
    line that does end with a newline was written whole and damaged afterwards (or the
    file was edited); dropping it would silently shift the run, so that raises
    RecordingError naming the line.
    """

    folder: Path
    meta: dict[str, Any]
    cycles: list[dict[str, Any]]
    frame_paths: list[Path]
    truncated_last_line: bool = False

    @classmethod
    def open(cls, folder: str | Path) -> Recording:
        folder = Path(folder)
        if not folder.is_dir():
            raise RecordingError(f"recording folder {str(folder)!r} does not exist or is not a folder")
        meta = _read_meta(folder / META_FILE)
        cycles, truncated = _read_cycles(folder / CYCLES_FILE)
        frame_paths: list[Path] = []
        for line_number, cycle in enumerate(cycles, start=1):
            path = _frame_path(folder, cycle, line_number)
            if path is not None:
                frame_paths.append(path)
        if truncated:
            log.warning("%s: the last line of %s was cut short (a crash while recording); left out", folder, CYCLES_FILE)
        return cls(folder, meta, cycles, frame_paths, truncated)

    @property
    def description(self) -> dict[str, Any]:
        return self.meta.get("description") or {}

    @property
    def summary(self) -> dict[str, Any] | None:
        return self.meta.get("summary")

    @property
    def complete(self) -> bool:
        """Whether the recorder was closed (the run did not crash) and no line was lost."""
        return self.summary is not None and not self.truncated_last_line

    @property
    def image_size(self) -> Size | None:
        size = self.meta.get("image_size")
        return None if size is None else (int(size[0]), int(size[1]))

    def frame_of(self, cycle: Mapping[str, Any]) -> Frame | None:
        """The frame recorded with ``cycle`` (one of ``cycles``), None if it had none."""
        ref = cycle.get(FRAME_KEY)
        if ref is None:
            return None
        return self._load(self.folder / ref["file"], ref)

    def frames(self) -> Generator[Frame, None, None]:
        """The recorded frames in order, with their recorded timestamps and source indices."""
        for cycle in self.cycles:
            frame = self.frame_of(cycle)
            if frame is not None:
                yield frame

    def _load(self, path: Path, ref: Mapping[str, Any]) -> Frame:
        try:
            data = np.fromfile(path, dtype=np.uint8)
        except OSError as exc:
            raise RecordingError(f"cannot read frame {str(path)!r}: {exc}") from exc
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if image is None or image.ndim != 2 or image.dtype != np.uint8:
            raise RecordingError(f"frame {str(path)!r} is not a monochrome 8-bit PNG")
        size = self.image_size
        if size is not None and (image.shape[1], image.shape[0]) != size:
            raise RecordingError(f"frame {str(path)!r} is {image.shape[1]}x{image.shape[0]}, meta.json says {size[0]}x{size[1]}")
        # (imdecode is typed as returning any Mat; the check above made it 8-bit)
        return Frame(cast(NDArray[np.uint8], image), float(ref["timestamp_s"]), int(ref["index"]))


def _read_meta(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise RecordingError(f"{str(path)!r} is missing: not a recording, or one whose creation failed")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{str(path)!r} is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        raise RecordingError(f"{str(path)!r} does not describe a {FORMAT_NAME}")
    version = meta.get("version")
    if version not in SUPPORTED_VERSIONS:
        raise RecordingError(
            f"{str(path)!r}: recording format version {version!r} is not supported "
            f"(this vservo reads version {', '.join(map(str, SUPPORTED_VERSIONS))})"
        )
    size = meta.get("image_size")
    if size is not None and not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
        raise RecordingError(f"{str(path)!r}: image_size is [width, height] or null, got {size!r}")
    return meta


def _read_cycles(path: Path) -> tuple[list[dict[str, Any]], bool]:
    """The cycle dicts of cycles.jsonl and whether its last line was cut short."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise RecordingError(f"{str(path)!r} is missing") from None
    lines = data.split(b"\n")
    # After the last "\n" comes either nothing (a complete file) or an unfinished line.
    unfinished = lines.pop()
    cycles: list[dict[str, Any]] = []
    for number, raw in enumerate(lines, start=1):
        cycles.append(_parse_line(raw, path, number))
    truncated = False
    if unfinished:
        try:
            cycles.append(_parse_line(unfinished, path, len(lines) + 1))
        except RecordingError:  # a crash while appending: see Recording's docstring
            truncated = True
    return cycles, truncated


def _parse_line(raw: bytes, path: Path, number: int) -> dict[str, Any]:
    try:
        value = json.loads(raw.decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{str(path)!r} line {number}: not valid JSON ({exc})") from None
    if not isinstance(value, dict):
        raise RecordingError(f"{str(path)!r} line {number}: a cycle is a JSON object, got {type(value).__name__}")
    return value


def _frame_path(folder: Path, cycle: dict[str, Any], line_number: int) -> Path | None:
    where = f"{str(folder / CYCLES_FILE)!r} line {line_number}"
    if FRAME_KEY not in cycle:
        raise RecordingError(f"{where}: the cycle has no {FRAME_KEY!r} entry")
    ref = cycle[FRAME_KEY]
    if ref is None:
        return None
    if not (
        isinstance(ref, dict)
        and isinstance(ref.get("file"), str)
        and _FRAME_FILE.fullmatch(ref["file"])
        and isinstance(ref.get("timestamp_s"), (int, float))
        and isinstance(ref.get("index"), int)
    ):
        raise RecordingError(f"{where}: bad frame reference {ref!r}")
    path = folder / ref["file"]
    if not path.is_file():
        raise RecordingError(f"{where}: frame {str(path)!r} is missing")
    return path


class PlaybackSource(BaseSource):
    """A recording's frames as a FrameSource, with their recorded timestamps and indices.

    realtime=False hands out frames as fast as they are read; realtime=True paces them as
    recorded: frame k is released no earlier than (t_k - t_0) after the first ``read``,
    measured with ``clock`` and waited with ``sleep`` (both injectable for tests).
    SourceLost after the last frame.
    """

    def __init__(
        self,
        recording: Recording,
        realtime: bool = False,
        sleep: Callable[[float], None] = time.sleep,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.recording = recording
        self.realtime = realtime
        self._sleep = sleep
        self._clock = clock
        self._frames = recording.frames()
        self._delivered = 0
        self._start: tuple[float, float] | None = None  # (wall clock, recorded time) of the first frame

    def __repr__(self) -> str:
        return f"PlaybackSource({str(self.recording.folder)!r})"

    @property
    def image_size(self) -> Size | None:
        return self.recording.image_size

    def read(self) -> Frame:
        self._check_open()
        frame = next(self._frames, None)
        if frame is None:
            raise SourceLost(f"end of recording {str(self.recording.folder)!r} after {self._delivered} frames")
        if self.realtime:
            if self._start is None:
                self._start = (float(self._clock()), frame.timestamp_s)
            else:
                due = self._start[0] + (frame.timestamp_s - self._start[1])
                wait = due - float(self._clock())
                if wait > 0.0:
                    self._sleep(wait)
        self._delivered += 1
        return frame

    def read_after(self, t_s: float) -> Frame:
        """The next recorded frame: a recording holds the frames its run used, each already
        fresh when it was recorded."""
        return self.read()

    def close(self) -> None:
        self._frames.close()
        super().close()
