"""Local echo: an adapter that hears its own requests, on the real wire path through the shim.

Every combination of the bus's ``echo`` setting with an adapter that echoes or does not,
reads and writes, a device present and one absent: values are the simulator's, a write
never succeeds on its own echo, and each mistake in the setting is named with its fix.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import TYPE_CHECKING

import pytest
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import run
from gateway.config import parse_config
from gateway.config.echo import EchoMode
from gateway.errors import BusTimeoutError, EchoMismatchError
from gateway.line.stats import ErrorKind
from gateway.line.transports.echo import AUTO_DECISION_READS
from gateway.shared.state import GatewayState
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.simulator.shim import FTDI_LATENCY_S, LineShim
from gateway.wire import frames
from tests.rigs import link_target, target
from tests.shimmed import LINE, shimmed
from tests.waiting import eventually

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line]

S10 = {"profile": "jumo-digiline-odo-s10", "address": 1, "animate": False}
S10_VALUES = {**S10, "values": {"temperature": 21.5}}
TARGETS = [
    link_target("s10", "jumo-digiline-odo-s10", 1),
    link_target("absent", "jumo-digiline-odo-s10", 7),  # nothing answers at address 7
]
CONTROL = 0x25AF  # S10 compensation control, one RAM register: a function-06 write


async def _reads_and_writes(tmp_path: Path, *, mode: EchoMode, echo: bool) -> dict[str, int]:
    async with shimmed(tmp_path, [S10_VALUES], TARGETS, echo_mode=mode, echo=echo) as rig:
        for _ in range(AUTO_DECISION_READS):
            (sample,) = await rig.read("s10", "temperature")
            assert sample.good
            assert sample.value == 21.5  # the simulator's value, not an echo's bytes
        (absent,) = await rig.read("absent", "temperature")
        assert absent.quality.value == "comms_error"
        assert absent.fault == "timeout"

        response = await rig.write("s10", "compensation_control", [1])
        assert response.address == CONTROL
        assert [r.address for r in rig.device(1).write_log] == [CONTROL]
        # Nothing answers at 7: the echo of the write must not pass for its answer.
        with pytest.raises(BusTimeoutError):
            await rig.write("absent", "compensation_control", [1])
        assert rig.line.stats.responses[7] == 0
        assert rig.server.bus.violations == []
        if echo:
            assert rig.shim.counters.echoed > 0
        return rig.errors()


@pytest.mark.parametrize("mode", [EchoMode.ON, EchoMode.AUTO])
async def test_an_echoing_adapter_set_on_or_auto_reads_and_writes_right(
    tmp_path: Path, mode: EchoMode, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="gateway.line.transports.echo")
    errors = await _reads_and_writes(tmp_path, mode=mode, echo=True)
    assert ErrorKind.ECHO not in errors
    assert ErrorKind.ECHO_MISMATCH not in errors
    assert errors.get(ErrorKind.TIMEOUT, 0) >= 2  # the absent device's read and write
    if mode is EchoMode.AUTO:
        (decided,) = [
            r.getMessage() for r in caplog.records if "echoes every request" in r.getMessage()
        ]
        assert "Set `echo: on` for bus line1" in decided


async def test_an_echoing_adapter_set_off_is_read_right_and_told_what_to_set(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    errors = await _reads_and_writes(tmp_path, mode=EchoMode.OFF, echo=True)
    assert errors[ErrorKind.ECHO] >= AUTO_DECISION_READS
    told = [r for r in caplog.records if "`echo: off`" in r.getMessage()]
    assert len(told) == 1  # once, not per request
    assert told[0].levelno == logging.WARNING
    assert "set `echo: on` (or `auto`)" in told[0].getMessage()


@pytest.mark.parametrize("mode", [EchoMode.OFF, EchoMode.AUTO])
async def test_a_quiet_adapter_set_off_or_auto_reads_and_writes_right(
    tmp_path: Path, mode: EchoMode, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="gateway.line.transports.echo")
    errors = await _reads_and_writes(tmp_path, mode=mode, echo=False)
    assert ErrorKind.ECHO not in errors
    if mode is EchoMode.AUTO:
        assert any("set `echo: off` for bus line1" in r.getMessage() for r in caplog.records)


async def test_echo_on_with_an_adapter_that_does_not_echo_says_so(tmp_path: Path) -> None:
    async with shimmed(tmp_path, [S10_VALUES], TARGETS, echo_mode=EchoMode.ON) as rig:
        state = rig.state("s10")
        request = frames.read_request(1, 0x2620, 2)
        with pytest.raises(EchoMismatchError) as caught:
            await rig.worker.transactions.transact(state, request, 9)
        assert str(caught.value).endswith(
            "is set to `echo: on` but the request to device 1 did not come back (the "
            "device's answer came instead): this adapter does not echo what it sends; set "
            "`echo: off` (or `auto`) for the bus"
        )
        assert rig.errors() == {ErrorKind.ECHO_MISMATCH: 1}
        # The device's answer came after the missing echo: the late-answer window holds,
        # so it is flushed as stale, not taken for a later request's.
        assert state.holds.not_before > 0


async def test_an_answer_sooner_than_the_wire_allows_is_never_taken(tmp_path: Path) -> None:
    """Whatever the setting: a copy of a write that comes back at once is not its answer.

    ``echo: off`` on an echoing adapter, a function-06 write to an address where nothing
    answers: the echo is a well-formed 06 answer, in before the request could even have
    been heard. It used to report the write done.
    """
    async with shimmed(tmp_path, [S10], TARGETS, echo_mode=EchoMode.OFF, echo=True) as rig:
        with pytest.raises(BusTimeoutError):
            await rig.write("absent", "compensation_control", [1])
        assert rig.line.stats.responses[7] == 0


async def test_the_shared_bus_never_hands_an_echo_to_another_master(tmp_path: Path) -> None:
    """Another master on the shared bus, an echoing adapter the config says nothing of.

    Its read gets the sensor's registers, not the echo's bytes; its function-06 write to a
    sensor that does not answer gets exception 0B, not the echo of its own request.
    """
    server = SimulatorServer(
        build_bus(parse_settings({"devices": [S10_VALUES], "line": LINE, "pace": True}))
    )
    server.open_pty(tmp_path / "ttySIM")
    shim = LineShim(upstream=tmp_path / "ttySIM", path=tmp_path / "ttyUSB0", echo=True)
    shim.open()
    config = parse_config(
        f"buses:\n  - {{name: basin, port: {tmp_path / 'ttyUSB0'}, baudrate: 9600, parity: E,"
        " echo: 'off'}\n"
        "devices:\n"
        "  - {name: s10, bus: basin, address: 1, profile: jumo-digiline-odo-s10}\n"
        "  - {name: ghost, bus: basin, address: 7, profile: jumo-digiline-odo-s10,"
        " offline_after: 1000}\n"
        "mqtt: {enabled: false}\nprometheus: {enabled: false}\n"
        f"state_dir: {tmp_path / 'state'}\n"
        "shared_bus:\n"
        "  listen: [{host: 127.0.0.1, port: 0, framing: tcp}]\n"
        "  clients:\n"
        "    - {name: scada, networks: [127.0.0.1], writes: [{device: ghost, registers: ['0x25AF']}]}\n",
        environ={},
    )
    state = GatewayState()
    stop = asyncio.Event()
    task = asyncio.create_task(run(config, stop=stop, state=state))
    try:
        for _ in range(200):
            if state.shared_bus.listening:
                break
            await asyncio.sleep(0.05)
        port = int(state.shared_bus.listening[0].rsplit(":", 1)[1])
        client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)
        await client.connect()
        try:
            read = await client.read_holding_registers(0x2620, count=2, device_id=1)
            assert not read.isError(), read
            assert read.registers == [0x0000, 0x41AC]  # 21.5, CDAB: the sensor's registers
            write = await client.write_register(CONTROL, 1, device_id=7)
            assert write.isError()
            assert write.exception_code == 0x0B  # gateway target device failed to respond
        finally:
            client.close()
        assert shim.counters.echoed > 0
        assert server.bus.violations == []
    finally:
        stop.set()
        await task
        shim.close()
        await server.close()


async def test_an_echoing_adapter_with_a_16_ms_latency_timer_unplugged_and_back(
    tmp_path: Path,
) -> None:
    """The USB adapter of a cabinet: it echoes, holds bytes to 16 ms ticks, and is replugged.

    The echo comes late (held with the answer's first bytes to the next tick), so only
    ``auto``'s reads can tell it; once decided, it is read back before every answer, and
    the decision outlives the replug (the same adapter comes back).
    """
    targets = [target("s10", "jumo-digiline-odo-s10", 1, interval=0.3)]
    async with shimmed(tmp_path, [S10_VALUES], targets, echo=True, latency_s=FTDI_LATENCY_S) as rig:
        task = asyncio.create_task(rig.worker.run())

        def temperatures_since(when: float) -> bool:
            return any(
                s.point == "temperature" and s.good and s.monotonic > when for s in rig.sink.samples
            )

        await eventually(
            lambda: rig.line.echo.echoes is not None and temperatures_since(0.0), within_s=10
        )
        assert rig.line.echo.echoes is True
        rig.shim.drop_carrier()
        unplugged = time.monotonic()
        await eventually(lambda: rig.line.stats.port_failures >= 1, within_s=10)
        rig.shim.restore_carrier()
        back = time.monotonic()
        # The port's backoff (0.5 s, then longer) and a loaded machine: as long as it takes.
        await eventually(lambda: temperatures_since(back), within_s=15)
        rig.worker.request_stop()
        await asyncio.wait_for(task, timeout=5)
        assert rig.line.stats.port_failures >= 1
        assert rig.server.bus.violations == []
        errors = rig.errors()
    assert ErrorKind.ECHO not in errors
    assert ErrorKind.ECHO_MISMATCH not in errors
    assert len(rig.shim.counters.deliveries) > 10  # bytes really were held to ticks
    temperatures = [s for s in rig.sink.samples if s.point == "temperature" and s.good]
    assert any(s.monotonic < unplugged for s in temperatures)
    assert any(s.monotonic > back for s in temperatures), "polling resumed after the replug"
    assert {s.value for s in temperatures} == {21.5}
