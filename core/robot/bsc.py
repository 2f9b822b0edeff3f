"""The data link of the Yaskawa host-control protocol: BSC-like blocks over RS-232.

docs/robot-link.md describes it. A message (a header such as ``01,000`` and a CR-ended
text) travels as one exchange: the sender bids with ENQ and the receiver answers ACK0;
each block follows, ``SOH header STX text ETX|ETB BCC`` for the first and
``STX text ETX|ETB BCC`` for the others, and is answered with ACK1, ACK0, ACK1 ... in
turn; EOT ends the exchange and the ACK parity starts again.

Recovery, for both ends of the line (a BscStation plays either):

- no valid answer within timer A: the sender repeats its ENQ (bidding), or sends ENQ to
  ask for the receiver's last answer (after a block), up to retry 1 times. An answer of
  the previous parity to that ENQ means the block never arrived: it is sent again. So a
  block whose ACK was lost is not delivered twice.
- NAK (a bad BCC, or a receiver that refuses): the sender repeats the block, up to
  retry 2 times.
- both ends bid at once: the host yields (``yields=True``), takes the JRC's
  message, then bids again; the JRC never yields.
- after its retries the sender ends with EOT and raises LinkError naming the cause; a
  receiver that sees EOT before the last block, or no end of text within timer B,
  raises LinkError too. Bytes that are no answer (line noise, late duplicates) are
  skipped; the BCC of a block is read by position, as it may look like a control
  character.

Fault injection (the JRC emulator's) hooks in through LinkFaults; the host runs
without it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Protocol

from vservo.core.cell.config import JrcLineConfig
from vservo.core.robot.host_link import LinkError

log = logging.getLogger("vservo.bsc")

SOH, STX, ETX, EOT, ENQ, DLE, NAK, ETB = 0x01, 0x02, 0x03, 0x04, 0x05, 0x10, 0x15, 0x17
ACK0 = bytes((DLE, 0x30))
ACK1 = bytes((DLE, 0x31))
MAX_TEXT_BYTES = 256
MAX_HEADER_BYTES = 16


@dataclass(frozen=True)
class Message:
    """One message: ``01,000`` a host command, ``90,000`` a status reply (``0000`` or an
    error code), ``90,001`` a data reply (comma-separated values). Text ends with CR."""

    header: str
    text: str


def block_check(body: bytes) -> bytes:
    """BCC: the unsigned 16-bit sum of the bytes after the leading SOH or STX up to and
    including ETX/ETB, low byte first."""
    return (sum(body) & 0xFFFF).to_bytes(2, "little")


def encode_blocks(message: Message) -> list[bytes]:
    """The blocks of a message, at most MAX_TEXT_BYTES of text each: ETB ends a block that
    has a successor, ETX the last one."""
    header = message.header.encode("ascii")
    text = message.text.encode("ascii")
    if len(header) > MAX_HEADER_BYTES or any(b < 0x20 for b in header):
        raise ValueError(f"not a header: {message.header!r}")
    if any(b < 0x20 and b != 0x0D for b in text):
        raise ValueError(f"a text may hold printable characters and CR only: {message.text!r}")
    chunks = [text[i : i + MAX_TEXT_BYTES] for i in range(0, len(text), MAX_TEXT_BYTES)] or [b""]
    blocks = []
    for i, chunk in enumerate(chunks):
        end = ETX if i == len(chunks) - 1 else ETB
        body = (header + bytes((STX,)) if i == 0 else b"") + chunk + bytes((end,))
        blocks.append(bytes((SOH if i == 0 else STX,)) + body + block_check(body))
    return blocks


def message_bytes(message: Message) -> int:
    """The bytes one message's exchange puts on the line, both ends together, without
    repeats: the sender's ENQ, the receiver's ACK0, each block and its ACK, the EOT."""
    return 1 + len(ACK0) + sum(len(block) + len(ACK1) for block in encode_blocks(message)) + 1


class Port(Protocol):
    """What the link needs of a serial port (pyserial's Serial has it): ``read`` returns
    what arrives within the port's short timeout, possibly nothing."""

    @property
    def in_waiting(self) -> int: ...
    def read(self, size: int) -> bytes: ...
    def write(self, data: bytes) -> int | None: ...


class ByteChannel:
    """A port with a read buffer, deadlines and byte counts.

    ``character_time_s`` paces the line: every byte read or written costs that long, as
    on a real line at the baud rate (a pseudo-terminal itself is not baud-limited).
    """

    def __init__(self, port: Port, character_time_s: float | None = None) -> None:
        self.port = port
        self.character_time_s = character_time_s
        self._buffer = bytearray()
        self.bytes_in = 0
        self.bytes_out = 0

    def read_byte(self, deadline: float) -> int | None:
        """The next byte, or None when nothing arrives before ``deadline`` (time.monotonic)."""
        while not self._buffer:
            if time.monotonic() >= deadline:
                return None
            chunk = self.port.read(max(1, self.port.in_waiting))
            if chunk and self.character_time_s:
                time.sleep(len(chunk) * self.character_time_s)
            self.bytes_in += len(chunk)
            self._buffer.extend(chunk)
        return self._buffer.pop(0)

    def unread(self, b: int) -> None:
        """Put a byte back: the next read_byte returns it."""
        self._buffer.insert(0, b)

    def write(self, data: bytes) -> None:
        if self.character_time_s:
            time.sleep(len(data) * self.character_time_s)
        self.port.write(data)
        self.bytes_out += len(data)

    def discard_input(self) -> int:
        """Drop what has arrived and not been read (late answers of an abandoned exchange)."""
        dropped = len(self._buffer)
        self._buffer.clear()
        while waiting := self.port.in_waiting:
            chunk = self.port.read(waiting)
            dropped += len(chunk)
            self.bytes_in += len(chunk)
        return dropped


class LinkFaults(Protocol):
    """The fault injection of a JRC emulator, at the data link."""

    def outgoing(self, data: bytes, what: str) -> bytes | None:
        """The bytes really sent for ``data`` (what: ack, nak, enq, eot, block): the same,
        altered, or None for silence; may sleep to delay them."""
        ...

    def on_block(self) -> str | None:
        """For a good block received: None to accept it, "nak" to refuse it, "no_ack" to
        accept it without answering."""
        ...


@dataclass
class LinkCounters:
    """What happened on the link: the recoveries, and the bytes that were no answer."""

    messages_sent: int = 0
    messages_received: int = 0
    enq_retries: int = 0  # ENQs repeated: bids unanswered, or a block's answer asked for
    text_resends: int = 0  # blocks sent again after NAK, or after the receiver said it had not got them
    naks_received: int = 0
    naks_sent: int = 0  # bad blocks received
    contentions: int = 0  # both ends bid at once
    missing_eot: int = 0  # a complete message whose EOT never came
    junk_bytes: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(vars(self))


@dataclass(frozen=True)
class _Block:
    header: str | None
    text: str
    final: bool


_BAD, _INTERRUPTED = "bad", "interrupted"


@dataclass
class BscStation:
    """One end of the line: sends and receives messages, with the recovery above.

    ``yields``: the host's role in contention. A message the host receives while it
    bids (the late reply of a command that failed) is logged and dropped.
    """

    channel: ByteChannel
    line: JrcLineConfig
    yields: bool
    faults: LinkFaults | None = None
    counters: LinkCounters = field(default_factory=LinkCounters)

    # -- sending ---------------------------------------------------------------------

    def send(self, message: Message) -> None:
        """Deliver one message; raises LinkError after ending the exchange with EOT."""
        blocks = encode_blocks(message)
        try:
            self._bid()
            for i, block in enumerate(blocks):
                self._send_block(block, i, len(blocks))
        except LinkError:
            self.abandon()
            raise
        self._write(bytes((EOT,)), "eot")
        self.counters.messages_sent += 1

    def abandon(self) -> None:
        """End whatever exchange is under way: EOT, and forget what has arrived unread."""
        self._write(bytes((EOT,)), "eot")
        self.channel.discard_input()

    def _bid(self) -> None:
        timer_a = self.line.timer_a_s
        for attempt in range(self.line.retry_1 + 1):
            if attempt:
                self.counters.enq_retries += 1
            self._write(bytes((ENQ,)), "enq")
            answer = self._answer(time.monotonic() + timer_a, ignore_enq=not self.yields)
            if answer == ACK0:
                return
            if answer == bytes((ENQ,)):  # both ends bid: the host yields
                self.counters.contentions += 1
                try:
                    log.info("contention: took the other end's message %s first", self.receive_text())
                except LinkError as exc:
                    log.info("contention: the other end's message was lost: %s", exc)
        raise LinkError(f"no ACK0 to ENQ after {self.line.retry_1 + 1} tries (timer A {timer_a:g} s)")

    def _send_block(self, block: bytes, index: int, count: int) -> None:
        expected, previous = (ACK1, ACK0) if index % 2 == 0 else (ACK0, ACK1)
        where = f"block {index + 1} of {count}"
        timer_a = self.line.timer_a_s
        naks = enqs = 0
        asked = False  # whether the last thing sent was an ENQ asking for the answer
        self._write(block, "block")
        deadline = time.monotonic() + timer_a
        while True:
            answer = self._answer(deadline, ignore_enq=True)
            if answer == expected:
                return
            if answer == bytes((EOT,)):
                raise LinkError(f"the other end ended the exchange (EOT) at {where}")
            if answer == bytes((NAK,)) or (answer == previous and asked):
                if answer == bytes((NAK,)):
                    self.counters.naks_received += 1
                naks += 1
                if naks > self.line.retry_2:
                    raise LinkError(f"{where} refused {naks} times (retry 2 = {self.line.retry_2})")
                self.counters.text_resends += 1
                self._write(block, "block")
                asked = False
                deadline = time.monotonic() + timer_a
            elif answer is None:
                enqs += 1
                if enqs > self.line.retry_1:
                    raise LinkError(f"no answer to {where} after {self.line.retry_1} ENQs (timer A {timer_a:g} s)")
                self.counters.enq_retries += 1
                self._write(bytes((ENQ,)), "enq")
                asked = True
                deadline = time.monotonic() + timer_a
            # A previous-parity ACK nobody asked for is a late duplicate: keep waiting.

    def _answer(self, deadline: float, ignore_enq: bool) -> bytes | None:
        """The next answer (ACK0, ACK1, NAK, ENQ, EOT) before the deadline; other bytes are skipped."""
        channel = self.channel
        while (b := channel.read_byte(deadline)) is not None:
            if b == DLE:
                following = channel.read_byte(deadline)
                if following in (0x30, 0x31):
                    return bytes((DLE, following))
                self.counters.junk_bytes += 1  # a DLE cut from its digit; what follows may be an answer
                if following is not None:
                    channel.unread(following)
            elif b in (NAK, EOT) or (b == ENQ and not ignore_enq):
                return bytes((b,))
            else:
                self.counters.junk_bytes += 1
        return None

    # -- receiving -------------------------------------------------------------------

    def wait_for_bid(self, deadline: float) -> bool:
        """Wait for the other end's ENQ until the deadline; other bytes are skipped."""
        while (b := self.channel.read_byte(deadline)) is not None:
            if b == ENQ:
                return True
            self.counters.junk_bytes += 1
        return False

    def receive(self, wait_s: float, what: str = "a message") -> Message:
        """Wait up to wait_s for the other end's bid, then take its message; raises
        LinkError after ending the exchange with EOT."""
        if not self.wait_for_bid(time.monotonic() + wait_s):
            self.abandon()
            raise LinkError(f"no ENQ for {what} within {wait_s:g} s")
        return self.receive_text()

    def receive_text(self) -> Message:
        """After the other end's ENQ: answer ACK0, take blocks until EOT; raises LinkError
        after ending the exchange with EOT."""
        try:
            return self._receive_text()
        except LinkError:
            self.abandon()
            raise

    def _receive_text(self) -> Message:
        self._write(ACK0, "ack")
        last_ack = ACK0
        header: str | None = None
        parts: list[str] = []
        complete = False
        deadline = time.monotonic() + self.line.timer_b_s
        while True:
            b = self.channel.read_byte(deadline)
            if b is None:
                if complete:  # the message is whole and the line has been silent for timer B: the EOT was lost
                    self.counters.missing_eot += 1
                    break
                raise LinkError(f"the text did not end within timer B ({self.line.timer_b_s:g} s)")
            if b == ENQ:  # the sender asks for our last answer: it is still there, wait on
                self._write(last_ack, "ack")
                deadline = time.monotonic() + self.line.timer_b_s
            elif b == EOT:
                if complete:
                    break
                raise LinkError("the other end ended the exchange (EOT) before the last block")
            elif b in (SOH, STX):
                block = self._read_block(b, deadline)
                if block == _INTERRUPTED:
                    self._write(last_ack, "ack")
                # _BAD (the one other str), or a first block without its header
                elif isinstance(block, str) or (header is None and block.header is None):
                    self.counters.naks_sent += 1
                    self._write(bytes((NAK,)), "nak")
                elif complete:  # the last block again: the sender missed our answer
                    self._write(last_ack, "ack")
                else:
                    verdict = self.faults.on_block() if self.faults else None
                    if verdict == "nak":
                        self._write(bytes((NAK,)), "nak")
                        continue
                    header = block.header if header is None else header
                    parts.append(block.text)
                    complete = block.final
                    last_ack = ACK1 if last_ack == ACK0 else ACK0
                    if verdict != "no_ack":
                        self._write(last_ack, "ack")
                    deadline = time.monotonic() + self.line.timer_b_s
            else:
                self.counters.junk_bytes += 1
        self.counters.messages_received += 1
        return Message(header or "", "".join(parts))

    def _read_block(self, start: int, deadline: float) -> _Block | str:
        """The rest of a block after its SOH or STX: the block, _BAD (bad BCC, malformed,
        cut short) or _INTERRUPTED (an ENQ: the sender asks for our last answer)."""
        body = bytearray()
        limit = MAX_HEADER_BYTES + 1 + MAX_TEXT_BYTES + 1
        while True:
            b = self.channel.read_byte(deadline)
            if b is None:
                return _BAD
            if b == ENQ:
                return _INTERRUPTED
            body.append(b)
            if b in (ETX, ETB):
                break
            if len(body) > limit:
                return _BAD
        # The BCC by position; a sender that stops mid-block is given timer A, not B.
        bcc_deadline = min(deadline, time.monotonic() + self.line.timer_a_s)
        first, second = (self.channel.read_byte(bcc_deadline) for _ in range(2))
        if first is None or second is None or bytes((first, second)) != block_check(bytes(body)):
            return _BAD
        content = bytes(body[:-1])
        header: str | None = None
        if start == SOH:
            head, separator, content = content.partition(bytes((STX,)))
            if not separator:
                return _BAD
            header = head.decode("ascii", "replace")
        return _Block(header, content.decode("ascii", "replace"), body[-1] == ETX)

    def _write(self, data: bytes, what: str) -> None:
        if self.faults is not None:
            altered = self.faults.outgoing(data, what)
            if not altered:
                return
            data = altered
        self.channel.write(data)
