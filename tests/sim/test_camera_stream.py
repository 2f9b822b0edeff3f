"""The simulated camera as an MJPEG network stream, read back by OpenCV through
VideoCaptureSource: real sockets, real JPEG, OpenCV's own FFmpeg demuxer.

Each rendered frame writes its serial number in binary as 16 large black or white blocks,
which survive JPEG; the test keeps the exposure time of every serial number, so it knows
when any frame it reads was exposed.
"""

from __future__ import annotations

import os
import socket
import threading
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from vservo.core.perception.camera_source import (
    FFMPEG_OPTIONS_VARIABLE,
    STREAM_RECEIVE_BUFFER_BYTES,
    SourceLost,
    VideoCaptureSource,
)
from vservo.core.sim.camera_stream import CameraStream

BITS = 16
BLOCK = 16  # pixels per bit block


class NumberedScene:
    """A render function whose frames carry their serial number; it records when each was exposed."""

    def __init__(self) -> None:
        self.exposed_s: list[float] = []
        self.lock = threading.Lock()

    def __call__(self) -> np.ndarray:
        with self.lock:
            number = len(self.exposed_s)
            self.exposed_s.append(time.monotonic())
        bits = (number >> np.arange(BITS)) & 1
        return np.repeat(np.repeat(255 * bits[None, :].astype(np.uint8), BLOCK, axis=0), BLOCK, axis=1)

    def exposure_of(self, image: np.ndarray) -> float:
        blocks = image.reshape(BLOCK, BLOCK * BITS).mean(axis=0).reshape(BITS, BLOCK).mean(axis=1)
        number = int(np.sum((blocks > 128) << np.arange(BITS)))
        with self.lock:
            return self.exposed_s[number]


def test_opencv_opens_the_stream_and_reads_the_frames_as_rendered() -> None:
    scene = NumberedScene()
    with CameraStream(scene, fps=50, exposure_latency_s=0.0) as stream:
        assert stream.url.startswith("http://127.0.0.1:") and stream.url.endswith("/stream.mjpg")
        capture = cv2.VideoCapture(stream.url)
        try:
            assert capture.isOpened()
            exposures = []
            for _ in range(5):
                ok, image = capture.read()
                assert ok and image.shape[:2] == (BLOCK, BLOCK * BITS)
                exposures.append(scene.exposure_of(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)))
        finally:
            capture.release()
    assert exposures == sorted(exposures) and len(set(exposures)) == 5


def test_several_clients_at_once_and_a_clean_stop() -> None:
    threads_before = set(threading.enumerate())
    stream = CameraStream(NumberedScene(), fps=50, exposure_latency_s=0.01).start()
    url, port = stream.url, int(stream.url.split(":")[2].split("/")[0])
    with pytest.raises(urllib.error.HTTPError) as not_found:
        urllib.request.urlopen(url.replace("stream.mjpg", "other"), timeout=5)
    assert not_found.value.code == 404
    sources = [VideoCaptureSource(url, reconnect_attempts=1, reconnect_delay_s=0.05) for _ in range(3)]
    stalled = socket.create_connection(("127.0.0.1", port))  # a client that asks, then never reads
    stalled.sendall(b"GET /stream.mjpg HTTP/1.0\r\n\r\n")
    try:
        assert all(source.read().image.shape == (BLOCK, BLOCK * BITS) for source in sources)
        stream.close()
        for source in sources:  # the stream's end reaches every client
            with pytest.raises(SourceLost):
                while True:
                    source.read()
    finally:
        for source in sources:
            source.close()
        stalled.close()
    assert set(threading.enumerate()) <= threads_before
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", port), timeout=5)


def test_read_after_never_returns_a_frame_exposed_before_the_motion_ended() -> None:
    """A slow consumer: it 'moves the robot' for a while between reads, as the look-and-move
    loop does, while the stream keeps exposing frames that arrive 80 ms late. The newest
    frame that has arrived when the motion ends is stale (the check that the hazard is
    there); read_after's frame never is."""
    scene = NumberedScene()
    stream_latency_s = 0.08
    with (
        CameraStream(scene, fps=30, exposure_latency_s=stream_latency_s) as stream,
        VideoCaptureSource(stream.url, exposure_latency_s=stream_latency_s + 0.07, reconnect_attempts=0) as source,
    ):
        source.read()
        for motion_s in (0.15, 0.1, 0.2, 0.12, 0.25, 0.1):
            time.sleep(motion_s)
            motion_ended_s = time.monotonic()
            newest = source.read()
            assert scene.exposure_of(newest.image) < motion_ended_s
            fresh = source.read_after(motion_ended_s)
            assert scene.exposure_of(fresh.image) >= motion_ended_s
            assert fresh.timestamp_s >= motion_ended_s


def test_buffer_frames_are_discarded_after_the_fresh_one() -> None:
    scene = NumberedScene()
    with (
        CameraStream(scene, fps=30, exposure_latency_s=0.02) as stream,
        VideoCaptureSource(stream.url, exposure_latency_s=0.06, buffer_frames=2, reconnect_attempts=0) as source,
    ):
        first = source.read()
        motion_ended_s = time.monotonic()
        fresh = source.read_after(motion_ended_s)
        assert fresh.index == first.index + 3  # the first frame after the motion and two more
        assert scene.exposure_of(fresh.image) >= motion_ended_s


def test_bad_settings_are_named() -> None:
    with pytest.raises(ValueError, match="fps"):
        CameraStream(NumberedScene(), fps=0.0)
    with pytest.raises(ValueError, match="jpeg_quality"):
        CameraStream(NumberedScene(), jpeg_quality=101)
    with pytest.raises(ValueError, match="exposure_latency_s"):
        CameraStream(NumberedScene(), exposure_latency_s=-0.1)


def read_part(stream_file) -> bytes:
    """The next JPEG of a multipart/x-mixed-replace body."""
    length = None
    while (line := stream_file.readline()) not in (b"\r\n", b""):
        if line.lower().startswith(b"content-length:"):
            length = int(line.split(b":")[1])
    assert length is not None, "a part without Content-Length"
    jpeg = stream_file.read(length)
    stream_file.readline()  # the CRLF after the JPEG
    return jpeg


def test_a_slow_client_is_sent_the_newest_frame_not_a_backlog() -> None:
    """Frames of 320x240 noise (about 80 kB each, so the kernel's buffers hold only a few):
    a client that stops reading for half a second gets, after what the buffers held, a
    frame exposed late in its pause, and far fewer frames than the camera sent."""
    scene = NumberedScene()
    rng = np.random.default_rng(0)

    def noisy() -> np.ndarray:
        image = rng.integers(0, 256, (240, 320), dtype=np.uint8)
        image[:BLOCK, : BLOCK * BITS] = scene()
        return image

    with CameraStream(noisy, fps=50, exposure_latency_s=0.0) as stream:
        port = int(stream.url.split(":")[2].split("/")[0])
        with socket.create_connection(("127.0.0.1", port)) as client:
            client.sendall(b"GET /stream.mjpg HTTP/1.0\r\n\r\n")
            body = client.makefile("rb")
            while body.readline() != b"\r\n":  # the response's headers
                pass
            read_part(body)
            paused_s = time.monotonic()
            time.sleep(0.5)
            received = 1
            exposures = []
            while len(exposures) < 8 and not (exposures and exposures[-1] > paused_s + 0.25):
                image = cv2.imdecode(np.frombuffer(read_part(body), np.uint8), cv2.IMREAD_GRAYSCALE)
                exposures.append(scene.exposure_of(image[:BLOCK, : BLOCK * BITS]))
                received += 1
            sent = stream.frames_sent
    # What the buffers held came first (a few frames exposed just after the pause began),
    # then a frame from its second half: the frames between were skipped, not queued.
    assert exposures[-1] > paused_s + 0.25, [round(t - paused_s, 3) for t in exposures]
    assert received < sent - 10  # about 25 frames were sent while it slept


def receive_buffers_to(port: int) -> list[int]:
    """SO_RCVBUF of each of this process's TCP sockets connected to ``port`` (OpenCV's among them)."""
    sizes = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            sock = socket.socket(fileno=os.dup(int(fd)))
        except OSError:  # not a socket
            continue
        with sock:
            try:
                if sock.type == socket.SOCK_STREAM and sock.getpeername()[1] == port:
                    sizes.append(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
            except (OSError, IndexError, TypeError):  # unconnected, or not an IP socket
                continue
    return sizes


@pytest.mark.parametrize("set_before", [None, "recv_buffer_size;40000"])
def test_a_stream_is_read_through_a_small_receive_buffer_unless_the_environment_sets_one(monkeypatch, set_before) -> None:
    """Left to itself the kernel grows a stream's receive buffer to megabytes of waiting frames
    (docs/vision.md, "A host too busy to read its camera"); the source pins it while OpenCV
    opens the stream, and leaves the environment as it found it."""
    if set_before is None:
        monkeypatch.delenv(FFMPEG_OPTIONS_VARIABLE, raising=False)
    else:
        monkeypatch.setenv(FFMPEG_OPTIONS_VARIABLE, set_before)
    with CameraStream(NumberedScene(), fps=50, exposure_latency_s=0.0) as stream:
        port = int(stream.url.split(":")[2].split("/")[0])
        with VideoCaptureSource(stream.url) as source:
            source.read()
            buffers = receive_buffers_to(port)
    # Linux doubles what it is asked for.
    assert buffers == [2 * (STREAM_RECEIVE_BUFFER_BYTES if set_before is None else 40000)]
    assert os.environ.get(FFMPEG_OPTIONS_VARIABLE) == set_before


def test_a_render_of_the_wrong_kind_ends_the_stream_and_says_why(caplog: pytest.LogCaptureFixture) -> None:
    with CameraStream(lambda: np.zeros((48, 64), np.float32)) as stream:
        capture = cv2.VideoCapture(stream.url)
        opened = capture.isOpened()
        capture.release()
    assert not opened
    assert "non-empty uint8 (height, width) image, got float32 array of shape (48, 64)" in caplog.text
