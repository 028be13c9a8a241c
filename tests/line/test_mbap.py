"""Modbus TCP buses (``tcp://``) against the simulator as a converter in Modbus TCP mode.

Real sockets on loopback, the simulator's own bus and referee behind them: values checked
against the simulated registers, a write's post-write wait measured on the serial side,
an absent device answered 0B by the converter, stale answers dropped by transaction id,
and the session settings (keepalive, user timeout, silence, pauses) as the kernel and the
wire see them.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket
import struct
import time
from typing import TYPE_CHECKING, Any

import pytest

from gateway.config.network import TcpSettings
from gateway.control.link import DeviceLink
from gateway.errors import BusTimeoutError, ConverterPathError
from gateway.line.boundary import RequestOptions
from gateway.line.engine.worker import BusWorker
from gateway.line.samples import Quality
from gateway.line.stats import ErrorKind
from gateway.line.transports.factory import build_line
from gateway.line.transports.modbus_tcp import ModbusTcpLine
from gateway.line.transports.rtu_over_tcp import RtuOverTcpLine
from gateway.line.transports.serial_line import SerialLine
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire import frames, mbap
from gateway.wire.timing import LineFormat
from tests.rigs import PLANT, ListSink, Rig, plant_targets, target

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable

    from gateway.line.engine.devices import DeviceTarget

LINE: dict[str, Any] = {"baudrate": 9600, "parity": "E", "stopbits": 1}


@contextlib.asynccontextmanager
async def mbap_rig(
    devices: list[dict[str, Any]],
    targets: list[DeviceTarget],
    *,
    tcp: TcpSettings | None = None,
    converter_timeout_s: float = 0.05,
    **worker_options: Any,
) -> AsyncIterator[Rig]:
    """The simulator as a Modbus TCP converter on loopback, a worker on a ``tcp://`` bus."""
    server = SimulatorServer(
        build_bus(parse_settings({"devices": devices, "line": LINE, "pace": True}))
    )
    port = await server.open_tcp(
        "127.0.0.1", 0, framing="tcp", converter_timeout_s=converter_timeout_s
    )
    sink = ListSink()
    line = build_line(port=f"tcp://127.0.0.1:{port}", line=LineFormat(**LINE), tcp=tcp)
    worker = BusWorker(name="line1", line=line, devices=targets, sinks=[sink], **worker_options)
    try:
        yield Rig(server=server, worker=worker, sink=sink, line=line)
    finally:
        await line.close()
        await server.close()


def static(devices: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{**device, "animate": False} for device in devices]


# --- the factory ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("port", "kind"),
    [
        ("tcp://10.0.0.5:502", ModbusTcpLine),
        ("socket://10.0.0.5:4001", RtuOverTcpLine),
        ("/dev/ttyUSB0", SerialLine),
        ("rfc2217://10.0.0.5:4001", SerialLine),
    ],
)
def test_the_port_picks_the_line(port: str, kind: type[object]) -> None:
    line = build_line(port=port, line=LineFormat())
    assert type(line) is kind
    assert line.port == port


# --- polling ---------------------------------------------------------------------------------


@pytest.mark.line
async def test_a_plant_polled_over_modbus_tcp_reads_the_simulated_registers() -> None:
    async with mbap_rig(static(PLANT), plant_targets(interval=0.3)) as r:
        await r.run_for(3.0)  # identity first: long strings at 9600 baud
        stats = r.line.stats
        bus = r.server.bus
        assert bus.stats()["timing_violations"] == 0
        compared = 0
        for state in r.worker.devices.values():
            device = bus.devices[state.target.address]
            good = [s for s in r.sink.samples if s.device == state.target.name and s.good]
            assert {s.point for s in good} >= {"temperature"}
            for sample in good:
                expected = device.get(sample.point)
                if isinstance(sample.value, float):
                    assert sample.value == pytest.approx(expected, rel=1e-6), sample.point
                    compared += 1
                elif isinstance(sample.value, int) and not isinstance(sample.value, bool):
                    assert sample.value == expected, sample.point
                    compared += 1
        assert compared > 30
        assert all(state.presence.online for state in r.worker.devices.values())
    # Every request answered, but the one in flight when the worker was stopped.
    assert sum(stats.requests.values()) - sum(stats.responses.values()) <= 1, stats.errors
    assert not stats.errors
    # The converter saw every request (the last one perhaps not yet, when the worker stopped).
    assert 0 <= sum(stats.requests.values()) - bus.counters["mbap_requests"] <= 1


@pytest.mark.line
async def test_no_inter_frame_gap_on_the_socket_but_the_converter_keeps_it() -> None:
    """The gateway sends at once; the converter's serial side still has its 3.5 characters."""
    async with mbap_rig(static(PLANT[:2]), plant_targets(interval=0.05)[:2]) as r:
        await r.run_for(1.0)
        records = r.frames()
    required = LineFormat(**LINE).frame_gap_s(0.002)
    previous_end = -math.inf
    for record in records:
        assert record.start - previous_end >= required - 1e-4
        previous_end = record.answer_at if record.answer_at is not None else record.start
    assert len(records) > 15


@pytest.mark.line
async def test_a_write_keeps_the_h10_post_write_wait() -> None:
    devices = static([{"profile": "jumo-digiline-odo-h10", "address": 2}, PLANT[3]])
    targets = [
        target("h10", "jumo-digiline-odo-h10", 2, interval=0.1),
        target("cl2", "jumo-tecline-cl2", 20, interval=0.1),
    ]
    async with mbap_rig(devices, targets) as r:
        link = DeviceLink(r.worker, "h10")
        point = link.profile.point("compensation_temperature")

        async def write() -> None:
            await asyncio.sleep(0.8)
            await link.write(point, 21.5)

        task = asyncio.create_task(write())
        await r.run_for(2.0)
        await asyncio.wait_for(task, timeout=1)
        records = r.frames()
        stats = r.server.bus.stats()
        assert r.server.bus.devices[2].get("compensation_temperature") == 21.5
    assert stats["timing_violations"] == 0
    index = next(i for i, rec in enumerate(records) if rec.function in {6, 16})
    written = records[index]
    assert written.answer_at is not None
    following = [rec for rec in records[index + 1 :] if rec.device == 2]
    assert following[0].start - written.answer_at >= 0.25  # H10/H20 manual 6.1.5
    assert following[0].start - written.answer_at < 0.25 + 0.1
    # Meanwhile the other device was polled: the wait is the device's, not the line's.
    assert any(rec.device == 20 and rec.start < following[0].start for rec in records[index + 1 :])


@pytest.mark.line
async def test_an_absent_device_is_the_converters_0b_a_failure_not_an_exception() -> None:
    devices = static([PLANT[0]])
    targets = [target("s10", "jumo-digiline-odo-s10", 1, interval=0.2)]
    targets.append(target("ghost", "jumo-digiline-odo-s10", 9, interval=0.2))
    async with mbap_rig(devices, targets) as r:
        # Three failures, each followed by the late-answer window (1 s): a 0B is a timeout.
        await r.run_for(3.5)
        stats = r.line.stats
        ghost = r.worker.devices["ghost"]
        assert ghost.presence.online is False
        assert not ghost.holds.split_before  # a 0B never splits a read as exception 02 would
        assert r.worker.devices["s10"].presence.online is True
        failed = [s for s in r.sink.samples if s.device == "ghost"]
        assert failed
        assert {s.quality for s in failed} == {Quality.COMMS_ERROR}
        assert {s.fault for s in failed} == {"gateway_target_failed"}
        assert r.server.bus.counters["mbap_0b"] >= 3
    assert stats.errors[9, "gateway_target_failed"] >= 3
    assert stats.errors[9, ErrorKind.EXCEPTION] == 0
    assert not stats.exception_codes
    offline = [e for e in r.sink.events if e.device == "ghost" and not e.online]
    assert "exception 0B" in offline[0].reason


@pytest.mark.line
async def test_a_0b_after_the_gateway_gave_up_is_a_stale_frame() -> None:
    """The converter waits longer than the gateway: its 0B comes after the timeout."""
    targets = [target("ghost", "jumo-digiline-odo-s10", 9, interval=0.2, timeout_s=0.05)]
    async with mbap_rig(static([PLANT[0]]), targets, converter_timeout_s=0.2) as r:
        await r.run_for(2.0)
        stats = r.line.stats
    assert stats.errors[9, ErrorKind.TIMEOUT] >= 2
    assert stats.errors[9, ErrorKind.STALE] >= 1
    assert stats.errors[9, "gateway_target_failed"] == 0


# --- a converter written by hand: answers the simulator does not give -------------------------


@contextlib.asynccontextmanager
async def hand_converter(answers: list[bytes]) -> AsyncIterator[int]:
    """A peer that answers each request with the next bytes built from its header.

    Each entry of ``answers`` is a PDU; ``b"STALE"`` sends the answer to the previous
    transaction id first (a late answer of an older request) and then nothing.
    """
    pending = list(answers)
    served: list[asyncio.Task[None]] = []

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        served.append(asyncio.current_task())  # type: ignore[arg-type]
        with contextlib.suppress(ConnectionError, asyncio.IncompleteReadError):
            while True:
                header = await reader.readexactly(mbap.MBAP_HEADER_LENGTH)
                request = mbap.decode(header + await reader.readexactly(header[5] - 1))
                assert request is not None
                frame = request[0]
                answer = pending.pop(0)
                if answer == b"STALE":
                    old = frames.read_response(frame.unit, 3, (1, 2))[1:-2]
                    writer.write(mbap.encode(frame.transaction - 1, frame.unit, old))
                else:
                    writer.write(mbap.encode(frame.transaction, frame.unit, answer))
        writer.close()
        await writer.wait_closed()

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    try:
        yield int(server.sockets[0].getsockname()[1])
    finally:
        server.close()
        await server.wait_closed()
        await asyncio.wait_for(asyncio.gather(*served), timeout=2)  # the client has closed


@pytest.mark.line
async def test_0a_older_transactions_and_a_good_answer() -> None:
    good = frames.read_response(1, 3, (0x0000, 0x41A2))[1:-2]
    answers = [bytes((0x83, 0x0A)), b"STALE", good]
    async with hand_converter(answers) as port:
        line = build_line(port=f"tcp://127.0.0.1:{port}", line=LineFormat())
        await line.open()
        request = frames.read_request(1, 0x2620, 2)
        try:
            with pytest.raises(ConverterPathError, match=r"exception 0A.*gateway path unavailable"):
                await line.transact(request, RequestOptions(timeout_s=0.2, gap_s=0.0))
            with pytest.raises(BusTimeoutError, match="no answer"):
                await line.transact(request, RequestOptions(timeout_s=0.1, gap_s=0.0))
            exchange = await line.transact(request, RequestOptions(timeout_s=0.2, gap_s=0.0))
        finally:
            await line.close()
    assert exchange is not None
    assert exchange.response.registers == (0x0000, 0x41A2)
    assert line.stats.errors[1, "gateway_path_unavailable"] == 1
    assert line.stats.errors[1, ErrorKind.STALE] == 1
    assert line.stats.errors[1, ErrorKind.TIMEOUT] == 1
    assert line.stats.responses[1] == 1


@pytest.mark.line
async def test_an_answer_the_socket_holds_at_the_deadline_is_taken() -> None:
    """As on an RTU line (tests/line/test_bus.py): the answer is in the socket when the wait's
    timer wakes the transaction, the loop held up in the pass the timer was due in. It
    is the answer, not a timeout and a stale frame."""
    listener = socket.create_server(("127.0.0.1", 0))
    line = build_line(port=f"tcp://127.0.0.1:{listener.getsockname()[1]}", line=LineFormat())
    await line.open()
    peer, _ = listener.accept()
    loop = asyncio.get_running_loop()
    assert isinstance(line, ModbusTcpLine)
    inbox = line._session
    assert inbox is not None
    wait = inbox.wait
    held: list[float] = []

    def answer_and_hold() -> None:
        request = peer.recv(256)
        pdu = frames.read_response(1, 3, (0x0000, 0x41A2))[1:-2]
        peer.sendall(struct.pack(">HHHB", *struct.unpack(">H", request[:2]), 0, len(pdu) + 1, 1))
        peer.sendall(pdu)
        time.sleep(0.01)  # held up: the bytes reach the socket, the loop does not run
        held.append(time.monotonic())

    async def wait_after_the_answer(timeout_s: float) -> None:
        if not held:  # the wait for the answer: due just before its timer
            loop.call_at(loop.time() + timeout_s - 1e-6, answer_and_hold)
        await wait(timeout_s)

    inbox.wait = wait_after_the_answer  # type: ignore[method-assign]
    try:
        exchange = await line.transact(
            frames.read_request(1, 0x2620, 2), RequestOptions(timeout_s=0.05, gap_s=0.0)
        )
    finally:
        await line.close()
        peer.close()
        listener.close()
    assert held, "the answer was never sent: the test did not set the race up"
    assert exchange is not None
    assert exchange.response.registers == (0x0000, 0x41A2)
    assert line.stats.errors[1, ErrorKind.TIMEOUT] == 0
    assert line.stats.errors[1, ErrorKind.STALE] == 0


# --- the session --------------------------------------------------------------------------


def _options(sock: socket.socket | Any) -> dict[str, int]:
    return {
        "keepalive": sock.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE),
        "idle": sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE),
        "interval": sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL),
        "count": sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT),
        "user_timeout_ms": sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT),
    }


SESSION = TcpSettings(keepalive_s=7, keepalive_interval_s=3, keepalive_count=4, user_timeout_s=9.5)
EXPECTED = {"keepalive": 1, "idle": 7, "interval": 3, "count": 4, "user_timeout_ms": 9500}


@pytest.mark.parametrize("framing", ["rtu", "tcp"])
@pytest.mark.line
async def test_keepalive_and_the_user_timeout_reach_the_socket(framing: str) -> None:
    server = SimulatorServer(build_bus(parse_settings({"devices": [PLANT[0]], "line": LINE})))
    port = await server.open_tcp("127.0.0.1", 0, framing=framing)
    scheme = "tcp" if framing == "tcp" else "socket"
    line = build_line(port=f"{scheme}://127.0.0.1:{port}", line=LineFormat(**LINE), tcp=SESSION)
    assert isinstance(line, RtuOverTcpLine | ModbusTcpLine)
    try:
        await line.open()
        sock = line.tcp_socket()
        assert sock is not None
        assert _options(sock) == EXPECTED
        exchange = await line.transact(
            frames.read_request(1, 0x2620, 2), RequestOptions(timeout_s=0.2, gap_s=0.005)
        )
        assert exchange is not None  # the settings leave the line working
    finally:
        await line.close()
        await server.close()


@pytest.mark.parametrize("framing", ["rtu", "tcp"])
@pytest.mark.line
async def test_the_pause_after_connecting_and_between_requests(framing: str) -> None:
    server = SimulatorServer(build_bus(parse_settings({"devices": [PLANT[0]], "line": LINE})))
    port = await server.open_tcp("127.0.0.1", 0, framing=framing)
    scheme = "tcp" if framing == "tcp" else "socket"
    settings = TcpSettings(connect_pause_s=0.3, request_pause_ms=80)
    line = build_line(port=f"{scheme}://127.0.0.1:{port}", line=LineFormat(**LINE), tcp=settings)
    request = frames.read_request(1, 0x2620, 2)
    try:
        # Stamped before the connection: the line counts its pause from its own connection,
        # a moment after, and a stamp after open() returned fell short of it by 10 µs once
        # beside a loaded machine's other tests.
        opened = time.monotonic()
        await line.open()
        exchanges = [
            await line.transact(request, RequestOptions(timeout_s=0.2, gap_s=0.005))
            for _ in range(3)
        ]
    finally:
        await line.close()
        await server.close()
    assert all(e is not None for e in exchanges)
    sent = [e.sent_at for e in exchanges if e is not None]
    received = [e.received_at for e in exchanges if e is not None]
    assert sent[0] - opened >= 0.3
    assert sent[0] - opened < 0.3 + 0.05
    assert all(sent[i + 1] - received[i] >= 0.08 for i in range(2))


class SilentPeer:
    """Accepts connections and keeps them open, reading everything and answering nothing."""

    def __init__(self) -> None:
        self.accepted: list[float] = []
        self.ended: list[float] = []
        self.writers: list[asyncio.StreamWriter] = []

    async def serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.accepted.append(time.monotonic())
        self.writers.append(writer)
        with contextlib.suppress(ConnectionError):
            while await reader.read(4096):
                pass
        self.ended.append(time.monotonic())
        writer.close()


async def until(condition: Callable[[], bool], timeout_s: float, what: str) -> float:
    """Wait for ``condition`` (another task's state); the seconds it took."""
    started = time.monotonic()
    async with asyncio.timeout(timeout_s):
        while not condition():  # noqa: ASYNC110 - the bus task's state, polled every 20 ms
            await asyncio.sleep(0.02)
    assert condition(), what
    return time.monotonic() - started


@contextlib.asynccontextmanager
async def running(worker: BusWorker) -> AsyncIterator[None]:
    task = asyncio.create_task(worker.run())
    try:
        yield
    finally:
        worker.request_stop()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        await worker.line.close()


@pytest.mark.parametrize("framing", ["tcp", "rtu"])
@pytest.mark.line
async def test_a_silent_peer_ends_the_session_then_a_converter_brings_the_devices_back(
    framing: str,
) -> None:
    """Connected but mute: the session ends after ``silent_requests``, devices go offline;
    a converter on the same port later, and they are back online."""
    peer = SilentPeer()
    silent = await asyncio.start_server(peer.serve, "127.0.0.1", 0)
    port = int(silent.sockets[0].getsockname()[1])
    settings = TcpSettings(silent_requests=3)
    scheme = "tcp" if framing == "tcp" else "socket"
    line = build_line(port=f"{scheme}://127.0.0.1:{port}", line=LineFormat(**LINE), tcp=settings)
    assert isinstance(line, ModbusTcpLine | RtuOverTcpLine)
    sink = ListSink()
    targets = [
        target(name, profile, address, interval=0.2, probe_max_s=0.5)
        for name, profile, address in (
            ("s10", "jumo-digiline-odo-s10", 1),
            ("h10", "jumo-digiline-odo-h10", 2),
        )
    ]
    worker = BusWorker(name="line1", line=line, devices=targets, sinks=[sink], reconnect_max_s=0.5)
    devices = worker.devices.values()
    bus = build_bus(parse_settings({"devices": static(PLANT[:2]), "line": LINE, "pace": True}))
    server = SimulatorServer(bus)
    async with running(worker):
        await until(lambda: bool(peer.ended), 10, "the silent session was never ended")
        # Three silent requests, each its timeout (and a device's late-answer window).
        assert peer.ended[0] - peer.accepted[0] < 3 * (0.2 + 1.0)
        assert line.watch.ended_at  # ended by its silence, not by the peer
        await until(lambda: all(s.presence.online is False for s in devices), 15, "still online")
        assert len(peer.accepted) >= 2  # reopened at once, still silent
        # The silent peer goes; a converter with the devices behind it takes its port.
        silent.close()
        for writer in peer.writers:
            writer.close()
        await silent.wait_closed()
        try:
            await server.open_tcp("127.0.0.1", port, framing=framing)
            await until(
                lambda: all(s.presence.online for s in devices), 10, "the devices did not return"
            )
        finally:
            await server.close()
    names = [(e.device, e.online) for e in sink.events]
    assert names.index(("s10", False)) < len(names) - 1 - names[::-1].index(("s10", True))
    assert [s for s in sink.samples if s.device == "s10" and s.point == "temperature" and s.good]


@pytest.mark.line
async def test_a_scan_through_the_converter_finds_the_devices_behind_it() -> None:
    from gateway.line.scan import scan  # noqa: PLC0415 - the scan is only this test's

    server = SimulatorServer(build_bus(parse_settings({"devices": PLANT, "line": LINE})))
    port = await server.open_tcp("127.0.0.1", 0, framing="tcp")
    try:
        report = await scan(
            f"tcp://127.0.0.1:{port}", formats=[LineFormat(**LINE)], addresses=[1, 2, 9, 10, 20]
        )
    finally:
        await server.close()
    found = {(d.address, d.profile) for d in report.devices}
    assert found == {
        (1, "jumo-digiline-odo-s10"),
        (2, "jumo-digiline-odo-h10"),
        (10, "reiss-m0c"),
        (20, "jumo-tecline-cl2"),
    }
    assert not report.garbled


@pytest.mark.line
async def test_a_broadcast_goes_through_unanswered_then_the_turnaround() -> None:
    devices = static([{"profile": "jumo-digiline-odo-h10", "address": 2}, PLANT[0]])
    targets = [
        target("h10", "jumo-digiline-odo-h10", 2, interval=0.05),
        target("s10", "jumo-digiline-odo-s10", 1, interval=0.05),
    ]
    async with mbap_rig(devices, targets) as r:
        poller = asyncio.create_task(r.worker.run())
        await asyncio.sleep(1.0)
        await asyncio.wait_for(r.worker.submit_broadcast(0x0305, [0]), timeout=2)
        await asyncio.sleep(1.0)
        poller.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await poller
        records = r.frames()
        stats = r.server.bus.stats()
        errors = r.line.stats.errors
    assert stats["timing_violations"] == 0
    assert not errors  # no answer was awaited, none came late
    index = next(i for i, rec in enumerate(records) if rec.device == 0)
    broadcast = records[index]
    assert (broadcast.outcome, broadcast.answer_at) == ("broadcast", None)
    after = records[index + 1 :]
    first_h10 = next(rec for rec in after if rec.device == 2)
    first_s10 = next(rec for rec in after if rec.device == 1)
    assert first_h10.start - broadcast.start >= 0.25  # H10/H20 6.1.5 after every write
    assert first_s10.start - broadcast.start >= 0.1  # the broadcast turnaround delay
