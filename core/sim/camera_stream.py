"""The simulated cell's camera as a network camera: an HTTP MJPEG stream.

Network cameras serve ``multipart/x-mixed-replace`` over HTTP, one JPEG per part; OpenCV's
FFmpeg backend opens such a stream by its URL (``cv2.VideoCapture(stream.url)``), so the
product reads the virtual cell exactly as it reads a real IP camera, through
``VideoCaptureSource``.

Timing is a camera's: frame k is exposed at t_k = t_0 + k / fps on a steady frame clock
(``render`` is called then, and shows the scene as it is at t_k), and it leaves the camera
``exposure_latency_s`` later (exposure, readout and encoding take that long on a real one).
A camera drops frames, it does not queue them: each client is sent the newest frame
whenever its socket can take one, and its send buffer is kept small, so a client that
reads slowly sees fewer frames, never old ones.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np

log = logging.getLogger("vservo.sim.camera_stream")

BOUNDARY = "vservoframe"
STREAM_PATH = "/stream.mjpg"
# Room for a few frames in the kernel per client (Linux doubles it; a 640 x 480 frame is
# about 9 kB at quality 100): enough to keep the link busy, too little to hold a backlog of
# stale frames. A client that reads slower than the frame rate skips frames instead.
SEND_BUFFER_BYTES = 16 * 1024


def encode_jpeg(image: np.ndarray, quality: int) -> bytes:
    """One frame as the stream sends it: an 8-bit monochrome (H, W) image as a JPEG."""
    if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8 or image.size == 0:
        what = f"{image.dtype} array of shape {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
        raise ValueError(f"a camera frame is a non-empty uint8 (height, width) image, got {what}")
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError(f"OpenCV could not encode a {image.shape[1]}x{image.shape[0]} frame as JPEG")
    return jpeg.tobytes()


class CameraStream:
    """An MJPEG camera on ``host``:``port`` (0: any free port), serving ``render()``'s view.

    render: the current 8-bit monochrome (H, W) view, called once per frame at its exposure
      time from the stream's frame thread.
    fps: frames per second of the frame clock.
    exposure_latency_s: time from a frame's exposure until it is sent.
    jpeg_quality: 0 .. 100, OpenCV's IMWRITE_JPEG_QUALITY. 100 by default: at 95 the
      detected corners move by up to 0.18 px on the cell's views, at 100 by 0.006 px, for
      a frame 17 % larger (docs/vision.md, "Through a stream").

    ``start()`` begins exposing frames and serving, ``close()`` stops both and closes the
    port, waiting for every thread it started; the stream is a context manager. Any number
    of clients may be connected at once, at ``url``.
    """

    def __init__(
        self,
        render: Callable[[], np.ndarray],
        *,
        fps: float = 30.0,
        exposure_latency_s: float = 0.05,
        jpeg_quality: int = 100,
        host: str = "127.0.0.1",
        port: int = 0,
    ) -> None:
        if not callable(render):
            raise ValueError(f"render must be a function returning the current view, got {type(render).__name__}")
        if not (math.isfinite(fps) and fps > 0.0):
            raise ValueError(f"fps must be finite and > 0, got {fps!r}")
        if not (math.isfinite(exposure_latency_s) and exposure_latency_s >= 0.0):
            raise ValueError(f"exposure_latency_s must be finite and >= 0, got {exposure_latency_s!r}")
        if isinstance(jpeg_quality, bool) or not isinstance(jpeg_quality, int) or not 0 <= jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be an integer in 0 .. 100, got {jpeg_quality!r}")
        self.render = render
        self.fps = float(fps)
        self.stalled = threading.Event()  # set: no frame is sent (a camera whose output hangs)
        self.exposure_latency_s = float(exposure_latency_s)
        self.jpeg_quality = jpeg_quality
        self._stop = threading.Event()
        self._sent = threading.Condition()
        self._jpeg: bytes | None = None  # the newest frame that left the camera
        self._frame_number = 0  # how many frames have left it
        self._connections: set[socket.socket] = set()
        self._server = _Server((host, port), self._handler_class())
        self._threads: list[threading.Thread] = []

    @property
    def url(self) -> str:
        host, port = self._server.socket.getsockname()[:2]  # (server_address, typed for every address family)
        return f"http://{host}:{port}{STREAM_PATH}"

    @property
    def frames_sent(self) -> int:
        """Frames that have left the camera so far (clients may have skipped some)."""
        with self._sent:
            return self._frame_number

    def start(self) -> CameraStream:
        if self._threads:
            raise RuntimeError(f"the camera stream at {self.url} is already started")
        self._threads = [
            threading.Thread(target=self._expose, name="camera-stream-clock", daemon=True),
            threading.Thread(
                target=self._server.serve_forever, kwargs={"poll_interval": 0.05}, name="camera-stream-server", daemon=True
            ),
        ]
        for thread in self._threads:
            thread.start()
        return self

    def close(self) -> None:
        """Stop the frame clock and the server, disconnect the clients, close the port."""
        self._stop.set()
        with self._sent:
            self._sent.notify_all()
            # A handler blocked sending to a client that stopped reading wakes up here.
            for connection in list(self._connections):
                try:
                    connection.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
        if self._threads:
            self._server.shutdown()
        for thread in self._threads:
            thread.join()
        self._server.server_close()  # joins the handler threads (ThreadingMixIn.block_on_close)

    def __enter__(self) -> CameraStream:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -- the camera ---------------------------------------------------------------------

    def _expose(self) -> None:
        """The frame clock: expose frame k at t_0 + k / fps, send it exposure_latency_s later.

        Frames in flight (exposed, not yet sent) wait in ``in_flight``; with a latency longer
        than a frame period several are, as in a real camera's pipeline. A frame the
        clock could not expose in time (an overloaded host) is skipped, keeping the clock
        steady rather than bunching frames up.
        """
        period = 1.0 / self.fps
        t0 = time.monotonic()
        k = 0
        in_flight: deque[tuple[float, bytes]] = deque()
        try:
            while not self._stop.is_set():
                t_exposure = t0 + k * period
                while in_flight and (not in_flight[0][0] > t_exposure):
                    self._wait_until(in_flight[0][0])
                    self._publish(in_flight.popleft()[1])
                self._wait_until(t_exposure)
                if self._stop.is_set():
                    break
                in_flight.append((t_exposure + self.exposure_latency_s, encode_jpeg(self.render(), self.jpeg_quality)))
                k = max(k + 1, math.floor((time.monotonic() - t0) / period) + 1)
        except Exception as exc:  # a broken render ends the stream; clients see it end
            log.error("camera stream at %s stopped: %s", self.url, exc)
            self._stop.set()
            with self._sent:
                self._sent.notify_all()

    def _wait_until(self, t: float) -> None:
        delay = t - time.monotonic()
        if delay > 0.0:
            self._stop.wait(delay)

    def _publish(self, jpeg: bytes) -> None:
        if self.stalled.is_set():
            return  # a stalled camera: its frames never leave it
        with self._sent:
            self._jpeg = jpeg
            self._frame_number += 1
            self._sent.notify_all()

    def newest_after(self, frame_number: int) -> tuple[int, bytes] | None:
        """The newest frame once one newer than ``frame_number`` has been sent; None once
        the stream stops."""
        with self._sent:
            while self._frame_number <= frame_number and not self._stop.is_set():
                self._sent.wait()
            if self._stop.is_set() or self._jpeg is None:
                return None
            return self._frame_number, self._jpeg

    # -- the server ---------------------------------------------------------------------

    def connect(self, connection: socket.socket) -> bool:
        """Count a client in, so that ``close`` can cut it off; False once closing."""
        with self._sent:
            if self._stop.is_set():
                return False
            self._connections.add(connection)
            return True

    def disconnect(self, connection: socket.socket) -> None:
        with self._sent:
            self._connections.discard(connection)

    def _handler_class(self) -> type[BaseHTTPRequestHandler]:
        stream = self

        class Handler(_StreamHandler):
            camera = stream

        return Handler


class _Server(ThreadingHTTPServer):
    daemon_threads = False  # server_close waits for the handlers: nothing is left running
    block_on_close = True


class _StreamHandler(BaseHTTPRequestHandler):
    """One client: the multipart stream at STREAM_PATH, 404 anywhere else."""

    camera: CameraStream
    protocol_version = "HTTP/1.0"  # the stream ends when the connection does

    def setup(self) -> None:
        self.request.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)
        super().setup()

    def log_message(self, format: str, *args: object) -> None:
        log.debug("%s: " + format, self.address_string(), *args)

    def do_GET(self) -> None:
        if self.path.split("?")[0] != STREAM_PATH:
            self.send_error(404, f"the camera serves {STREAM_PATH} only")
            return
        camera = self.camera
        if not camera.connect(self.request):
            return
        try:
            self.send_response(200)
            self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            sent = 0
            while (newest := camera.newest_after(sent)) is not None:
                sent, jpeg = newest
                # Blocks while the client's socket is full; the frames sent meanwhile are
                # skipped for this client, as a camera drops them.
                self.wfile.write(
                    f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n".encode() + jpeg + b"\r\n"
                )
        except OSError:  # the client went away, or close() disconnected it
            pass
        finally:
            camera.disconnect(self.request)
