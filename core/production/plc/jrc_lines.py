"""The handshake's signals on the JRC's I/O lines, the way the vacuum cup is wired.

The PLC's outputs are wired to general inputs of the JRC, which the host reads with
IOREAD; the host cannot switch a general output, so the cell's signals go out as network
inputs written with IOWRITE, and a ladder line per signal, set up once on the pendant,
copies each to the general output wired to the PLC (docs/robot-link.md, I/O). The
addresses are byte.bit ([line.plc.inputs], [line.plc.outputs]).

Each poll reads every input byte once (one IOREAD per byte); outputs are written only
when they change, one IOREAD and one IOWRITE per changed byte under the link's lock, so
other signals of that byte (the cup's suction) keep their state. At 9600 baud an
exchange takes 0.15 to 0.25 s: the poll period on a real JRC is that long at least, and
the handshake leaves the link to the run while busy (Handshake.listening).
"""

from __future__ import annotations

from dataclasses import astuple

from vservo.core.cell.config import PlcConfig
from vservo.core.production.plc.handshake import PlcInputs, PlcOutputs, job_number
from vservo.core.robot.jrc import JrcBackend, io_byte


class JrcLines:
    """The handshake's signals on ``jrc``'s I/O at the addresses of ``config``."""

    def __init__(self, config: PlcConfig, jrc: JrcBackend) -> None:
        self.config, self.jrc = config, jrc
        self._input_bytes = sorted({io_byte(a)[0] for a in config.inputs.addresses()})
        self._outputs = config.outputs.addresses()
        self._written: PlcOutputs | None = None  # what the lines carry, once written

    def read(self) -> PlcInputs:
        values = {byte: self.jrc.read_io(byte)[0] for byte in self._input_bytes}

        def signal(address: int) -> bool:
            byte, bit = io_byte(address)
            return bool(values[byte] >> bit & 1)

        inputs = self.config.inputs
        return PlcInputs(
            start=signal(inputs.start),
            job_number=job_number([signal(bit) for bit in inputs.job_bits]),
            part_present=signal(inputs.part_present),
            reset=signal(inputs.reset),
        )

    def write(self, outputs: PlcOutputs) -> None:
        before = astuple(self._written) if self._written is not None else (None,) * len(self._outputs)
        changed = {address: bool(value) for address, value, old in zip(self._outputs, astuple(outputs), before) if value != old}
        if changed:
            self.jrc.write_signals(changed)
        self._written = outputs

    def close(self) -> None:
        """The lines belong to the JRC's link, which the rig closes."""
