"""The floor under the gateway's CPU per transaction: a master that does nothing else.

Same libraries as the gateway (pyserial-asyncio-fast for the port, pymodbus's RTU framer
and PDUs for the frames), same simulated line and the same reads of the reference plant,
round-robin, one after the other. It keeps none of what makes a gateway: no schedule, no
decoded values, no device health, no timing rules beyond sleeping the inter-frame gap
(asyncio's sleep: up to 1 ms late, so it is slower on the wire; only its CPU is the
figure). What it costs per transaction is what any asyncio master with these libraries
pays on this machine: the event loop's turns, the port's reads and writes, the framer.

``bench/bus_efficiency.py`` runs it after the gateway on the same line and prints both, or,
with ``--at-once``, in a process of its own on a line of its own while the gateway runs
(this module's command line: the reads as JSON, the figures printed as JSON).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

import serial_asyncio_fast
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.register_message import ReadHoldingRegistersRequest

if TYPE_CHECKING:
    from collections.abc import Sequence

ANSWER_TIMEOUT_S = 1.0


class _Answer(asyncio.Protocol):
    """Collects the bytes of the answer to the one request in flight."""

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.waiter: asyncio.Future[None] | None = None

    def data_received(self, data: bytes) -> None:
        self.buffer.extend(data)
        if self.waiter is not None and not self.waiter.done():
            self.waiter.set_result(None)


async def measure_bare(
    port: Path, baudrate: int, gap_s: float, reads: Sequence[tuple[int, int, int]], seconds: float
) -> dict[str, float]:
    """Read ``reads`` (device, address, count) round-robin for ``seconds``; CPU per read."""
    loop = asyncio.get_running_loop()
    answer = _Answer()
    # No parity on the pseudo-terminal, as the gateway does there (it refuses one).
    transport, _ = await serial_asyncio_fast.create_serial_connection(
        loop, lambda: answer, str(port), baudrate=baudrate
    )
    framer = FramerRTU(DecodePDU(is_server=False))
    requests = [
        (
            bytes(framer.buildFrame(ReadHoldingRegistersRequest(address=a, count=c, dev_id=d))),
            5 + 2 * c,
        )
        for d, a, c in reads
    ]
    devices = [d for d, _, _ in reads]
    done = failed = 0
    try:
        cpu0, wall0 = time.process_time(), time.monotonic()
        while time.monotonic() - wall0 < seconds:
            for (frame, length), device in zip(requests, devices, strict=True):
                await asyncio.sleep(gap_s)
                answer.buffer.clear()
                transport.write(frame)
                try:
                    while len(answer.buffer) < length:
                        answer.waiter = loop.create_future()
                        await asyncio.wait_for(answer.waiter, ANSWER_TIMEOUT_S)
                except TimeoutError:
                    failed += 1  # counted and shown: a floor from failed reads is no floor
                    continue
                _, pdu = framer.handleFrame(bytes(answer.buffer), device, 0)
                if pdu is None or len(pdu.registers) * 2 + 5 != length:
                    failed += 1
                    continue
                done += 1
        cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
    finally:
        transport.abort()
    return {
        "bare_transactions_per_s": done / wall,
        "bare_cpu_us_per_transaction": 1e6 * cpu / max(done, 1),
        "bare_failed": failed,
    }


async def wake_cost(wait_s: float, waits: int = 300) -> dict[str, float]:
    """CPU of one timed wait of the event loop: going to sleep for ``wait_s`` and waking.

    A transaction needs two at least (the inter-frame gap, the answer), so this is the
    part of the floor no code of a master can remove. On a virtual machine it is far more
    than the few microseconds of the system calls: the interpreter resumes with cold
    caches after every sleep.
    """
    cpu0 = time.process_time()
    for _ in range(waits):
        await asyncio.sleep(wait_s)
    return {"wake_cpu_us": 1e6 * (time.process_time() - cpu0) / waits}


async def warmed_up(
    port: Path,
    baudrate: int,
    gap_s: float,
    reads: Sequence[tuple[int, int, int]],
    seconds: float,
    *,
    warm_s: float,
) -> dict[str, float]:
    """:func:`measure_bare` after ``warm_s`` unmeasured, as the gateway's run warms up."""
    await measure_bare(port, baudrate, gap_s, reads, warm_s)
    return await measure_bare(port, baudrate, gap_s, reads, seconds)


def main() -> None:
    """Measure on one port and print the figures as JSON (for ``bus_efficiency --at-once``)."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--port", type=Path, required=True)
    parser.add_argument("--baudrate", type=int, required=True)
    parser.add_argument("--gap-s", type=float, required=True)
    parser.add_argument("--reads", required=True, help="JSON list of [device, address, count]")
    parser.add_argument("--seconds", type=float, required=True)
    parser.add_argument("--warm-s", type=float, default=2.0)
    args = parser.parse_args()
    reads = [(int(d), int(a), int(c)) for d, a, c in json.loads(args.reads)]
    figures = asyncio.run(
        warmed_up(args.port, args.baudrate, args.gap_s, reads, args.seconds, warm_s=args.warm_s)
    )
    print(json.dumps(figures), flush=True)


if __name__ == "__main__":
    main()
