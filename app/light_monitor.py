"""Light monitors: clients of ``vservo serve`` that read what its page would receive, without a browser.

A light monitor connects to viser's WebSocket as the page does (the subprotocol
``viser-v<version>``: viser refuses a client of another version), decodes every batch of
messages the server sends and counts the camera frames, the updates of an image element's
JPEG. It renders nothing, so the frames it counts are what the server manages to send, not
what a renderer manages to show (``vservo bench ui`` measures both).

Viser's framing of one batch (viser 1.1.1 is pinned; its viser/infra/_infra.py,
``_message_producer``):

    [8 bytes]  size of the msgpack payload (little-endian)
    [8 bytes]  size of the zstd-compressed payload (little-endian)
    [N bytes]  the zstd-compressed msgpack {"messages": [...], "timestampSec", "binaryBufferLengths"}
    then the binary buffers (numpy arrays), each at an 8-byte-aligned offset, referred to from
    the messages by placeholders {"__binary_index": i, "dtype": ...}.

``LightMonitors`` runs several monitors in a process of their own (spawned), so their
decoding takes no time from the server's interpreter when both run on one machine.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import time
from dataclasses import dataclass, field
from enum import StrEnum
from importlib.metadata import version
from typing import Any
from urllib.parse import urlsplit

import msgspec.msgpack
import numpy as np
import websockets.asyncio.client
import zstandard
from websockets.typing import Origin, Subprotocol

from vservo.core.errors import VservoError

HEADER_BYTES = 16
READY_TIMEOUT_S = 60.0
LIGHT_COUNTS = (1, 5, 20)  # light clients ``vservo bench ui`` connects by default


class Monitors(StrEnum):
    """The monitors ``vservo bench ui`` connects (defined here, light to import, for its options)."""

    LIGHT = "light"  # light monitors (this module): every message decoded, nothing rendered
    CHROMIUM = "chromium"  # headless Chromium pages, rendering the whole page
    BOTH = "both"


class MonitorError(VservoError, RuntimeError):
    """A light monitor could not connect or read what the server sent."""


def _resolve_buffers(value: Any, buffers: list[memoryview]) -> Any:
    """The messages with their binary placeholders replaced by the arrays they stand for."""
    if isinstance(value, dict):
        if "__binary_index" in value and "dtype" in value:
            return np.frombuffer(buffers[value["__binary_index"]], dtype=np.dtype(value["dtype"]))
        return {key: _resolve_buffers(inner, buffers) for key, inner in value.items()}
    if isinstance(value, list):
        return [_resolve_buffers(inner, buffers) for inner in value]
    return value


def decode_batch(raw: bytes, decompressor: zstandard.ZstdDecompressor) -> list[dict]:
    """One WebSocket message from viser's server as the list of its messages (dicts with a "type")."""
    if len(raw) < HEADER_BYTES:
        raise MonitorError(f"a viser batch of {len(raw)} bytes is shorter than its {HEADER_BYTES}-byte header")
    size, compressed_size = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
    end = HEADER_BYTES + compressed_size
    payload = msgspec.msgpack.decode(decompressor.decompress(raw[HEADER_BYTES:end], max_output_size=size))
    buffers, offset, view = [], end, memoryview(raw)
    for length in payload["binaryBufferLengths"]:
        offset += (8 - offset % 8) % 8
        buffers.append(view[offset : offset + length])
        offset += length
    if offset > len(raw):
        raise MonitorError(f"a viser batch of {len(raw)} bytes announces {offset} bytes of binary buffers")
    return _resolve_buffers(payload["messages"], buffers)


@dataclass
class ImageStream:
    """One image element of the page: its label and the time (monotonic s) of each JPEG received."""

    label: str
    times: list[float] = field(default_factory=list)
    last_jpeg: bytes | None = None

    def receive(self, data: bytes | None, at: float) -> None:
        if data:
            self.times.append(at)
            self.last_jpeg = data


class LightMonitor:
    """One client of the page: decodes every batch, keeps the image elements' frame times."""

    def __init__(self, url: str) -> None:
        self.url = url.replace("http://", "ws://", 1).replace("https://", "wss://", 1)
        page = urlsplit(url)  # the Origin the page's browser sends: the server accepts only its own page
        self.origin = f"{page.scheme}://{page.netloc}"
        self.images: dict[str, ImageStream] = {}
        self.messages = 0
        self.received_bytes = 0
        self.connected = asyncio.Event()

    def camera(self) -> ImageStream | None:
        """The camera image: of the page's image elements, the one updated most (only it streams)."""
        return max(self.images.values(), key=lambda stream: len(stream.times), default=None)

    def take(self, batch: list[dict], at: float) -> None:
        for message in batch:
            self.messages += 1
            kind = message["type"]
            if kind == "GuiImageMessage":
                stream = self.images.setdefault(message["uuid"], ImageStream(message["props"].get("label") or ""))
                stream.receive(message["props"].get("_data"), at)
            elif kind == "GuiUpdateMessage" and message["uuid"] in self.images:
                self.images[message["uuid"]].receive(message["updates"].get("_data"), at)
            elif kind == "GuiRemoveMessage":
                self.images.pop(message["uuid"], None)

    async def run(self, stop: asyncio.Event) -> None:
        """Read the server until ``stop`` is set (or the server closes the connection)."""
        decompressor = zstandard.ZstdDecompressor()
        async with websockets.asyncio.client.connect(
            self.url, subprotocols=[Subprotocol(f"viser-v{version('viser')}")], origin=Origin(self.origin), max_size=None
        ) as connection:
            self.connected.set()
            stopping = asyncio.ensure_future(stop.wait())
            try:
                while not stop.is_set():
                    receiving = asyncio.ensure_future(connection.recv())
                    await asyncio.wait({receiving, stopping}, return_when=asyncio.FIRST_COMPLETED)
                    if not receiving.done():
                        receiving.cancel()
                        break
                    raw = receiving.result()
                    if isinstance(raw, str):
                        raise MonitorError(f"{self.url}: a text message where viser sends binary batches")
                    self.received_bytes += len(raw)
                    self.take(decode_batch(raw, decompressor), time.monotonic())
            finally:
                stopping.cancel()


# -- several monitors in their own process -----------------------------------------------------


async def _serve_monitors(url: str, count: int, connection: Any) -> None:
    """The monitors' process: connect ``count`` monitors, then answer the parent's requests."""
    monitors = [LightMonitor(url) for _ in range(count)]
    stop = asyncio.Event()
    tasks = [asyncio.create_task(monitor.run(stop)) for monitor in monitors]

    def failure() -> str | None:
        for task in tasks:
            if task.done():
                why = "cancelled" if task.cancelled() else repr(task.exception() or "the server closed the connection")
                return f"a light monitor of {url} stopped: {why}"
        return None

    async def all_ready() -> None:
        while not all(monitor.camera() is not None for monitor in monitors) and failure() is None:
            await asyncio.sleep(0.05)

    try:
        await asyncio.wait_for(all_ready(), READY_TIMEOUT_S)
    except TimeoutError:
        pass
    connection.send(
        failure()
        or (
            "ready"
            if all(m.camera() for m in monitors)
            else f"the page of {url} showed no image element within {READY_TIMEOUT_S:.0f} s"
        )
    )
    while await asyncio.to_thread(connection.recv) == "frames":
        connection.send(failure() or [list(camera.times) if (camera := m.camera()) else [] for m in monitors])
    stop.set()
    await asyncio.gather(*tasks, return_exceptions=True)


def _monitors_main(url: str, count: int, connection: Any) -> None:
    asyncio.run(_serve_monitors(url, count, connection))


class LightMonitors:
    """``count`` light monitors of ``url`` in a spawned process; ``frames()`` their camera frame times."""

    def __init__(self, url: str, count: int) -> None:
        self.count = count
        context = multiprocessing.get_context("spawn")  # the server's threads must not be forked
        self._connection, child = context.Pipe()
        self.process = context.Process(target=_monitors_main, args=(url, count, child), name="light-monitors", daemon=True)
        self.process.start()
        child.close()
        try:
            self._expect(self._reply(READY_TIMEOUT_S + 30.0), str)
        except BaseException:
            self.close()
            raise

    def _reply(self, timeout_s: float) -> Any:
        if not self._connection.poll(timeout_s):
            raise MonitorError(f"the light monitors' process did not answer within {timeout_s:.0f} s")
        try:
            return self._connection.recv()
        except EOFError:
            raise MonitorError(f"the light monitors' process ended (exit code {self.process.exitcode})") from None

    @staticmethod
    def _expect(reply: Any, kind: type) -> Any:
        if isinstance(reply, str) and reply != "ready":
            raise MonitorError(reply)
        if not isinstance(reply, kind):
            raise MonitorError(f"the light monitors' process answered {reply!r}")
        return reply

    def frames(self) -> list[list[float]]:
        """Per monitor, the monotonic time (s, this machine's clock) of each camera frame it received."""
        self._connection.send("frames")
        return self._expect(self._reply(30.0), list)

    def close(self) -> None:
        if self.process.is_alive():
            try:
                self._connection.send("stop")
            except OSError:
                pass
            self.process.join(10.0)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self._connection.close()

    def __enter__(self) -> LightMonitors:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
