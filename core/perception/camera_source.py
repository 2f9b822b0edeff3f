"""Where images come from: a live camera, a video file or stream, still images, a recording.

Every source hands out ``Frame`` objects through one small interface, ``FrameSource``:
``read()`` blocks until the next frame and raises ``SourceLost`` once the source cannot
deliver anymore; ``close()`` releases it; a source is a context manager. Frames are
always monochrome 8-bit (H, W) arrays, the camera of the cell being monochrome: colour
frames are converted to grey and 16-bit frames keep their high byte (``to_mono8``).

Timestamps depend on the source: a live source (camera, stream) stamps each frame with
a monotonic clock when the frame arrives, less its ``exposure_latency_s``, a video file
when ``read`` gets the frame, playback of a recording
(``vservo.core.perception.recording.PlaybackSource``) gives the recorded time and a
simulated source the simulation time. Only differences between the timestamps of one
source mean anything. Sizes are (width, height) in pixels, as OpenCV and ``CameraModel``
give them; ``Frame.image`` has the numpy shape (height, width).

``read_after(t_s)`` is what the look-and-move loop calls: a frame exposed after the
robot's last motion ended at ``t_s`` on the robot's clock, never one that waited in a
buffer through the motion (docs/vision.md, "No stale frames", says how each source kind
guarantees it).

Sources are not thread-safe: one consumer reads each source.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np
from numpy.typing import NDArray

from vservo.core.errors import VservoError

log = logging.getLogger("vservo.camera")

Size = tuple[int, int]  # (width, height) in pixels

# How long closing a live source waits for its reader's read in progress to return.
CLOSE_WAIT_S = 2.0
# How long a reader waits for a live source's next frame, unless told (the cell file
# passes its [safety] watchdog_s); at most MAX_FRAME_TIMEOUT_S.
DEFAULT_FRAME_TIMEOUT_S = 5.0
MAX_FRAME_TIMEOUT_S = 600.0
# A stream's receive buffer in the kernel, pinned, for streams over TCP. Left to itself Linux
# grows it to megabytes, hundreds of a small camera's JPEGs: a reader that falls behind (a
# busy host) then reads frames seconds old, each stamped as just arrived (2.4 s measured at a
# load average of 19, docs/vision.md). Full, a small buffer makes the sender drop frames
# instead, as a camera does. Linux doubles the figure; a few 640 x 480 JPEGs fit.
STREAM_RECEIVE_BUFFER_BYTES = 16 * 1024
TCP_STREAM_SCHEMES = ("http://", "https://", "tcp://")
FFMPEG_OPTIONS_VARIABLE = "OPENCV_FFMPEG_CAPTURE_OPTIONS"
_ffmpeg_options_lock = threading.Lock()  # the environment is the process's: one open at a time


class CameraSourceError(VservoError, RuntimeError):
    """A source that cannot be opened, or a frame it delivered that cannot be used."""


class SourceLost(CameraSourceError):
    """The source cannot deliver anymore: end of a file or recording, or a camera that
    stayed unreachable through all its reconnection attempts."""


@dataclass(frozen=True, eq=False)
class Frame:
    """One monochrome image and when it was exposed.

    image: uint8 array of shape (height, width).
    timestamp_s: seconds; for live sources a monotonic clock when the frame arrived less
      the source's exposure latency, the recorded time for playback, the simulation time
      for a simulated source.
    index: the source's frame counter, 0 for its first frame.
    Frames compare by identity (``eq=False``): comparing the pixels is the caller's choice.
    """

    image: NDArray[np.uint8]
    timestamp_s: float
    index: int

    def __post_init__(self) -> None:
        image = self.image
        if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8 or image.size == 0:
            what = f"{image.dtype} array of shape {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
            raise ValueError(f"a frame image is a non-empty uint8 (height, width) array, got {what}")
        if (
            isinstance(self.timestamp_s, bool)
            or not isinstance(self.timestamp_s, (int, float))
            or not math.isfinite(self.timestamp_s)
        ):
            raise ValueError(f"a frame timestamp is a finite number of seconds, got {self.timestamp_s!r}")
        if isinstance(self.index, bool) or not isinstance(self.index, (int, np.integer)) or self.index < 0:
            raise ValueError(f"a frame index is an integer >= 0, got {self.index!r}")

    @property
    def size(self) -> Size:
        """(width, height) in pixels."""
        height, width = self.image.shape
        return width, height


@runtime_checkable
class FrameSource(Protocol):
    """What the servo loop and the recorder need from any source of frames."""

    @property
    def image_size(self) -> Size | None:
        """(width, height) of the frames, None while the source cannot tell yet."""
        ...

    def read(self) -> Frame:
        """The next frame; raises SourceLost when the source cannot deliver anymore."""
        ...

    def read_after(self, t_s: float) -> Frame:
        """A frame exposed at or after ``t_s``, a time on the robot's clock (``clock_s``):
        the end of the last motion, so the frame shows where the robot stopped."""
        ...

    def close(self) -> None:
        """Release the source; calling it again does nothing."""
        ...

    @property
    def lost(self) -> str | None:
        """Why the source gave up delivering for good (SourceLost), None while it delivers."""
        ...

    def __enter__(self) -> FrameSource: ...

    def __exit__(self, *exc_info: object) -> None: ...


class BaseSource:
    """Context-manager plumbing shared by the sources: ``with source: ...`` closes it."""

    _closed = False

    def __enter__(self):
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def lost(self) -> str | None:
        return None  # a source that is never lost (files, the simulator); a live one says why

    def close(self) -> None:
        self._closed = True

    def _check_open(self) -> None:
        if self._closed:
            raise CameraSourceError(f"{self!r} is closed")


def read_mono8(path: str | Path) -> NDArray[np.uint8]:
    """The image file at ``path`` as an 8-bit single-channel image (``to_mono8``).

    Raises CameraSourceError naming the file when it is missing, cannot be decoded or
    has a layout ``to_mono8`` does not take.
    """
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise CameraSourceError(f"cannot read image {str(path)!r}: {exc.strerror or exc}") from None
    if data.size == 0:  # cv2.imdecode asserts on an empty buffer instead of returning None
        raise CameraSourceError(f"cannot decode image {str(path)!r}: the file is empty")
    raw = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise CameraSourceError(f"cannot decode image {str(path)!r}")
    try:
        return to_mono8(raw)
    except CameraSourceError as exc:
        raise CameraSourceError(f"{str(path)!r}: {exc}") from None


def to_mono8(image: np.ndarray) -> NDArray[np.uint8]:
    """A camera image as an 8-bit monochrome (H, W) array.

    Accepts (H, W), (H, W, 1), BGR (H, W, 3) and BGRA (H, W, 4) images (OpenCV's channel
    order) of uint8 or uint16. Colour goes to grey with ``cv2.cvtColor``; 16-bit keeps
    the high byte (value >> 8), mapping the full 16-bit range onto 0 .. 255. A camera
    that puts 10 or 12 significant bits in 16-bit words therefore comes out dark: scale
    such frames before handing them over.
    """
    if not isinstance(image, np.ndarray) or image.size == 0:
        raise CameraSourceError(f"expected an image array, got {type(image).__name__}")
    if image.dtype not in (np.uint8, np.uint16):
        raise CameraSourceError(f"unsupported pixel type {image.dtype}: frames are 8- or 16-bit")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    elif image.ndim != 2:
        raise CameraSourceError(f"unsupported image shape {image.shape}: expected (H, W) or (H, W, 1|3|4)")
    if image.dtype == np.uint16:
        image = np.right_shift(image, 8).astype(np.uint8)
    return np.ascontiguousarray(image)


def _check_size(size: Size | None, name: str) -> Size | None:
    if size is None:
        return None
    if len(size) != 2 or not all(isinstance(v, (int, np.integer)) and v > 0 for v in size):
        raise ValueError(f"{name} is (width, height) in positive pixels, got {size!r}")
    return int(size[0]), int(size[1])


def _format_size(size: Size) -> str:
    return f"{size[0]}x{size[1]}"


class CaptureLike(Protocol):
    """The part of ``cv2.VideoCapture`` a VideoCaptureSource uses (tests pass fakes)."""

    def isOpened(self) -> bool: ...

    def read(self) -> tuple[bool, Any]: ...

    def release(self) -> None: ...

    # Positional-only: OpenCV names these parameters propId.
    def set(self, prop_id: int, value: float, /) -> bool: ...

    def get(self, prop_id: int, /) -> float: ...


@contextmanager
def _receive_buffer_pinned(spec: str) -> Iterator[None]:
    """While OpenCV opens ``spec``: FFmpeg's ``recv_buffer_size`` option for a stream over TCP
    (OpenCV reads FFmpeg's options from OPENCV_FFMPEG_CAPTURE_OPTIONS, "key;value|..."),
    unless the environment already sets it; the environment is as it was afterwards."""
    if not spec.lower().startswith(TCP_STREAM_SCHEMES):
        yield
        return
    with _ffmpeg_options_lock:
        before = os.environ.get(FFMPEG_OPTIONS_VARIABLE)
        if before is None or "recv_buffer_size;" not in before:
            pinned = f"recv_buffer_size;{STREAM_RECEIVE_BUFFER_BYTES}"
            os.environ[FFMPEG_OPTIONS_VARIABLE] = pinned if not before else f"{before}|{pinned}"
        try:
            yield
        finally:
            if before is None:
                os.environ.pop(FFMPEG_OPTIONS_VARIABLE, None)
            else:
                os.environ[FFMPEG_OPTIONS_VARIABLE] = before


def is_video_file(spec: int | str) -> bool:
    """Whether ``spec`` names a video file (or an image sequence such as ``img_%04d.png``).

    Everything else is live: a device index, a device path under /dev/, a stream URL
    (anything with ``://``) and a GStreamer pipeline (anything with ``!``). A file ends;
    a live source that stops delivering is reconnected.
    """
    return isinstance(spec, str) and "://" not in spec and not spec.startswith("/dev/") and "!" not in spec


class VideoCaptureSource(BaseSource):
    """Frames from OpenCV's VideoCapture: a camera by device index, a video file, a stream.

    spec: device index (0, 1, ...), path of a video file, or a stream URL / pipeline
      (see ``is_video_file`` for how they are told apart).
    expected_size: (width, height); a frame of another size raises CameraSourceError.
    reconnect_attempts / reconnect_delay_s: when a live source fails to deliver a frame,
      the capture is released and reopened up to this many times, waiting the delay
      before each attempt; then SourceLost. A video file is never reopened for a failed
      read: its end raises SourceLost("end of video file ..."), or rewinds with ``loop``.
    loop: replay a video file from its start when it ends (files only).
    exposure_latency_s: the longest time from a frame's exposure until it arrives here
      (exposure, readout, encoding, network, decoding); a live frame is stamped with the
      time it arrived less this latency.
    buffer_frames: frames ``read_after`` still discards once a frame arrived late enough,
      for a pipeline that holds frames inside even while it is read continuously (0 for
      a plain camera or stream: see ``read_after``).
    frame_timeout_s: the longest a live source may go without delivering a frame to a
      waiting reader: then it is lost (``SourceLost`` naming the stall), so a camera whose
      connection stays open but sends nothing stops a run within this time, and not at
      the network stack's own timeouts minutes later. A stream is also opened and read
      with OpenCV's open and read timeouts at this value.
    clock / sleep: the timestamp clock and the wait between reconnections, injectable so
      tests neither wait nor depend on the time of day. The clock must be the robot's
      (``time.monotonic`` for the JRC link) for ``read_after``; by default the wait ends
      early when the source is closed.
    opener: makes a capture from the spec, ``cv2.VideoCapture`` by default; tests inject
      fakes that fail and recover.

    A live source (device, stream) is read continuously by a thread of its own, which
    keeps only the newest frame and the time it arrived: the driver's and the stream's
    buffers are drained as fast as they fill, so a frame is never older on arrival than
    the pipeline's latency, and a consumer that reads slowly sees fewer frames, never old
    ones. That thread owns the capture (reading, reconnecting, releasing it). A video file
    is read in the caller's thread, one frame per read: its frames are not live.

    A spec that cannot be opened at all raises CameraSourceError at construction, without
    retries: a wrong index or path is a set-up error, not a dropped connection. Opening a
    device index that does not exist is immediate with OpenCV's V4L2 backend (well under
    a millisecond), so this fails fast.
    """

    def __init__(
        self,
        spec: int | str,
        *,
        expected_size: Size | None = None,
        reconnect_attempts: int = 3,
        reconnect_delay_s: float = 0.5,
        loop: bool = False,
        exposure_latency_s: float = 0.0,
        buffer_frames: int = 0,
        frame_timeout_s: float = DEFAULT_FRAME_TIMEOUT_S,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] | None = None,
        opener: Callable[[int | str], CaptureLike] | None = None,
    ) -> None:
        if isinstance(spec, bool) or not isinstance(spec, (int, str)) or spec == "" or (isinstance(spec, int) and spec < 0):
            raise ValueError(f"a capture spec is a device index >= 0 or a non-empty path/URL, got {spec!r}")
        if isinstance(reconnect_attempts, bool) or not isinstance(reconnect_attempts, int) or reconnect_attempts < 0:
            raise ValueError(f"reconnect_attempts must be an integer >= 0, got {reconnect_attempts!r}")
        if not (reconnect_delay_s >= 0.0 and math.isfinite(reconnect_delay_s)):
            raise ValueError(f"reconnect_delay_s must be finite and >= 0, got {reconnect_delay_s!r}")
        if not (exposure_latency_s >= 0.0 and math.isfinite(exposure_latency_s)):
            raise ValueError(f"exposure_latency_s must be finite and >= 0, got {exposure_latency_s!r}")
        if isinstance(buffer_frames, bool) or not isinstance(buffer_frames, int) or buffer_frames < 0:
            raise ValueError(f"buffer_frames must be an integer >= 0, got {buffer_frames!r}")
        if not 0.0 < frame_timeout_s <= MAX_FRAME_TIMEOUT_S:
            raise ValueError(
                f"frame_timeout_s must be more than 0 and at most {MAX_FRAME_TIMEOUT_S:g} s, got {frame_timeout_s!r}"
            )
        self.spec = spec
        self.is_file = is_video_file(spec)
        if loop and not self.is_file:
            raise ValueError(f"loop applies to video files only, not to the live source {spec!r}")
        self.expected_size = _check_size(expected_size, "expected_size")
        self.reconnect_attempts = reconnect_attempts
        self.reconnect_delay_s = float(reconnect_delay_s)
        self.loop = loop
        self.exposure_latency_s = float(exposure_latency_s)
        self.buffer_frames = buffer_frames
        self.frame_timeout_s = float(frame_timeout_s)
        self._clock = clock
        self._stopping = threading.Event()
        self._sleep: Callable[[float], object] = sleep if sleep is not None else self._stopping.wait
        self._opener: Callable[[int | str], CaptureLike] = opener if opener is not None else self._open_capture
        self._next_index = 0
        self._last_size: Size | None = None
        self._lost: str | None = None  # why the source is gone, once it is
        cap, why = self._open()
        if cap is None:
            raise CameraSourceError(f"cannot open {self._describe()}: {why}")
        self._cap: CaptureLike | None = cap
        self._reported_size = _reported_size(cap)
        # A live source's newest frame, the clock when it arrived, and its arrival number;
        # the number of the last one handed out. Guarded by _arrived.
        self._arrived = threading.Condition()
        self._newest: tuple[np.ndarray, float, int] | None = None
        self._taken = 0
        self._reader: threading.Thread | None = None
        if not self.is_file:
            self._reader = threading.Thread(target=self._read_continuously, name=f"capture {spec}", daemon=True)
            self._reader.start()

    def __repr__(self) -> str:
        return f"VideoCaptureSource({self.spec!r})"

    def _describe(self) -> str:
        if isinstance(self.spec, int):
            return f"camera device {self.spec}"
        return f"video file {self.spec!r}" if self.is_file else f"stream {self.spec!r}"

    def _open_capture(self, spec: int | str) -> CaptureLike:
        """OpenCV's capture of ``spec``; a stream's opens and reads time out at frame_timeout_s,
        and one over TCP gets a small receive buffer (STREAM_RECEIVE_BUFFER_BYTES)."""
        if isinstance(spec, int) or self.is_file:
            return cv2.VideoCapture(spec)
        timeout_ms = int(1000 * self.frame_timeout_s)
        with _receive_buffer_pinned(spec):
            return cv2.VideoCapture(
                spec, cv2.CAP_ANY, [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, timeout_ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms]
            )

    def _open(self) -> tuple[CaptureLike | None, str]:
        """A fresh opened capture, or None and why not."""
        try:
            cap = self._opener(self.spec)
        except Exception as exc:  # OpenCV raises cv2.error for some bad specs; fakes anything
            return None, f"{type(exc).__name__}: {exc}"
        if cap.isOpened():
            return cap, ""
        cap.release()
        # (a file's spec is a str: is_video_file)
        if self.is_file and isinstance(self.spec, str) and not Path(self.spec).exists() and "%" not in self.spec:
            return None, "no such file"
        if self.is_file:
            return None, "OpenCV cannot decode it (not a video, or a codec this build lacks)"
        return None, "no such device, or it is busy or unreachable"

    def _read_once(self) -> np.ndarray | None:
        """One read from the current capture: the image, or None when it failed."""
        if self._cap is None:
            return None
        try:
            ok, image = self._cap.read()
        except cv2.error as exc:
            log.warning("%s: read raised %s", self._describe(), exc)
            return None
        if not ok or image is None or getattr(image, "size", 0) == 0:
            return None
        return image

    def _release(self) -> None:
        if self._cap is not None:
            try:
                self._cap.release()
            finally:
                self._cap = None

    def _lose(self, why: str) -> SourceLost:
        self._release()
        with self._arrived:
            self._lost = why
            self._arrived.notify_all()
        return SourceLost(why)

    @property
    def image_size(self) -> Size | None:
        return self._last_size or self.expected_size or self._reported_size

    @property
    def lost(self) -> str | None:
        return self._lost

    def _frame(self, image: np.ndarray, arrived_s: float) -> Frame:
        """The next Frame of this source from a captured image and the clock at its arrival."""
        mono = to_mono8(image)
        height, width = mono.shape
        if self.expected_size is not None and (width, height) != self.expected_size:
            raise CameraSourceError(
                f"{self._describe()} delivered a {_format_size((width, height))} frame, "
                f"expected {_format_size(self.expected_size)} (width x height)"
            )
        self._last_size = (width, height)
        frame = Frame(mono, float(arrived_s) - self.exposure_latency_s, self._next_index)
        self._next_index += 1
        return frame

    def read(self) -> Frame:
        """The next frame: of a file, the next one in it; of a live source, the newest frame
        not handed out before, waiting for it to arrive."""
        self._check_open()
        if not self.is_file:
            return self._take(arrived_after_s=-math.inf)
        if self._lost is not None:
            raise SourceLost(self._lost)
        image = self._read_once()
        if image is None:
            image = self._rewind()
        return self._frame(image, self._clock())

    def read_after(self, t_s: float) -> Frame:
        """A frame exposed at or after ``t_s`` (this source's clock, which must be the robot's).

        The capture's frames carry no exposure time we can trust (CAP_PROP_POS_MSEC is a
        position in the stream, not a time on our clock), but the reading thread knows
        when each frame arrived, and it drains every buffer between the camera and here
        (as long as the host gives it time: one starved finds frames that waited, see
        STREAM_RECEIVE_BUFFER_BYTES): so a frame arrives at most ``exposure_latency_s``
        after its exposure, and one that arrived at or after t_s + exposure_latency_s was
        exposed at or after t_s. This returns the newest such frame not handed out before,
        waiting for the first one when none has arrived yet, whatever the frame rate and
        however slowly the caller reads; with ``buffer_frames`` it then still discards that
        many, for a pipeline that holds frames inside however fast it is read (each costs a
        frame period).

        A video file's frames are not live: its next frame, as ``read``.

        Raises CameraSourceError when t_s is ahead of the clock (the robot's clock and
        this source's are not the same one), SourceLost as ``read`` does.
        """
        self._check_open()
        if self.is_file:
            return self.read()
        now = float(self._clock())
        if t_s > now:
            raise CameraSourceError(
                f"{self._describe()}: asked for a frame exposed after {t_s:.3f} s, {t_s - now:.3f} s ahead of "
                "the source's clock: the camera source must run on the robot's clock"
            )
        frame = self._take(arrived_after_s=t_s + self.exposure_latency_s)
        for _ in range(self.buffer_frames):
            frame = self._take(arrived_after_s=-math.inf)
        return frame

    def _take(self, arrived_after_s: float) -> Frame:
        """The newest live frame not handed out before that arrived at or after
        ``arrived_after_s``, waiting for one; SourceLost once the reader gave up, or when
        no new frame came within frame_timeout_s."""
        # The wall clock, not the injectable one: a deadline on how long this thread waits.
        deadline = time.monotonic() + self.frame_timeout_s
        with self._arrived:
            while True:
                self._check_open()
                if self._newest is not None:
                    image, arrived_s, number = self._newest
                    if number > self._taken and arrived_s >= arrived_after_s:
                        self._taken = number
                        break
                if self._lost is not None:
                    raise SourceLost(self._lost)
                remaining_s = deadline - time.monotonic()
                if remaining_s <= 0.0:
                    raise self._stalled()
                self._arrived.wait(remaining_s)
        return self._frame(image, arrived_s)

    def _stalled(self) -> SourceLost:
        """Give the source up after frame_timeout_s without a frame (called holding _arrived).

        Its reader may be blocked in a read that returns only at the network's timeouts; it
        owns the capture, so it is told to stop and releases the capture when that read
        returns. A reconnection (``Rig.reconnect`` on Reset) opens a new source meanwhile.
        """
        self._lost = f"{self._describe()} delivered no frame for {self.frame_timeout_s:g} s: the camera stalled"
        self._stopping.set()
        self._arrived.notify_all()
        return SourceLost(self._lost)

    def _read_continuously(self) -> None:
        """The live reader: read, stamp and keep the newest frame until closed or lost."""
        number = 0
        try:
            while not self._stopping.is_set():
                image = self._read_once()
                if image is None:
                    if self._stopping.is_set():
                        break
                    image = self._reconnect()
                arrived_s = float(self._clock())
                number += 1
                with self._arrived:
                    self._newest = (image, arrived_s, number)
                    self._arrived.notify_all()
        except SourceLost:
            pass  # _lose recorded why; the consumer raises it
        except Exception as exc:  # a broken capture or clock must reach the consumer, not vanish
            self._lose(f"{self._describe()}: reading failed: {type(exc).__name__}: {exc}")
        finally:
            self._release()

    def _rewind(self) -> np.ndarray:
        """The first frame again at the end of a looping file; SourceLost without ``loop``."""
        if not self.loop:
            raise self._lose(f"end of video file {self.spec!r} after {self._next_index} frames")
        log.debug("%s: rewinding", self._describe())
        if self._cap is not None and self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0):
            image = self._read_once()
            if image is not None:
                return image
        # Some backends cannot seek: reopening the file starts it over as well.
        self._release()
        cap, why = self._open()
        self._cap = cap
        image = self._read_once()
        if image is None:
            raise self._lose(f"video file {self.spec!r} yields no frame after rewinding{': ' + why if why else ''}")
        return image

    def _reconnect(self) -> np.ndarray:
        """Release and reopen a live source until it delivers, or SourceLost."""
        why = "read failed"
        for attempt in range(1, self.reconnect_attempts + 1):
            self._release()
            log.warning(
                "%s: no frame (%s); reconnecting in %.2f s, attempt %d of %d",
                self._describe(),
                why,
                self.reconnect_delay_s,
                attempt,
                self.reconnect_attempts,
            )
            self._sleep(self.reconnect_delay_s)
            if self._stopping.is_set():
                raise self._lose(f"{self._describe()} is closed")
            self._cap, open_why = self._open()
            if self._cap is None:
                why = f"reopening failed: {open_why}"
                continue
            image = self._read_once()
            if image is not None:
                log.info("%s: reconnected at attempt %d", self._describe(), attempt)
                return image
            why = "read failed after reopening"
        raise self._lose(
            f"{self._describe()} delivers no frame after {self.reconnect_attempts} reconnection attempts "
            f"{self.reconnect_delay_s:g} s apart (last: {why})"
        )

    def close(self) -> None:
        """Release the capture; a live source's reader finishes its read and releases it."""
        with self._arrived:
            super().close()
            self._arrived.notify_all()
        self._stopping.set()
        if self._reader is None:
            self._release()
            return
        # A read returns within a frame period from a delivering camera; one that hangs
        # on a vanished stream returns at the capture's own timeout, and releases then.
        self._reader.join(timeout=CLOSE_WAIT_S)
        if self._reader.is_alive():
            log.warning(
                "%s: still waiting for a frame after %.1f s; it is released when the read returns", self._describe(), CLOSE_WAIT_S
            )


def _reported_size(cap: CaptureLike) -> Size | None:
    """The frame size the capture reports before delivering any, if it does."""
    width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    return (width, height) if width > 0 and height > 0 else None


class ImageFolderSource(BaseSource):
    """Still images of a folder played in sorted file-name order, one per ``read``.

    For set-up and tests: a few saved frames stand in for the camera. Names sort as
    strings, so number them with leading zeros (``000012.png``). Images of any depth or
    channel count ``to_mono8`` accepts are converted; all must have the size of the first.
    timestamps: one per image (finite, non-decreasing); without them each frame is
    stamped with ``clock`` when read. The index of a frame is its position in the order.
    SourceLost after the last image.
    """

    def __init__(
        self,
        folder: str | Path,
        pattern: str = "*.png",
        timestamps: Sequence[float] | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise CameraSourceError(f"image folder {str(self.folder)!r} does not exist or is not a folder")
        self.paths = tuple(sorted((p for p in self.folder.glob(pattern) if p.is_file()), key=lambda p: p.name))
        if not self.paths:
            raise CameraSourceError(f"no image matches {pattern!r} in {str(self.folder)!r}")
        if timestamps is not None:
            timestamps = [float(t) for t in timestamps]
            if len(timestamps) != len(self.paths):
                raise ValueError(f"{len(timestamps)} timestamps for {len(self.paths)} images in {str(self.folder)!r}")
            if not all(math.isfinite(t) for t in timestamps) or any(b < a for a, b in zip(timestamps, timestamps[1:])):
                raise ValueError("image timestamps must be finite and non-decreasing")
        self.timestamps = None if timestamps is None else tuple(timestamps)
        self._clock = clock
        self._next = 0
        self._size: Size | None = None

    def __repr__(self) -> str:
        return f"ImageFolderSource({str(self.folder)!r})"

    @property
    def image_size(self) -> Size | None:
        return self._size

    def __len__(self) -> int:
        return len(self.paths)

    def read(self) -> Frame:
        self._check_open()
        if self._next >= len(self.paths):
            raise SourceLost(f"end of image folder {str(self.folder)!r} after {len(self.paths)} images")
        path = self.paths[self._next]
        image = read_mono8(path)
        height, width = image.shape
        if self._size is not None and (width, height) != self._size:
            raise CameraSourceError(
                f"image {str(path)!r} is {_format_size((width, height))}, the folder's first image "
                f"{_format_size(self._size)} (width x height)"
            )
        self._size = (width, height)
        timestamp = self.timestamps[self._next] if self.timestamps is not None else float(self._clock())
        frame = Frame(image, timestamp, self._next)
        self._next += 1
        return frame

    def read_after(self, t_s: float) -> Frame:
        """The next image: a still has no exposure time on the robot's clock, and a dry run
        on a folder checks the vision, not the timing."""
        return self.read()
