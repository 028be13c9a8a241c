"""The shared bus: independent masters reach the simulated sensors through the running gateway.

The gateway polls a line of simulated sensors (9600 8E1 on a pseudo-terminal) while a
pymodbus client and mbpoll talk Modbus TCP (or RTU over TCP) to it on a real socket. The
simulator referees the timing of everything on its line: the gateway's polls and the
other masters' requests alike.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import sqlite3
import struct
import subprocess
import urllib.request
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import pytest
from prometheus_client.parser import text_string_to_metric_families
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import run
from gateway.config import parse_config
from gateway.control.flash import LEDGER_FILE
from gateway.errors import ConfigError
from gateway.shared.state import GatewayState
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire import frames
from tests.mqtt_broker import free_port

if TYPE_CHECKING:
    from collections.abc import AsyncIterator
    from pathlib import Path

    from gateway.simulator.device import SimulatedDevice

pytestmark = [pytest.mark.line]

LINE = {"baudrate": 9600, "parity": "E", "stopbits": 1}
TECLINE = 20  # a tecLine Cl2 at address 20
H10 = 2
SIMULATED = [
    {
        "profile": "jumo-tecline-cl2",
        "address": TECLINE,
        "animate": False,
        "values": {"concentration": 0.168},
    },
    {"profile": "jumo-digiline-odo-h10", "address": H10, "animate": False},
]


@dataclass
class Plant:
    simulator: SimulatorServer
    state: GatewayState
    tcp_port: int
    rtu_port: int

    def device(self, address: int) -> SimulatedDevice:
        return self.simulator.bus.devices[address]

    def frames_to(self, address: int) -> list[Any]:
        return [f for f in self.simulator.bus.frame_log if f.device == address]


def _listen_port(state: GatewayState, framing: str) -> int:
    for url in state.shared_bus.listening:
        if url.startswith(f"{framing}://"):
            return int(url.rsplit(":", 1)[1])
    raise AssertionError(state.shared_bus.listening)


@contextlib.asynccontextmanager
async def plant(
    tmp_path: Path,
    shared_bus: str,
    *,
    poll_interval: float = 1.0,
    metrics_port: int = 0,
    cl2_options: str = "",
) -> AsyncIterator[Plant]:
    simulator = SimulatorServer(build_bus(parse_settings({"devices": SIMULATED, "line": LINE})))
    port = tmp_path / "ttyRS485"
    simulator.open_pty(port)
    config = parse_config(
        f"buses:\n"
        f"  - {{name: basin, port: {port}, baudrate: 9600, parity: E}}\n"
        "devices:\n"
        f"  - {{name: cl2, bus: basin, address: {TECLINE}, profile: jumo-tecline-cl2,"
        f" poll_interval: {poll_interval}{cl2_options}}}\n"
        f"  - {{name: oxygen, bus: basin, address: {H10}, profile: jumo-digiline-odo-h10,"
        f" poll_interval: {poll_interval}}}\n"
        "mqtt: {enabled: false}\n"
        + (
            f"prometheus: {{host: 127.0.0.1, port: {metrics_port}}}\n"
            if metrics_port
            else "prometheus: {enabled: false}\n"
        )
        + f"state_dir: {tmp_path / 'state'}\n"
        f"{shared_bus}",
        environ={},
    )
    state = GatewayState()
    stop = asyncio.Event()
    task = asyncio.create_task(run(config, stop=stop, state=state))
    try:
        for _ in range(100):
            if len(state.shared_bus.listening) == len(config.shared_bus.listen):
                break
            if task.done():
                await task  # it failed to start: its error is the test's
            await asyncio.sleep(0.05)
        tcp = _listen_port(state, "tcp") if "framing: rtu" not in shared_bus else 0
        rtu = _listen_port(state, "rtu") if "framing: rtu" in shared_bus else 0
        await asyncio.sleep(0.5)  # the first polls
        yield Plant(simulator=simulator, state=state, tcp_port=tcp, rtu_port=rtu)
    finally:
        stop.set()
        await asyncio.wait_for(task, timeout=10)
        await simulator.close()


SHARED = (
    "shared_bus:\n"
    "  listen: [{host: 127.0.0.1, port: 0}]\n"
    "  clients:\n"
    "    - name: service\n"
    "      networks: [127.0.0.1/32]\n"
    "      writes:\n"
    "        - {device: oxygen, registers: ['0x2013-0x2014']}\n"
)


def _violations(plant: Plant) -> list[dict[str, Any]]:
    return [v.as_dict() for v in plant.simulator.bus.violations]


async def test_a_pymodbus_client_reads_the_devices_answer_while_the_gateway_polls(
    tmp_path: Path,
) -> None:
    async with plant(tmp_path, SHARED) as p:
        client = AsyncModbusTcpClient("127.0.0.1", port=p.tcp_port, timeout=3)
        await client.connect()
        before = len(p.frames_to(TECLINE))
        reads = [
            await client.read_holding_registers(0x0000, count=6, device_id=TECLINE)
            for _ in range(5)
        ]
        inputs = await client.read_input_registers(0x0000, count=2, device_id=TECLINE)
        client.close()
        await asyncio.sleep(0.3)
        registers = p.device(TECLINE).registers
        polled = p.state.device_samples("basin", "cl2")
    expected = [registers.get(a, 0) for a in range(6)]
    assert all(not r.isError() for r in reads)
    assert [r.registers for r in reads] == [expected] * 5
    assert inputs.registers == expected[:2]
    # 0.168 mg/l as the tecLine sends it (CDAB): what the client got is the sensor's value.
    assert struct.unpack(">f", struct.pack(">HH", *reversed(expected[:2])))[0] == pytest.approx(
        0.168
    )
    # Every read went on the wire (no cache for this client), beside the gateway's polls.
    asked = [f for f in p.frames_to(TECLINE)[before:] if (f.address, f.quantity) == (0, 6)]
    assert len(asked) >= 5
    assert polled["concentration"].value == pytest.approx(0.168)
    assert _violations(p) == []


async def test_mbpoll_reads_through_the_gateway(tmp_path: Path) -> None:
    async with plant(tmp_path, SHARED) as p:
        result = await asyncio.to_thread(
            subprocess.run,
            [
                "mbpoll",
                "-m", "tcp",
                "-p", str(p.tcp_port),
                "-a", str(TECLINE),
                "-r", "1",  # mbpoll counts registers from 1: register 0x0000
                "-c", "6",
                "-t", "4:hex",
                "-1",
                "127.0.0.1",
            ],
            capture_output=True,
            text=True,
            timeout=20,
            check=False,
        )  # fmt: skip
        registers = p.device(TECLINE).registers
        violations = _violations(p)
    assert result.returncode == 0, result.stderr
    shown = [
        line.split(":")[1].strip() for line in result.stdout.splitlines() if line.startswith("[")
    ]
    assert shown == [f"0x{registers.get(a, 0):04X}" for a in range(6)]
    assert violations == []


async def _raw(port: int, request: bytes) -> bytes:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(request)
        await writer.drain()
        head = await asyncio.wait_for(reader.readexactly(6), timeout=5)
        length = int.from_bytes(head[4:6], "big")
        return head + await asyncio.wait_for(reader.readexactly(length), timeout=5)
    finally:
        writer.close()


def _mbap(transaction: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", transaction, 0, len(pdu) + 1, unit) + pdu


async def test_refusals_are_modbus_exceptions_and_nothing_reaches_the_line(tmp_path: Path) -> None:
    async with plant(tmp_path, SHARED) as p:
        before = len(p.simulator.bus.frame_log)
        unknown_unit = await _raw(p.tcp_port, _mbap(1, 99, bytes.fromhex("0300000001")))
        function_08 = await _raw(p.tcp_port, _mbap(2, TECLINE, bytes.fromhex("0800000000")))
        too_many = await _raw(p.tcp_port, _mbap(3, TECLINE, bytes.fromhex("030000007E")))
        # The service client may write 0x2013-0x2014 of the oxygen sensor only.
        not_granted = await _raw(p.tcp_port, _mbap(4, TECLINE, bytes.fromhex("0602060000")))
        outside = await _raw(
            p.tcp_port, _mbap(5, H10, bytes.fromhex("102013000306000041200000"))
        )  # 0x2013-0x2015: one register past the grant
        foreign = [f for f in list(p.simulator.bus.frame_log)[before:] if f.function != 3]
        client = p.state.shared_bus.clients["service"]
    # The answers: exception 0A (no such unit), 01 (function), 03 (quantity), 01 (write not
    # granted to this device), 02 (register outside the grant); transaction ids kept.
    assert unknown_unit == _mbap(1, 99, bytes.fromhex("830A"))
    assert function_08 == _mbap(2, TECLINE, bytes.fromhex("8801"))
    assert too_many == _mbap(3, TECLINE, bytes.fromhex("8303"))
    assert not_granted == _mbap(4, TECLINE, bytes.fromhex("8601"))
    assert outside == _mbap(5, H10, bytes.fromhex("9002"))
    assert foreign == []  # no write, no function 08 went on the line
    assert client.refused["write_not_allowed"] == 1
    assert client.refused["register_not_allowed"] == 1
    assert client.exceptions[0x0A] == 1


async def test_a_granted_write_reaches_the_device_and_its_post_write_wait_holds(
    tmp_path: Path,
) -> None:
    # compensation_temperature (H10 0x2013, float, RAM): 10.0 °C as CDAB words 0x0000 0x4120.
    async with plant(tmp_path, SHARED, poll_interval=0.2) as p:
        answer = await _raw(p.tcp_port, _mbap(7, H10, bytes.fromhex("10201300020400004120")))
        await asyncio.sleep(1.0)
        writes = [w for w in p.device(H10).write_log if w.address == 0x2013]
        after = (
            [f for f in p.frames_to(H10) if f.start > writes[0].time - p.simulator.bus.started]
            if writes
            else []
        )
        violations = _violations(p)
    assert answer == _mbap(7, H10, bytes.fromhex("1020130002"))  # the device's echo
    assert [w.values for w in writes] == [(0x0000, 0x4120)]
    assert after, "the gateway went on polling the sensor after the write"
    assert violations == []  # the 250 ms post-write wait held (H10/H20 6.1.5)


async def test_reads_are_answered_from_fresh_registers_without_the_wire(tmp_path: Path) -> None:
    shared = (
        "shared_bus:\n"
        "  listen: [{host: 127.0.0.1, port: 0}]\n"
        "  clients:\n"
        "    - {name: scada, networks: [127.0.0.0/8], cache_max_age: 5.0}\n"
    )
    async with plant(tmp_path, shared) as p:
        await asyncio.sleep(0.5)
        before = [f for f in p.frames_to(TECLINE) if (f.address, f.quantity) == (0, 6)]
        answer = await _raw(p.tcp_port, _mbap(9, TECLINE, bytes.fromhex("0300000006")))
        after = [f for f in p.frames_to(TECLINE) if (f.address, f.quantity) == (0, 6)]
        registers = p.device(TECLINE).registers
        cached = p.state.shared_bus.clients["scada"].cache_answers
    words = b"".join(registers.get(a, 0).to_bytes(2, "big") for a in range(6))
    assert answer == _mbap(9, TECLINE, bytes([3, 12]) + words)
    assert cached == 1
    # Polled at 1 s: no read of 0x0000/6 went out for the client within this second.
    assert len(after) - len(before) <= 1


async def test_rtu_over_tcp_frames_answer_with_the_devices_frame(tmp_path: Path) -> None:
    shared = "shared_bus:\n  listen: [{host: 127.0.0.1, port: 0, framing: rtu}]\n"
    async with plant(tmp_path, shared) as p:
        request = frames.read_request(TECLINE, 0x0000, 2).frame
        reader, writer = await asyncio.open_connection("127.0.0.1", p.rtu_port)
        writer.write(request)
        answer = await asyncio.wait_for(reader.readexactly(9), timeout=5)
        writer.close()
        registers = p.device(TECLINE).registers
    assert answer == frames.read_response(TECLINE, 3, [registers.get(0, 0), registers.get(1, 0)])


async def test_a_flood_of_requests_gets_busy_answers_and_polling_keeps_its_deadlines(
    tmp_path: Path,
) -> None:
    shared = (
        "shared_bus:\n"
        "  listen: [{host: 127.0.0.1, port: 0}]\n"
        "  bus_share: 0.1\n"
        "  max_wait: 0.5\n"
        "  max_pending: 4\n"
    )
    async with plant(tmp_path, shared, poll_interval=0.5) as p:

        async def hammer(transaction_base: int) -> list[bytes]:
            answers = []
            for n in range(15):
                pdu = bytes.fromhex("0300000006")
                answers.append(await _raw(p.tcp_port, _mbap(transaction_base + n, TECLINE, pdu)))
            return answers

        results = await asyncio.gather(*(hammer(100 * k) for k in range(6)))
        health = {h.device: h for h in p.state.health()}
        violations = _violations(p)
        foreign = p.state.shared_bus.buses["basin"]
    answers = [a for batch in results for a in batch]
    busy = [a for a in answers if a[7:] == bytes.fromhex("8306")]
    served = [a for a in answers if a[7] == 0x03]
    assert len(busy) + len(served) == len(answers)  # each got an answer: the device's, or 06
    assert busy, "a tenth of the bus cannot carry six clients reading 125 registers back to back"
    assert served
    assert all(h.missed_deadlines == 0 for h in health.values()), health
    assert violations == []
    assert foreign.refused["queue_full"] + foreign.refused["no_share"] == len(busy)


async def test_garbage_on_the_socket_closes_that_connection_and_nothing_reaches_the_line(
    tmp_path: Path,
) -> None:
    async with plant(tmp_path, SHARED) as p:
        before = len(p.simulator.bus.frame_log)
        for garbage in (b"\x00\x01\x00\x07\x00\x06\x14\x03\x00\x00\x00\x01", b"\xff" * 300):
            reader, writer = await asyncio.open_connection("127.0.0.1", p.tcp_port)
            writer.write(garbage)
            closed = await asyncio.wait_for(reader.read(), timeout=5)
            writer.close()
            assert closed == b""
        # A client that connects and sends nothing does not hold up anyone else.
        idle = socket.create_connection(("127.0.0.1", p.tcp_port))
        answer = await _raw(p.tcp_port, _mbap(1, TECLINE, bytes.fromhex("0300000002")))
        idle.close()
        logged = list(p.simulator.bus.frame_log)[before:]
    assert answer[7:9] == b"\x03\x04"
    assert all(f.outcome == "answered" for f in logged), {f.outcome for f in logged}


def _get(url: str) -> str:
    with urllib.request.urlopen(url, timeout=5) as response:  # noqa: S310 - a local test URL
        return str(response.read().decode())


async def test_clients_show_in_healthz_and_their_requests_in_the_metrics(tmp_path: Path) -> None:
    port = free_port()
    async with plant(tmp_path, SHARED, metrics_port=port) as p:
        reader, writer = await asyncio.open_connection("127.0.0.1", p.tcp_port)
        for transaction in range(3):
            writer.write(_mbap(transaction, TECLINE, bytes.fromhex("0300000002")))
            await asyncio.wait_for(reader.readexactly(13), timeout=5)
        writer.write(_mbap(9, 99, bytes.fromhex("0300000002")))
        await asyncio.wait_for(reader.readexactly(9), timeout=5)
        local = "%s:%d" % writer.get_extra_info("sockname")[:2]  # noqa: UP031
        health = json.loads(await asyncio.to_thread(_get, f"http://127.0.0.1:{port}/healthz"))
        text = await asyncio.to_thread(_get, f"http://127.0.0.1:{port}/metrics")
        writer.close()
    samples = {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }
    assert health["shared_bus"]["clients"] == {"service": [local]}
    assert health["shared_bus"]["listening"] == [f"tcp://127.0.0.1:{p.tcp_port}"]
    service = (("client", "service"),)
    assert samples["gateway_shared_bus_requests_total", (*service, ("function", "03"))] == 4
    assert samples["gateway_shared_bus_exceptions_total", (*service, ("code", "0A"))] == 1
    assert samples["gateway_shared_bus_refused_total", (*service, ("reason", "unknown_unit"))] == 1
    assert samples["gateway_shared_bus_received_bytes_total", service] == 4 * 12
    assert samples["gateway_shared_bus_sent_bytes_total", service] == 3 * 13 + 9
    assert samples["gateway_shared_bus_queue_wait_seconds_count", service] == 3
    assert samples["gateway_shared_bus_connections", service] == 1
    assert samples["gateway_shared_bus_busy_seconds_total", (("bus", "basin"),)] > 0
    assert samples["gateway_shared_bus_share", (("bus", "basin"),)] == 0.25


async def test_a_device_that_stopped_answering_gets_0b_and_then_no_bus_time(
    tmp_path: Path,
) -> None:
    async with plant(tmp_path, SHARED, poll_interval=0.2) as p:
        p.simulator.bus.silence(TECLINE, 30.0, asyncio.get_running_loop().time())
        # The first request waits out the device's timeout on the wire: 0B.
        first = await _raw(p.tcp_port, _mbap(1, TECLINE, bytes.fromhex("0300000002")))
        for _ in range(100):  # the gateway's polls fail too: offline after 3 in a row
            if p.state.devices["basin", "cl2"].online is False:
                break
            await asyncio.sleep(0.1)
        online = p.state.devices["basin", "cl2"].online
        count = len(p.frames_to(TECLINE))
        later = [
            await _raw(p.tcp_port, _mbap(2 + n, TECLINE, bytes.fromhex("0300000002")))
            for n in range(5)
        ]
        sent_for_them = len(p.frames_to(TECLINE)) - count
        oxygen = await _raw(p.tcp_port, _mbap(9, H10, bytes.fromhex("0300000002")))
    assert first == _mbap(1, TECLINE, bytes.fromhex("830B"))
    assert online is False
    assert later == [_mbap(2 + n, TECLINE, bytes.fromhex("830B")) for n in range(5)]
    # Offline: answered at once; only the gateway's own probes (a few per second at most)
    # reach the silent device meanwhile.
    assert sent_for_them <= 2
    assert oxygen[7:9] == b"\x03\x04"  # the other sensor on the line is still served


async def test_a_pymodbus_client_writes_where_granted_and_reads_it_back(tmp_path: Path) -> None:
    async with plant(tmp_path, SHARED) as p:
        client = AsyncModbusTcpClient("127.0.0.1", port=p.tcp_port, timeout=3)
        await client.connect()
        # compensation_temperature of the H10 (0x2013, float CDAB, volatile): 12.5 °C.
        written = await client.write_registers(0x2013, [0x0000, 0x4148], device_id=H10)
        back = await client.read_holding_registers(0x2013, count=2, device_id=H10)
        refused = await client.write_register(0x2013, 1, device_id=TECLINE)
        client.close()
        log = [w.values for w in p.device(H10).write_log if w.address == 0x2013]
        violations = _violations(p)
    assert not written.isError()
    assert back.registers == [0x0000, 0x4148]
    assert refused.isError()
    assert refused.exception_code == 0x01  # writes to the tecLine are not granted
    assert log == [(0x0000, 0x4148)]
    assert violations == []


async def test_connections_beyond_the_limit_are_closed_and_the_others_served(
    tmp_path: Path,
) -> None:
    shared = "shared_bus:\n  listen: [{host: 127.0.0.1, port: 0}]\n  max_connections: 2\n"
    async with plant(tmp_path, shared) as p:
        held = [await asyncio.open_connection("127.0.0.1", p.tcp_port) for _ in range(2)]
        await asyncio.sleep(0.2)
        reader, writer = await asyncio.open_connection("127.0.0.1", p.tcp_port)
        closed = await asyncio.wait_for(reader.read(), timeout=5)
        writer.close()
        held_reader, held_writer = held[0]
        held_writer.write(_mbap(1, TECLINE, bytes.fromhex("0300000002")))
        answer = await asyncio.wait_for(held_reader.readexactly(13), timeout=5)
        for _, w in held:
            w.close()
    assert closed == b""
    assert answer[7:9] == b"\x03\x04"


async def test_an_address_taken_by_another_program_is_a_clear_error(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        shared = f"shared_bus:\n  listen: [{{host: 127.0.0.1, port: {port}}}]\n"
        with pytest.raises(ConfigError) as error:
            async with plant(tmp_path, shared):
                pass
    assert str(error.value) == (
        f"shared_bus.listen[0]: cannot listen on 127.0.0.1:{port}: address already in use"
    )


async def test_writes_to_flash_count_against_the_devices_budget(tmp_path: Path) -> None:
    shared = (
        "shared_bus:\n"
        "  listen: [{host: 127.0.0.1, port: 0}]\n"
        "  clients:\n"
        "    - name: service\n"
        "      networks: [127.0.0.1/32]\n"
        "      writes: [{device: cl2, registers: ['0x0206-0x020B']}]\n"
    )
    # X_Zero (tecLine 0x0206, float CDAB, flash) = 2.0 nA, twice, with a budget of one a day.
    write = bytes.fromhex("10 0206 0002 04 0000 4000")
    async with plant(tmp_path, shared, cl2_options=", flash_write_budget: 1") as p:
        first = await _raw(p.tcp_port, _mbap(1, TECLINE, write))
        second = await _raw(p.tcp_port, _mbap(2, TECLINE, write))
        log = [w.values for w in p.device(TECLINE).write_log if w.address == 0x0206]
        refused = p.state.shared_bus.clients["service"].refused
    assert first == _mbap(1, TECLINE, bytes.fromhex("10 0206 0002"))
    assert second == _mbap(2, TECLINE, bytes.fromhex("90 01"))
    assert log == [(0x0000, 0x4000)]  # the second never reached the sensor
    assert refused["flash_budget"] == 1
    ledger = sqlite3.connect(tmp_path / "state" / LEDGER_FILE)
    rows = ledger.execute("SELECT device, point, count FROM flash_writes").fetchall()
    ledger.close()
    assert rows == [("cl2", "x_zero", 1)]  # the same ledger as the gateway's own writes
