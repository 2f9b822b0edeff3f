"""The PLC handshake in the controller process: its poller and its way into the controller.

When the cell file has [line.plc], ``vservo controller`` starts a ``PlcService``: every
``poll_period_s`` (plus the time the reads take) it reads the PLC's signals from the lines
(the Modbus server or the JRC's I/O), steps the handshake (handshake.py) and writes the
cell's signals when they change. A start or a reset is carried out by the controller's
own ``start`` and ``reset`` (``ControllerCell``), under its command lock and with the
page's guards: the PLC is one more client of the controller, never a second path to the
robot. A poll that fails (the JRC link down, say) is logged and tried again the next
period; the handshake's state stands meanwhile.
"""

from __future__ import annotations

import logging
import threading
from typing import Protocol

from vservo.core.cell.config import ConfigError, PlcConfig, PlcTransport
from vservo.core.errors import VservoError
from vservo.core.production.cell_controller import CellController
from vservo.core.production.plc.handshake import Handshake, PlcInputs, PlcOutputs
from vservo.core.production.protocol.state import Outcome, Phase
from vservo.core.robot.jrc import JrcBackend

log = logging.getLogger("vservo.plc")


class PlcLines(Protocol):
    """Where the handshake's signals travel: ``modbus.ModbusLines`` or ``jrc_lines.JrcLines``."""

    def read(self) -> PlcInputs: ...

    def write(self, outputs: PlcOutputs) -> None: ...

    def close(self) -> None: ...


class ControllerCell:
    """The controller as the handshake sees it (handshake.PlcCell)."""

    def __init__(self, controller: CellController) -> None:
        self.controller = controller

    def phase(self) -> Phase:
        return Phase(self.controller.state.phase)

    def running(self) -> bool:
        return self.controller.running

    def start(self, job: str, part_id: str | None) -> None:
        self.controller.start(job, part_id=part_id, by_line=True)

    def outcome(self) -> Outcome | None:
        outcome = self.controller.last_outcome
        return None if outcome is None else outcome.outcome

    def reset(self) -> None:
        self.controller.reset()

    def say(self, detail: str) -> None:
        self.controller.update(detail=detail)


def open_lines(config: PlcConfig, controller: CellController) -> PlcLines:
    """The lines [line.plc] transport names: a Modbus TCP server, or the rig's JRC's I/O."""
    if config.transport is PlcTransport.MODBUS:
        from vservo.core.production.plc.modbus import ModbusLines  # pymodbus: loaded for a cell that serves Modbus

        return ModbusLines(config)
    from vservo.core.production.plc.jrc_lines import JrcLines

    jrc = controller.rig.robot.robot
    if not isinstance(jrc, JrcBackend):
        raise ConfigError(f'line.plc.transport = "jrc_io": the PLC on the JRC\'s I/O needs the JRC, not the {jrc.name!r} robot')
    return JrcLines(config, jrc)


class PlcService:
    """The handshake of ``config`` polled on ``lines`` for ``controller``, on a thread of its own."""

    def __init__(self, controller: CellController, config: PlcConfig, lines: PlcLines) -> None:
        self.config, self.lines = config, lines
        self.handshake = Handshake(config, ControllerCell(controller))
        self.polls = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, name="plc-handshake", daemon=True)
        self._thread.start()

    @classmethod
    def start(cls, controller: CellController) -> PlcService | None:
        """The service of the controller's cell file's [line.plc]; None when it has none."""
        config = controller.rig.config.plc
        if config is None:
            return None
        return cls(controller, config, open_lines(config, controller))

    def where(self) -> dict[str, object]:
        """Where the PLC finds the cell's signals, for the controller's first line of output."""
        address = getattr(self.lines, "address", None)
        if address is None:
            return {"transport": str(self.config.transport)}
        return {"transport": str(self.config.transport), "host": address[0], "port": address[1]}

    def _poll(self) -> None:
        inputs, written, failing = PlcInputs(), None, ""
        while not self._stop.wait(self.config.poll_period_s):
            try:
                if self.handshake.listening:
                    inputs = self.lines.read()
                outputs = self.handshake.step(inputs)
                if outputs != written:
                    self.lines.write(outputs)
                    written = outputs
                self.polls += 1
                failing = ""
            except Exception as exc:  # the lines failed (the JRC link, the server), or a bug: said once, tried again
                if str(exc) != failing:
                    log.error(
                        "PLC handshake: %s (trying again every %g s)",
                        exc,
                        self.config.poll_period_s,
                        exc_info=not isinstance(exc, VservoError),
                    )
                failing = str(exc)

    def close(self) -> None:
        """Stop polling, the cell's signals low, the lines closed; safe to call twice."""
        if self._thread.is_alive():
            self._stop.set()
            self._thread.join()
            try:
                self.lines.write(PlcOutputs())
            except VservoError as exc:
                log.warning("PLC handshake: the outputs could not be switched off: %s", exc)
        self.lines.close()
