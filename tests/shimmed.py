"""A simulated line behind the adapter shim: what the hardware tests talk to.

The simulator serves its pty at ``ttySIM``; :class:`~gateway.simulator.shim.LineShim`
relays it to ``ttyUSB0`` with the faults a real adapter has (echo, latency, noise), and a
:class:`BusWorker` owns ``ttyUSB0`` as the gateway would.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from gateway.config.echo import EchoMode
from gateway.line.engine.worker import BusWorker
from gateway.line.transports.serial_line import SerialLine
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.simulator.shim import LineShim
from gateway.wire import frames
from gateway.wire.timing import LineFormat
from tests.rigs import ListSink

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Sequence
    from pathlib import Path

    from gateway.line.engine.devices import DeviceState, DeviceTarget
    from gateway.line.samples import Sample
    from gateway.simulator.device import SimulatedDevice

LINE: dict[str, Any] = {"baudrate": 9600, "parity": "E", "stopbits": 1}


@dataclass
class Shimmed:
    server: SimulatorServer
    shim: LineShim
    worker: BusWorker
    line: SerialLine
    sink: ListSink

    def state(self, device: str) -> DeviceState:
        return self.worker.devices[device]

    def device(self, address: int) -> SimulatedDevice:
        return self.server.bus.devices[address]

    async def read(self, device: str, *names: str) -> list[Sample]:
        """Read points now, with the worker's retries, as a command would."""
        state = self.state(device)
        points = [state.profile.point(name) for name in names]
        return await self.worker.transactions.read_now(state, points)

    async def write(self, device: str, point: str, registers: Sequence[int]) -> frames.Response:
        """Write registers to a point (06 for one, 16 for more), once, no retry."""
        state = self.state(device)
        target = state.profile.point(point)
        request = frames.write_request(state.target.address, target.address, list(registers))
        return await self.worker.transactions.write(state, target, request)

    def errors(self) -> dict[str, int]:
        """Errors of the line by kind, summed over the devices."""
        by_kind: dict[str, int] = {}
        for (_, kind), count in self.line.stats.errors.items():
            by_kind[kind] = by_kind.get(kind, 0) + count
        return by_kind


@contextlib.asynccontextmanager
async def shimmed(
    tmp_path: Path,
    devices: list[dict[str, Any]],
    targets: list[DeviceTarget],
    *,
    echo_mode: EchoMode = EchoMode.AUTO,
    echo: bool = False,
    latency_s: float = 0.0,
    noise_interval_s: float = 0.0,
    line: dict[str, Any] | None = None,
) -> AsyncIterator[Shimmed]:
    line = line or LINE
    server = SimulatorServer(
        build_bus(parse_settings({"devices": devices, "line": line, "pace": True}))
    )
    server.open_pty(tmp_path / "ttySIM")
    shim = LineShim(
        upstream=tmp_path / "ttySIM",
        path=tmp_path / "ttyUSB0",
        echo=echo,
        latency_s=latency_s,
        noise_interval_s=noise_interval_s,
    )
    shim.open()
    bus_line = SerialLine(
        port=str(tmp_path / "ttyUSB0"), line=LineFormat(**line), bus="line1", echo=echo_mode
    )
    sink = ListSink()
    worker = BusWorker(name="line1", line=bus_line, devices=targets, sinks=[sink])
    await worker.claim_port()  # opened as `gateway run` opens it, the schedule started
    try:
        yield Shimmed(server=server, shim=shim, worker=worker, line=bus_line, sink=sink)
    finally:
        await bus_line.close()
        shim.close()
        await server.close()
