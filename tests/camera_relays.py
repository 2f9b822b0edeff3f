"""Loopback TCP relays put between the virtual cell's camera stream and the product, to make
the camera misbehave as a real one (or a busy host reading it) can: stall, or arrive late.
The product reaches the camera through a copy of the cell file pointing at the relay."""

from __future__ import annotations

import queue
import socket
import threading
import time
import tomllib
from pathlib import Path
from typing import Any

from tests.virtual_cell_process import VirtualCellProcess
from vservo.core.cell.cell_file import dumps_cell


class LoopbackRelay:
    """A TCP relay on loopback in front of ``upstream``: each connection accepted is joined
    to one of its own to the upstream; ``_join`` says how the bytes go on."""

    def __init__(self, upstream: tuple[str, int]) -> None:
        self.upstream = upstream
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.closing = False
        self.sockets: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def close(self) -> None:
        self.closing = True
        self.listener.close()
        for sock in self.sockets:
            sock.close()

    def _accept(self) -> None:
        while not self.closing:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            server = socket.create_connection(self.upstream)
            self.sockets += [client, server]
            self._join(client, server)

    def _join(self, client: socket.socket, server: socket.socket) -> None:
        raise NotImplementedError

    @staticmethod
    def _start(target: Any, *args: Any) -> None:
        threading.Thread(target=target, args=args, daemon=True).start()


class StallingRelay(LoopbackRelay):
    """A relay that can stall: a connection open when ``stall`` is called never forwards
    another byte, yet stays open; connections made after ``resume`` flow."""

    def __init__(self, upstream: tuple[str, int]) -> None:
        self.generation = 0  # a connection forwards only while it is of the current generation
        self.flowing = True
        super().__init__(upstream)

    def stall(self) -> None:
        self.flowing = False
        self.generation += 1

    def resume(self) -> None:
        self.flowing = True

    def _join(self, client: socket.socket, server: socket.socket) -> None:
        for source, sink in ((client, server), (server, client)):
            self._start(self._pump, source, sink, self.generation)

    def _pump(self, source: socket.socket, sink: socket.socket, generation: int) -> None:
        try:
            while data := source.recv(65536):
                while not (self.flowing and generation == self.generation):
                    if self.closing:
                        return
                    time.sleep(0.02)
                sink.sendall(data)
        except OSError:
            pass


class DelayingRelay(LoopbackRelay):
    """A relay that hands what the server sends on ``delay_s`` after it came (none at first):
    a stream as a reader that fell behind sees it."""

    def __init__(self, upstream: tuple[str, int]) -> None:
        self.delay_s = 0.0
        super().__init__(upstream)

    def _join(self, client: socket.socket, server: socket.socket) -> None:
        held: queue.Queue[tuple[float, bytes]] = queue.Queue()
        self._start(self._forward, client, server)  # the requests, at once
        self._start(self._hold, server, held)
        self._start(self._hand_on, held, client)

    @staticmethod
    def _forward(source: socket.socket, sink: socket.socket) -> None:
        try:
            while data := source.recv(65536):
                sink.sendall(data)
        except OSError:
            pass

    def _hold(self, source: socket.socket, held: queue.Queue) -> None:
        try:
            while data := source.recv(65536):
                held.put((time.monotonic() + self.delay_s, data))
        except OSError:
            pass

    @staticmethod
    def _hand_on(held: queue.Queue, sink: socket.socket) -> None:
        try:
            while True:
                due_s, data = held.get()
                time.sleep(max(0.0, due_s - time.monotonic()))
                sink.sendall(data)
        except OSError:
            pass


def camera_through(cell: VirtualCellProcess, relay_class: type[LoopbackRelay], cell_file: Path, **tables: Any) -> LoopbackRelay:
    """A relay of ``relay_class`` in front of ``cell``'s camera, and at ``cell_file`` a copy of
    its cell file whose camera is reached through it (top-level ``tables`` updated as given)."""
    camera_url = cell.addresses["camera_url"]
    host_port = camera_url.split("//")[1].split("/")[0]
    host, port = host_port.rsplit(":", 1)
    relay = relay_class((host, int(port)))
    copy = tomllib.loads(Path(cell.addresses["cell_file"]).read_text())
    copy["camera"]["source"]["device"] = camera_url.replace(host_port, f"127.0.0.1:{relay.port}")
    for name, table in tables.items():
        copy.setdefault(name, {}).update(table)
    cell_file.write_text(dumps_cell(copy))
    return relay
