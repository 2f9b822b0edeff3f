"""The handshake's signals on a Modbus TCP server (pymodbus) that the PLC polls as a client.

The PLC writes its signals to coils (function 5 or 15; it may read them back with 1) and
reads the cell's from discrete inputs (function 2), at the protocol addresses (0-based)
of [line.plc.inputs] and [line.plc.outputs]; with ``part_id_register`` it writes the
part's ID to holding registers (function 6 or 16), two ASCII characters a register, high
byte first, padded with NUL or spaces. The server answers every unit ID. Addresses
beyond the mapped ones answer ILLEGAL ADDRESS.

The server runs its asyncio loop on a thread of its own; the handshake's poller reads and
writes the server's datastore through it, so a PLC's request and a poll never interleave
inside one datastore call.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import astuple
from typing import Any

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from vservo.core.cell.config import PlcConfig
from vservo.core.errors import VservoError
from vservo.core.production.plc.handshake import PlcInputs, PlcOutputs, job_number

log = logging.getLogger("vservo.plc.modbus")

READ_COILS, READ_DISCRETE_INPUTS, READ_HOLDING_REGISTERS = 1, 2, 3
ANY_UNIT = 0  # the datastore's device 0 answers every unit ID
START_TIMEOUT_S = 10.0
CALL_TIMEOUT_S = 5.0


class ModbusServerError(VservoError, RuntimeError):
    """The handshake's Modbus server cannot start or serve."""


def decode_part_id(registers: Sequence[int]) -> str | None:
    """The part ID in holding registers: two ASCII characters each, high byte first, the
    padding (NUL, spaces) stripped; None when they hold nothing."""
    raw = b"".join(int(r).to_bytes(2, "big") for r in registers)
    text = raw.replace(b"\0", b" ").decode("latin-1").strip()
    return text or None


class ModbusLines:
    """The handshake's signals on a Modbus TCP server at [line.plc] host:port; ``address``
    is where it listens (the port the system gave for port 0)."""

    def __init__(self, config: PlcConfig) -> None:
        self.config = config
        self._inputs = config.inputs.addresses()
        self._outputs = config.outputs.addresses()
        self._discrete = [False] * (max(self._outputs) + 1)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="plc-modbus", daemon=True)
        self._thread.start()
        try:
            self._server: ModbusTcpServer = self._call(self._serve(), START_TIMEOUT_S)
        except (OSError, RuntimeError) as exc:
            self._stop_loop()
            raise ModbusServerError(
                f"line.plc: the Modbus TCP server cannot listen on {config.host}:{config.port}: {exc}"
            ) from None
        socket = self._server.transport.sockets[0]  # a listening asyncio Server
        self.address: tuple[str, int] = socket.getsockname()[:2]
        log.info("PLC handshake: Modbus TCP server on %s:%d", *self.address)

    def _device(self) -> SimDevice:
        def bits(count: int) -> list[SimData]:
            return [SimData(0, count=count, values=False, datatype=DataType.BITS)]

        registers = 1
        if self.config.part_id_register is not None:
            registers = self.config.part_id_register + self.config.part_id_registers
        return SimDevice(
            id=ANY_UNIT,
            simdata=(
                bits(max(self._inputs) + 1),
                bits(len(self._discrete)),
                [SimData(0, count=registers, values=0, datatype=DataType.REGISTERS)],
                [SimData(0, count=1, values=0, datatype=DataType.REGISTERS)],
            ),
        )

    async def _serve(self) -> ModbusTcpServer:
        server = ModbusTcpServer(self._device(), address=(self.config.host, self.config.port))
        await server.serve_forever(background=True)
        return server

    def _call(self, coroutine: Any, timeout_s: float = CALL_TIMEOUT_S) -> Any:
        future: Future = asyncio.run_coroutine_threadsafe(coroutine, self._loop)
        return future.result(timeout_s)

    def _get(self, function: int, address: int, count: int) -> list:
        values = self._call(self._server.context.async_getValues(ANY_UNIT, function, address, count))
        if not isinstance(values, list):
            raise ModbusServerError(f"the Modbus datastore refused a read of {count} at {address}: {values!r}")
        return values

    def read(self) -> PlcInputs:
        coils = self._get(READ_COILS, 0, max(self._inputs) + 1)
        inputs = self.config.inputs
        part_id = None
        if self.config.part_id_register is not None:
            part_id = decode_part_id(
                self._get(READ_HOLDING_REGISTERS, self.config.part_id_register, self.config.part_id_registers)
            )
        return PlcInputs(
            start=bool(coils[inputs.start]),
            job_number=job_number([bool(coils[bit]) for bit in inputs.job_bits]),
            part_present=bool(coils[inputs.part_present]),
            reset=bool(coils[inputs.reset]),
            part_id=part_id,
        )

    def write(self, outputs: PlcOutputs) -> None:
        for address, value in zip(self._outputs, astuple(outputs)):
            self._discrete[address] = bool(value)
        refused = self._call(self._server.context.async_setValues(ANY_UNIT, READ_DISCRETE_INPUTS, 0, list(self._discrete)))
        if refused is not None:
            raise ModbusServerError(f"the Modbus datastore refused the outputs: {refused!r}")

    def close(self) -> None:
        """Stop serving (the PLC's connections are closed); safe to call twice."""
        if self._thread.is_alive():
            try:
                self._call(self._server.shutdown())
            finally:
                self._stop_loop()

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join()
        self._loop.close()
