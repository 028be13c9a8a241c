"""The simulator on a real line: a pseudo-terminal and a TCP socket, read by independent masters.

mbpoll (libmodbus) and pymodbus's client read the simulator over a pty; raw sockets show
each injected fault as the bytes a master receives.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import shutil
import threading
import time
from typing import TYPE_CHECKING, Any

import pytest
import serial
from pymodbus.client import AsyncModbusSerialClient

from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire import frames

if TYPE_CHECKING:
    from collections.abc import AsyncIterator
    from pathlib import Path

    from gateway.simulator.bus import SimulatedBus

pytestmark = [pytest.mark.line]

MBPOLL = shutil.which("mbpoll")
DEVICES = [
    {
        "profile": "jumo-digiline-odo-s10",
        "address": 1,
        "animate": False,
        "values": {"temperature": 20.25},
    },
    {
        "profile": "jumo-tecline-cl2",
        "address": 20,
        "animate": False,
        "values": {"concentration": 0.168},
    },
    {"profile": "jumo-digiline-odo-h10", "address": 3, "animate": False},
]


@contextlib.asynccontextmanager
async def serving(devices: list[dict[str, Any]], **settings: Any) -> AsyncIterator[SimulatorServer]:
    server = SimulatorServer(build_bus(parse_settings({"devices": devices, **settings})))
    try:
        yield server
    finally:
        await server.close()


async def mbpoll(*args: str) -> tuple[int, str]:
    assert MBPOLL is not None, (
        "mbpoll is missing: scripts/setup installs the Debian package (as root)"
    )
    process = await asyncio.create_subprocess_exec(
        MBPOLL, *args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT
    )
    output, _ = await asyncio.wait_for(process.communicate(), timeout=20)
    return process.returncode or 0, output.decode()


def mbpoll_values(output: str) -> dict[int, str]:
    return {
        int(ref): value for ref, value in re.findall(r"^\[(\d+)\]:\s+(\S+)", output, re.MULTILINE)
    }


async def test_mbpoll_reads_the_simulator_over_a_pty(tmp_path: Path) -> None:
    port = tmp_path / "ttySIM"
    async with serving(DEVICES) as server:
        server.open_pty(port)
        base = ["-m", "rtu", "-b", "9600", "-P", "none", "-0", "-1", "-o", "1", str(port)]
        # S10 temperature at 0x2620 as a word-swapped float: mbpoll's default order is CDAB.
        code, out = await mbpoll("-a", "1", "-r", str(0x2620), "-c", "1", "-t", "4:float", *base)
        assert code == 0, out
        assert mbpoll_values(out) == {0x2620: "20.25"}
        # tecLine concentration at 0x0000.
        code, out = await mbpoll("-a", "20", "-r", "0", "-c", "1", "-t", "4:float", *base)
        assert code == 0, out
        assert float(mbpoll_values(out)[0]) == pytest.approx(0.168, abs=1e-6)
        # A digiLine string: the device name, 5 registers.
        code, out = await mbpoll("-a", "1", "-r", "0", "-c", "5", "-t", "4:hex", *base)
        assert code == 0, out
        words = [int(v, 16) for v in mbpoll_values(out).values()]
        text = b"".join(w.to_bytes(2, "big") for w in words).split(b"\x00")[0]
        assert text == b"ODO S10"
        # An unmapped address answers exception 02.
        code, out = await mbpoll("-a", "1", "-r", str(0x2345), "-c", "1", *base)
        assert code != 0
        assert "Illegal data address" in out
        stats = server.bus.stats()
    assert stats["exceptions"] == {"2": 1}
    assert stats["timing_violations"] == 0


async def test_pymodbus_client_agrees(tmp_path: Path) -> None:

    port = tmp_path / "ttySIM"
    async with serving(DEVICES) as server:
        server.open_pty(port)
        client = AsyncModbusSerialClient(port=str(port), baudrate=9600, timeout=1, retries=0)
        await client.connect()
        try:
            float32 = client.DATATYPE.FLOAT32
            answer = await client.read_holding_registers(0x2620, count=2, device_id=1)
            assert (
                client.convert_from_registers(answer.registers, float32, word_order="little")
                == 20.25
            )
            await asyncio.sleep(0.05)  # pymodbus itself leaves no inter-frame gap
            answer = await client.read_holding_registers(0x0000, count=2, device_id=20)
            concentration = client.convert_from_registers(
                answer.registers, float32, word_order="little"
            )
            assert concentration == pytest.approx(0.168, abs=1e-6)
        finally:
            client.close()


async def test_pty_can_be_unplugged_and_plugged_back(tmp_path: Path) -> None:
    port = tmp_path / "ttyUSB0"
    async with serving(DEVICES) as server:
        server.open_pty(port)
        server.unplug_pty()
        assert not port.exists()
        code, _ = await mbpoll(
            "-m", "rtu", "-a", "1", "-r", "9760", "-c", "1", "-t", "4:float", "-0", "-1", str(port)
        )
        assert code != 0
        server.replug_pty()
        code, out = await mbpoll(
            "-m",
            "rtu",
            "-a",
            "1",
            "-b",
            "9600",
            "-P",
            "none",
            "-r",
            "9760",
            "-c",
            "1",
            "-t",
            "4:float",
            "-0",
            "-1",
            str(port),
        )
        assert code == 0, out
        assert mbpoll_values(out) == {9760: "20.25"}


# --- faults, as the bytes a master sees on a TCP line ---------------------------------------


async def exchange(port: int, request: frames.Request, *, wait_s: float = 0.3) -> bytes:
    """Send one request over RTU-over-TCP and collect every byte for ``wait_s``."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(request.frame)
        await writer.drain()
        received = b""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + wait_s
        while (left := deadline - loop.time()) > 0:
            try:
                chunk = await asyncio.wait_for(reader.read(256), timeout=left)
            except TimeoutError:
                break
            if not chunk:
                break
            received += chunk
        return received
    finally:
        writer.close()


TEMPERATURE = frames.read_request(1, 0x2620, 2)
CLEAN = bytes.fromhex("01 03 04 00 00 41 A2 4B DA")


async def faulty(
    fault: dict[str, Any], request: frames.Request = TEMPERATURE, **kw: float
) -> bytes:
    async with serving([{**DEVICES[0], "faults": fault}]) as server:
        port = await server.open_tcp("127.0.0.1", 0)
        return await exchange(port, request, **kw)


async def test_clean_answer_over_tcp() -> None:
    assert await faulty({}) == CLEAN


async def test_fault_corrupted_crc_on_the_wire() -> None:
    received = await faulty({"crc": 1.0})
    assert len(received) == len(CLEAN)
    assert received != CLEAN
    assert not frames.crc_ok(received)


async def test_fault_dropped_answer_on_the_wire() -> None:
    assert await faulty({"drop": 1.0}) == b""


async def test_fault_late_answer_on_the_wire() -> None:
    assert await faulty({"late": 1.0, "late_s": 0.4}, wait_s=0.3) == b""
    assert await faulty({"late": 1.0, "late_s": 0.4}, wait_s=0.8) == CLEAN


async def test_fault_noise_before_the_answer_on_the_wire() -> None:
    received = await faulty({"noise": 1.0})
    assert received.endswith(CLEAN)
    assert 1 <= len(received) - len(CLEAN) <= 4


async def test_fault_wrong_address_on_the_wire() -> None:
    received = await faulty({"wrong_address": 1.0})
    assert received[0] == 2
    assert received[1:-2] == CLEAN[1:-2]
    assert frames.crc_ok(received)


async def test_fault_string_byte_count_on_the_wire() -> None:
    received = await faulty(
        {"string_byte_count_16bit": True}, request=frames.read_request(1, 0x0000, 5)
    )
    assert received[:4] == bytes.fromhex("01 03 00 0A")
    assert frames.crc_ok(received)
    assert received[4:11] == b"ODO S10"


async def test_fault_silent_sensor_on_the_wire() -> None:
    async with serving([{**DEVICES[0], "faults": {"silences": [[0.0, 0.6]]}}]) as server:
        port = await server.open_tcp("127.0.0.1", 0)
        assert await exchange(port, TEMPERATURE, wait_s=0.2) == b""
        await asyncio.sleep(0.5)
        assert await exchange(port, TEMPERATURE) == CLEAN


async def test_early_request_is_ignored_on_the_wire() -> None:
    async with serving([DEVICES[0]]) as server:
        port = await server.open_tcp("127.0.0.1", 0)
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(TEMPERATURE.frame + TEMPERATURE.frame)  # no gap at all between the two
        await writer.drain()
        first = await asyncio.wait_for(reader.readexactly(len(CLEAN)), timeout=1)
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(reader.read(1), timeout=0.2)
        writer.close()
        assert first == CLEAN
        assert server.bus.stats()["violations_by_rule"] == {"inter_frame_gap": 1}


async def test_frames_that_waited_out_a_stall_of_the_referee_are_not_judged() -> None:
    """Back-to-back requests that arrive while the simulator's loop is held up.

    The kernel kept them while the loop was blocked, so their arrival times say nothing
    of the master's gaps: the referee must not blame it. Both are answered, none is a
    violation, and the stall is counted. The test before shows the same bytes judged.
    """
    async with serving([DEVICES[0]]) as server:
        port = await server.open_tcp("127.0.0.1", 0)
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        await asyncio.sleep(0.05)
        writer.write(TEMPERATURE.frame)
        time.sleep(0.004)  # noqa: ASYNC251 - the master's gap, while the loop is held up
        writer.write(TEMPERATURE.frame)
        time.sleep(0.03)  # noqa: ASYNC251 - a harness busy elsewhere: nobody reads
        received = await asyncio.wait_for(reader.readexactly(2 * len(CLEAN)), timeout=1)
        writer.close()
        assert received == CLEAN + CLEAN
        stats = server.bus.stats()
        assert stats["timing_violations"] == 0
        assert stats["counters"]["unjudged"] == 2
        assert stats["counters"]["referee_stalls"] >= 1


async def test_a_request_read_before_the_late_end_of_the_last_burst_is_not_merged_into_it(
    tmp_path: Path,
) -> None:
    """The first request is read on time; the loop is then held up past the silence that
    ends its burst, and the second request, sent 20 ms later (the master kept its gap), is
    read before the late flush (a pty's reader runs before the loop's overdue timers).
    Judged as one burst, the second was taken to follow the first with no gap at all and
    blamed on the master (seen once in a scan of 247 addresses at 115200 baud). Bytes read
    while the loop catches up cannot be timed: the burst is answered, frame by frame, and
    not judged.
    """
    port = tmp_path / "ttySIM"
    server = FeedsCounted(build_bus(parse_settings({"devices": [DEVICES[0]]})))
    try:
        server.open_pty(port)
        master = serial.Serial(str(port), baudrate=9600, timeout=1)
        try:
            await asyncio.sleep(0.05)
            master.write(TEMPERATURE.frame)
            await asyncio.wait_for(server.fed.wait(), 1)  # read, not yet flushed
            second = threading.Timer(0.02, master.write, (TEMPERATURE.frame,))
            second.start()
            time.sleep(0.04)  # noqa: ASYNC251 - the simulator's loop held up meanwhile
            second.join()
            received = await asyncio.to_thread(master.read, 2 * len(CLEAN))
        finally:
            master.close()
        assert received == CLEAN + CLEAN
        stats = server.bus.stats()
        assert stats["timing_violations"] == 0, stats["violations"]
        assert stats["counters"]["unjudged"] == 2
    finally:
        await server.close()


class FeedsCounted(SimulatorServer):
    """The simulator, saying when it first read bytes (it asks then whether it was held up)."""

    def __init__(self, bus: SimulatedBus) -> None:
        super().__init__(bus)
        self.fed = asyncio.Event()

    def stalled(self, now: float) -> bool:
        self.fed.set()
        return super().stalled(now)


async def test_pyserial_socket_url_reaches_the_simulator() -> None:

    async with serving([DEVICES[0]]) as server:
        port = await server.open_tcp("127.0.0.1", 0)
        line = serial.serial_for_url(f"socket://127.0.0.1:{port}", timeout=1)
        try:
            line.write(TEMPERATURE.frame)
            received = await asyncio.to_thread(line.read, len(CLEAN))
        finally:
            line.close()
        assert received == CLEAN


async def test_wire_pacing_takes_the_real_line_time() -> None:
    line = {"baudrate": 9600, "parity": "E", "stopbits": 1}
    async with serving([DEVICES[0]], line=line, pace=True) as server:
        port = await server.open_tcp("127.0.0.1", 0)
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        loop = asyncio.get_running_loop()
        sent = loop.time()
        writer.write(TEMPERATURE.frame)
        answer = await asyncio.wait_for(reader.readexactly(len(CLEAN)), timeout=1)
        elapsed = loop.time() - sent
        writer.close()
    character = 11 / 9600
    assert answer == CLEAN
    # request (8 bytes) + t1 (5 ms) + answer (9 bytes) at 1.146 ms per character
    assert elapsed >= 17 * character + 0.005
