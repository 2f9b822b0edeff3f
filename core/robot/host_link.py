"""What carries the Yaskawa host commands: one command out, the controller's answer back.

The host command set (docs/robot-link.md: RPOSC, RSTATS, MOVL, IMOV, HOLD, SVON, IOREAD,
IOWRITE...) is the same on every controller of the family; what differs is the link. A
JRC takes it in BSC blocks over RS-232 (core/robot/serial_link.py), a DX100 or a later
controller also over TCP through its Ethernet server (core/robot/ethernet_link.py). The
JRC backend (core/robot/jrc.py) speaks the command set over either, and the emulator
(core/sim/jrc_emulator.py) answers it behind either.

Every answer is one of two kinds, whatever its framing: a status (``0000`` done, or a
4-digit error code) or data (comma-separated values).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Protocol

from vservo.core.robot.backend import RobotError


class LinkError(RobotError):
    """The link failed after its recovery; the message names the phase and the cause."""


class LinkLost(LinkError):
    """The device under the link is gone: nothing, not even a hold, gets through until
    the link is opened again (connect)."""


class CommandNotOffered(RobotError):
    """The controller's server does not offer the command over this link (JWAIT over
    Ethernet); the message names the command and the server's words."""


class ReplyKind(StrEnum):
    STATUS = "status"  # 0000, or a 4-digit error code
    DATA = "data"  # comma-separated values


@dataclass(frozen=True)
class Answer:
    """A controller's answer to one host command, its framing removed."""

    kind: ReplyKind
    text: str  # the status code's digits, or the values; no line end

    @staticmethod
    def status(code: int) -> Answer:
        return Answer(ReplyKind.STATUS, f"{code:04d}")

    @staticmethod
    def data(text: str) -> Answer:
        return Answer(ReplyKind.DATA, text)


class HostLink(Protocol):
    """A transport of host commands. ``exchange`` raises LinkError when the link failed
    (the command may or may not have been carried out; the link may still carry a hold),
    LinkLost when it cannot carry anything any more, CommandNotOffered when the server
    refuses the command itself."""

    @property
    def where(self) -> str:
        """The controller's address in words: the serial device, or host:port."""
        ...

    def open(self) -> None:
        """Make the link ready; a lost one is opened anew."""
        ...

    def close(self) -> None: ...

    def exchange(self, text: str, reply_wait_s: float) -> Answer:
        """Send one host command (its text without line end) and take its answer,
        waiting up to ``reply_wait_s`` for it."""
        ...

    def offers(self, command: str) -> bool:
        """Whether the controller takes ``command`` (its name, e.g. "JWAIT") over this link."""
        ...
