"""Camera sources: real OpenCV capture of a written video, and fake captures that fail.

The video is written with cv2.VideoWriter, MJPG in .avi (works with opencv-python-
headless, whose bundled FFmpeg also writes XVID .avi and mp4v .mp4; the helper falls
back to those). Each frame encodes its index as the position of a bright vertical bar,
which survives MJPG's lossy compression. Read back, every frame is 3-channel BGR, so
the source's grey conversion is exercised by the real decoder.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import cv2
import numpy as np
import pytest

from vservo.core.perception.camera_source import (
    CameraSourceError,
    Frame,
    FrameSource,
    ImageFolderSource,
    SourceLost,
    VideoCaptureSource,
    is_video_file,
    to_mono8,
)

WIDTH, HEIGHT = 64, 48
N_FRAMES = 8
BAR_WIDTH = 4
BAR_STEP = 7

CODECS = (("MJPG", ".avi"), ("XVID", ".avi"), ("mp4v", ".mp4"))


def bar_frame(index: int) -> np.ndarray:
    """A colour frame whose bright bar starts at column BAR_STEP * index + 2."""
    image = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    start = BAR_STEP * index + 2
    image[:, start : start + BAR_WIDTH] = (255, 255, 255)
    return image


def bar_index(image: np.ndarray) -> int:
    """The frame index a bar frame encodes, read from the centre of its bright columns."""
    columns = np.flatnonzero(image.mean(axis=0) > 128)
    return round((columns.mean() - 2 - (BAR_WIDTH - 1) / 2) / BAR_STEP)


@pytest.fixture(scope="module")
def video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("video")
    for fourcc, ext in CODECS:
        path = folder / f"bars_{fourcc}{ext}"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10.0, (WIDTH, HEIGHT), isColor=True)
        if not writer.isOpened():
            continue
        for i in range(N_FRAMES):
            writer.write(bar_frame(i))
        writer.release()
        probe = cv2.VideoCapture(str(path))
        ok, _ = probe.read()
        probe.release()
        if ok:
            return path
    pytest.fail(f"no codec of {CODECS} writes a readable video with this OpenCV build")


def fake_clock(start: float = 100.0, step: float = 0.25):
    ticks = itertools.count()
    return lambda: start + step * next(ticks)


def test_video_file_reads_grey_frames_in_order_then_ends(video: Path) -> None:
    with VideoCaptureSource(str(video), clock=fake_clock()) as source:
        assert isinstance(source, FrameSource)
        frames = [source.read() for _ in range(N_FRAMES)]
        with pytest.raises(SourceLost, match="end of video file"):
            source.read()
        with pytest.raises(SourceLost):  # stays lost
            source.read()
    for i, frame in enumerate(frames):
        assert frame.image.shape == (HEIGHT, WIDTH) and frame.image.dtype == np.uint8
        assert frame.index == i
        assert bar_index(frame.image) == i
        assert frame.timestamp_s == pytest.approx(100.0 + 0.25 * i)
    assert source.image_size == (WIDTH, HEIGHT)


def test_video_file_loop_rewinds_and_keeps_counting(video: Path) -> None:
    with VideoCaptureSource(str(video), loop=True, clock=fake_clock()) as source:
        frames = [source.read() for _ in range(N_FRAMES + 3)]
    assert [f.index for f in frames] == list(range(N_FRAMES + 3))
    assert [bar_index(f.image) for f in frames] == list(range(N_FRAMES)) + [0, 1, 2]
    timestamps = [f.timestamp_s for f in frames]
    assert timestamps == sorted(timestamps)


def test_expected_size_is_checked(video: Path) -> None:
    with VideoCaptureSource(str(video), expected_size=(WIDTH, HEIGHT)) as source:
        assert source.image_size == (WIDTH, HEIGHT)
        assert source.read().size == (WIDTH, HEIGHT)
    with VideoCaptureSource(str(video), expected_size=(640, 480)) as source:
        with pytest.raises(CameraSourceError, match=r"64x48 frame, expected 640x480") as info:
            source.read()
        assert not isinstance(info.value, SourceLost)


def test_missing_file_is_named(tmp_path: Path) -> None:
    missing = tmp_path / "nope.avi"
    with pytest.raises(CameraSourceError, match="nope.avi.*no such file"):
        VideoCaptureSource(str(missing))


def test_file_that_is_not_a_video(tmp_path: Path) -> None:
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"not a video at all")
    with pytest.raises(CameraSourceError, match="junk.avi"):
        VideoCaptureSource(str(junk))


def test_a_missing_device_is_a_set_up_error_named_by_its_index() -> None:
    # Through the real OpenCV: no retries for a device that does not exist.
    with pytest.raises(CameraSourceError, match="camera device 99"):
        VideoCaptureSource(99)


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="video files only"):
        VideoCaptureSource(0, loop=True, opener=lambda spec: FakeCapture([]))
    with pytest.raises(ValueError, match="reconnect_attempts"):
        VideoCaptureSource(0, reconnect_attempts=-1, opener=lambda spec: FakeCapture([]))
    with pytest.raises(ValueError, match="expected_size"):
        VideoCaptureSource(0, expected_size=(640,), opener=lambda spec: FakeCapture([]))
    with pytest.raises(ValueError, match="spec"):
        VideoCaptureSource(True)


def test_live_or_file() -> None:
    assert is_video_file("run.avi") and is_video_file("frames/img_%04d.png")
    assert not is_video_file(0)
    assert not is_video_file("rtsp://192.168.0.10/stream")
    assert not is_video_file("/dev/video0")
    assert not is_video_file("v4l2src ! videoconvert ! appsink")


# --- fake captures: reconnection without waiting -------------------------------------------


class FakeCapture:
    """A capture that plays a script: an image to deliver, or None for a failed read."""

    def __init__(self, script: list[np.ndarray | None], opened: bool = True) -> None:
        self.script = list(script)
        self.opened = opened
        self.released = False

    def isOpened(self) -> bool:
        return self.opened

    def read(self):
        if self.released or not self.script:
            return False, None
        image = self.script.pop(0)
        return (image is not None), image

    def release(self) -> None:
        self.released = True

    def set(self, prop_id: int, value: float) -> bool:
        return False

    def get(self, prop_id: int) -> float:
        return 0.0


class Opener:
    """Hands out the given captures in turn and counts the calls."""

    def __init__(self, captures: list[FakeCapture]) -> None:
        self.captures = list(captures)
        self.calls: list[int | str] = []
        self.made: list[FakeCapture] = []

    def __call__(self, spec: int | str) -> FakeCapture:
        self.calls.append(spec)
        capture = self.captures.pop(0) if self.captures else FakeCapture([None] * 3)
        self.made.append(capture)
        return capture


def grey(value: int) -> np.ndarray:
    return np.full((HEIGHT, WIDTH), value, np.uint8)


def test_reconnects_after_failed_reads() -> None:
    """A live source's reader reconnects on its own; the consumer sees the frame after the
    outage, then SourceLost once the camera stays away through every attempt."""
    opener = Opener(
        [
            FakeCapture([grey(1), None]),  # drops out after a frame
            FakeCapture([], opened=False),  # first reopen: device not back yet
            FakeCapture([None]),  # second: opens but no frame yet
            FakeCapture([grey(3)]),  # third: back for a frame, then gone for good
        ]
    )
    sleeps: list[float] = []
    source = VideoCaptureSource(2, reconnect_attempts=3, reconnect_delay_s=0.5, opener=opener, sleep=sleeps.append)
    values = []
    with pytest.raises(SourceLost, match="3 reconnection attempts"):
        while True:
            values.append(int(source.read().image[0, 0]))
    # The reader keeps only the newest frame: 1 may have been replaced before it was read.
    assert values in ([1, 3], [3])
    assert sleeps == [0.5] * 6  # three attempts to bring it back, three before giving up
    assert opener.calls == [2] * 7
    assert all(c.released for c in opener.made)
    source.close()


def test_source_lost_after_exactly_the_reconnect_attempts() -> None:
    opener = Opener([FakeCapture([grey(7), None])] + [FakeCapture([None]) for _ in range(10)])
    sleeps: list[float] = []
    source = VideoCaptureSource(
        "rtsp://cell/cam", reconnect_attempts=4, reconnect_delay_s=0.2, opener=opener, sleep=sleeps.append
    )
    assert source.read().index == 0
    with pytest.raises(SourceLost, match="4 reconnection attempts"):
        source.read()
    assert len(opener.calls) == 1 + 4
    assert sleeps == [0.2] * 4
    assert all(c.released for c in opener.made)
    with pytest.raises(SourceLost):  # gone for good: no further attempts
        source.read()
    assert len(opener.calls) == 5


def test_no_reconnect_attempts_means_lost_at_first_failure() -> None:
    opener = Opener([FakeCapture([None])])
    source = VideoCaptureSource(0, reconnect_attempts=0, opener=opener, sleep=pytest.fail)
    with pytest.raises(SourceLost):
        source.read()
    assert len(opener.calls) == 1


def test_opener_exception_is_a_camera_error() -> None:
    def opener(spec):
        raise cv2.error("backend exploded")

    with pytest.raises(CameraSourceError, match="camera device 5.*backend exploded"):
        VideoCaptureSource(5, opener=opener)


def test_colour_and_16_bit_frames_become_mono8() -> None:
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    deep = rng.integers(0, 65536, (HEIGHT, WIDTH), dtype=np.uint16)
    opener = Opener([FakeCapture([bgr, deep, deep[:, :, None]])])  # a decoder of a file: every frame is read
    with VideoCaptureSource("frames.avi", opener=opener, clock=fake_clock()) as source:
        np.testing.assert_array_equal(source.read().image, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
        np.testing.assert_array_equal(source.read().image, (deep >> 8).astype(np.uint8))
        np.testing.assert_array_equal(source.read().image, (deep >> 8).astype(np.uint8))
    with pytest.raises(CameraSourceError, match="pixel type"):
        to_mono8(np.zeros((4, 4), np.float32))


def test_closed_source_refuses_to_read() -> None:
    source = VideoCaptureSource(0, opener=Opener([FakeCapture([grey(1)])]))
    source.close()
    source.close()
    with pytest.raises(CameraSourceError, match="closed"):
        source.read()


def test_frame_validates_its_image() -> None:
    with pytest.raises(ValueError, match="uint8"):
        Frame(np.zeros((4, 4, 3), np.uint8), 0.0, 0)
    with pytest.raises(ValueError, match="uint8"):
        Frame(np.zeros((4, 4), np.float64), 0.0, 0)
    with pytest.raises(ValueError, match="timestamp"):
        Frame(grey(0), float("nan"), 0)
    with pytest.raises(ValueError, match="index"):
        Frame(grey(0), 0.0, -1)
    assert Frame(grey(0), 1.5, 3).size == (WIDTH, HEIGHT)


# --- still images -------------------------------------------------------------------------


def test_image_folder_plays_sorted_images(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "002.png"), bar_frame(2))  # colour
    cv2.imwrite(str(tmp_path / "000.png"), bar_frame(0)[:, :, 0])
    cv2.imwrite(str(tmp_path / "001.png"), bar_frame(1)[:, :, 0].astype(np.uint16) * 257)  # 16-bit
    (tmp_path / "notes.txt").write_text("not an image")
    with ImageFolderSource(tmp_path, timestamps=[0.0, 0.1, 0.2]) as source:
        assert isinstance(source, FrameSource)
        frames = [source.read() for _ in range(3)]
        with pytest.raises(SourceLost, match="3 images"):
            source.read()
    assert [bar_index(f.image) for f in frames] == [0, 1, 2]
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.timestamp_s for f in frames] == [0.0, 0.1, 0.2]
    assert source.image_size == (WIDTH, HEIGHT)


def test_image_folder_errors(tmp_path: Path) -> None:
    with pytest.raises(CameraSourceError, match="no image matches"):
        ImageFolderSource(tmp_path)
    with pytest.raises(CameraSourceError, match="does not exist"):
        ImageFolderSource(tmp_path / "missing")
    cv2.imwrite(str(tmp_path / "a.png"), grey(1))
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match="1 timestamps for 2 images"):
        ImageFolderSource(tmp_path, timestamps=[0.0])
    source = ImageFolderSource(tmp_path, clock=fake_clock())
    assert source.read().timestamp_s == 100.0
    with pytest.raises(CameraSourceError, match=r"b\.png.*10x10.*64x48"):
        source.read()


def test_read_after_ahead_of_the_clock_names_the_source() -> None:
    with VideoCaptureSource(0, opener=Opener([FakeCapture([grey(1)])]), clock=lambda: 100.0) as source:
        with pytest.raises(CameraSourceError, match=r"camera device 0: .*0\.500 s ahead of the source's clock"):
            source.read_after(100.5)


def test_a_video_file_reads_after_any_time_its_next_frame(video: Path) -> None:
    """A file's frames are not live: no wait, no discards, whatever the latency and buffer."""
    with VideoCaptureSource(str(video), exposure_latency_s=0.1, buffer_frames=2, clock=fake_clock(), sleep=pytest.fail) as source:
        assert [bar_index(source.read_after(t).image) for t in (0.0, 50.0, 99.0)] == [0, 1, 2]


def test_an_image_folder_reads_after_any_time_its_next_image(tmp_path: Path) -> None:
    for i in range(2):
        cv2.imwrite(str(tmp_path / f"{i:02d}.png"), np.full((4, 6), 10 * i, np.uint8))
    with ImageFolderSource(tmp_path, timestamps=[0.0, 0.1]) as source:
        assert [source.read_after(5.0).index for _ in range(2)] == [0, 1]
