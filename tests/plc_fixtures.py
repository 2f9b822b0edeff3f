"""A PLC program for the tests: the standard handshake played against the cell, on a
pymodbus client (the cell's Modbus TCP server) or on the virtual cell's I/O panel (the
JRC's lines). What it reads is only what a PLC sees: the cell's six output signals."""

from __future__ import annotations

import json
import time
import urllib.request
from dataclasses import dataclass

from pymodbus.client import ModbusTcpClient

from vservo.core.cell.config import PlcConfig
from vservo.core.production.plc.handshake import PlcOutputs

CYCLE_TIMEOUT_S = 120.0


@dataclass(frozen=True)
class Cycle:
    """One cycle as the PLC saw it: the outputs when done (or fault) came, and whether busy was seen."""

    result: PlcOutputs
    saw_busy: bool


class Plc:
    """The handshake from the PLC's side; subclasses carry the signals."""

    def __init__(self, config: PlcConfig) -> None:
        self.config = config

    def write(self, signals: dict[int, bool]) -> None:
        raise NotImplementedError

    def outputs(self) -> PlcOutputs:
        raise NotImplementedError

    def set(self, *, start: bool | None = None, part_present: bool | None = None, reset: bool | None = None) -> None:
        inputs = self.config.inputs
        wanted = {inputs.start: start, inputs.part_present: part_present, inputs.reset: reset}
        self.write({address: on for address, on in wanted.items() if on is not None})

    def select_job(self, number: int) -> None:
        self.write({bit: bool(number >> i & 1) for i, bit in enumerate(self.config.inputs.job_bits)})

    def wait_for(self, check, what: str, timeout_s: float = CYCLE_TIMEOUT_S) -> PlcOutputs:
        deadline = time.monotonic() + timeout_s
        while True:
            outputs = self.outputs()
            if check(outputs):
                return outputs
            if time.monotonic() > deadline:
                raise AssertionError(f"the PLC waited for {what}: not within {timeout_s} s; outputs {outputs}")
            time.sleep(0.005)

    def start(self, job: int, part_present: bool = True) -> None:
        """Wait for ready, select the job and say whether the part is there, raise start."""
        self.wait_for(lambda o: o.ready, "ready")
        self.select_job(job)
        self.set(part_present=part_present)
        self.set(start=True)

    def finish(self) -> Cycle:
        """Wait for done or fault (noting busy on the way), then drop start; done must fall."""
        saw_busy = False

        def ended(outputs: PlcOutputs) -> bool:
            nonlocal saw_busy
            saw_busy = saw_busy or outputs.busy
            return outputs.done or outputs.fault

        result = self.wait_for(ended, "done or fault")
        self.set(start=False)
        if result.done:
            self.wait_for(lambda o: not o.done and not o.ok and not o.not_ok, "done, OK and not OK to drop with start")
        return Cycle(result, saw_busy)

    def cycle(self, job: int, part_present: bool = True) -> Cycle:
        self.start(job, part_present)
        return self.finish()

    def reset(self) -> None:
        """Pulse reset: high until fault drops, then low."""
        self.set(reset=True)
        self.wait_for(lambda o: not o.fault, "fault to drop on reset")
        self.set(reset=False)


class ModbusPlc(Plc):
    """The PLC as a Modbus TCP client: its signals on coils, the cell's read from discrete inputs."""

    def __init__(self, config: PlcConfig, host: str, port: int) -> None:
        super().__init__(config)
        self.client = ModbusTcpClient(host, port=port, timeout=5)
        if not self.client.connect():
            raise AssertionError(f"no Modbus server at {host}:{port}")

    def write(self, signals: dict[int, bool]) -> None:
        for address, on in signals.items():
            reply = self.client.write_coil(address, on)
            assert not reply.isError(), reply

    def write_part_id(self, text: str) -> None:
        raw = text.encode("ascii").ljust(2 * self.config.part_id_registers, b"\0")
        registers = [int.from_bytes(raw[i : i + 2], "big") for i in range(0, len(raw), 2)]
        assert self.config.part_id_register is not None
        reply = self.client.write_registers(self.config.part_id_register, registers)
        assert not reply.isError(), reply

    def outputs(self) -> PlcOutputs:
        addresses = self.config.outputs.addresses()
        reply = self.client.read_discrete_inputs(0, count=max(addresses) + 1)
        assert not reply.isError(), reply
        return PlcOutputs(*(bool(reply.bits[a]) for a in addresses))

    def close(self) -> None:
        self.client.close()


class PanelPlc(Plc):
    """The PLC wired to the JRC's I/O: it drives the JRC's inputs and reads the outputs the
    JRC's ladder copies out, on the virtual cell's I/O panel (its fixture's /io)."""

    def __init__(self, config: PlcConfig, fixture_url: str) -> None:
        super().__init__(config)
        self.url = f"{fixture_url}/io"

    def write(self, signals: dict[int, bool]) -> None:
        body = json.dumps({"inputs": {str(a): on for a, on in signals.items()}}).encode()
        request = urllib.request.Request(self.url, data=body, headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=10) as reply:
            assert reply.status == 200

    def outputs(self) -> PlcOutputs:
        with urllib.request.urlopen(self.url, timeout=10) as reply:
            lines = json.load(reply)["outputs"]
        return PlcOutputs(*(bool(lines[str(a)]) for a in self.config.outputs.addresses()))

    def close(self) -> None:
        pass


class EmulatorPlc(Plc):
    """The PLC wired to an in-process JRC emulator's I/O panel."""

    def __init__(self, config: PlcConfig, emulator) -> None:
        super().__init__(config)
        self.emulator = emulator

    def write(self, signals: dict[int, bool]) -> None:
        self.emulator.set_inputs(signals)

    def outputs(self) -> PlcOutputs:
        lines = self.emulator.io_panel().outputs
        return PlcOutputs(*(lines[a] for a in self.config.outputs.addresses()))

    def close(self) -> None:
        pass
