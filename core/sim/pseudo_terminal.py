"""A pseudo-terminal pair in raw mode: a serial line without hardware (docs/robot-link.md, "The emulator").

The JRC emulator keeps the master end; the host opens the slave's device path
with pyserial, as it would open /dev/ttyS0. The slave is put in raw mode before anything
is written (the default line discipline echoes bytes and turns CR into newlines, which
corrupts BSC blocks), and its descriptor stays open for the pair's lifetime so the
settings hold and the master never reads EIO between two host connections.
"""

from __future__ import annotations

import fcntl
import os
import select
import termios
import tty


class FdPort:
    """A bsc.Port on a file descriptor: the master end of a pseudo-terminal."""

    def __init__(self, fd: int, poll_s: float = 0.005) -> None:
        self.fd, self.poll_s = fd, poll_s

    @property
    def in_waiting(self) -> int:
        return int.from_bytes(fcntl.ioctl(self.fd, termios.FIONREAD, b"\0\0\0\0"), "little")

    def read(self, size: int) -> bytes:
        ready, _, _ = select.select([self.fd], [], [], self.poll_s)
        return os.read(self.fd, size) if ready else b""

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            view = view[os.write(self.fd, view) :]
        return len(data)


class PseudoTerminal:
    """``device`` is the path the host opens; ``port`` the JRC's end."""

    def __init__(self) -> None:
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd)
        self.device = os.ttyname(self.slave_fd)
        self.port = FdPort(self.master_fd)

    def close(self) -> None:
        """Close both ends; safe to call twice."""
        for fd in (self.master_fd, self.slave_fd):
            if fd >= 0:
                os.close(fd)
        self.master_fd = self.slave_fd = -1

    def __enter__(self) -> PseudoTerminal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
