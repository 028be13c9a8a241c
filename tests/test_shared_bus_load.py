"""What one other master can do to the line: floods, clients that never read, odd RTU frames.

The gateway polls two simulated sensors (9600 8E1 on a pseudo-terminal) while another
master, in a process of its own (``tests.flood_client``), pipelines requests at it as fast
as TCP takes them. The simulator's frame log is the judge of the polling: it holds the
time every request reached the line.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import sys
from pathlib import Path
from typing import Any

from tests.test_shared_bus import H10, TECLINE, Plant, plant

ROOT = Path(__file__).parent.parent
POLL_S = 0.5
SLACK_S = 0.25  # a poll may wait out the transaction and the other master's turn before it


async def flood(port: int, unit: int, seconds: float, pdu: str = "0300000002") -> dict[str, Any]:
    """Run ``tests.flood_client`` against ``port``: what it sent, and the answers it read."""
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "tests.flood_client",
        "--port",
        str(port),
        "--unit",
        str(unit),
        "--pdu",
        pdu,
        "--seconds",
        str(seconds),
        cwd=ROOT,
        stdout=asyncio.subprocess.PIPE,
    )
    assert process.stdout is not None
    assert await asyncio.wait_for(process.stdout.readline(), timeout=10) == b"connected\n"
    output = await asyncio.wait_for(process.stdout.read(), timeout=seconds + 10)
    assert await process.wait() == 0
    result: dict[str, Any] = json.loads(output)
    return result


def largest_gaps(p: Plant, since: float, until: float) -> dict[int, float]:
    """Per sensor, the longest time between two requests the line carried to it."""
    gaps: dict[int, float] = {}
    for address in (TECLINE, H10):
        starts = (
            [since] + [f.start for f in p.frames_to(address) if since <= f.start <= until] + [until]
        )
        gaps[address] = max(b - a for a, b in itertools.pairwise(starts))
    return gaps


def bus_time(p: Plant) -> float:
    """Now, on the simulator's clock (seconds since its bus started)."""
    return asyncio.get_running_loop().time() - p.simulator.bus.started


def missed(p: Plant) -> int:
    return sum(h.missed_deadlines for h in p.state.health())


async def test_a_client_pipelining_unknown_unit_ids_does_not_stop_the_polling(
    tmp_path: Path,
) -> None:
    shared = "shared_bus:\n  listen: [{host: 127.0.0.1, port: 0}]\n"
    async with plant(tmp_path, shared, poll_interval=POLL_S) as p:
        await asyncio.sleep(1.0)  # identity and the first slow reads are through
        missed_before, since = missed(p), bus_time(p)
        result = await flood(p.tcp_port, 99, 4.0)
        until = bus_time(p)
        gaps = largest_gaps(p, since, until)
        missed_after = missed(p)
        other = p.state.shared_bus.clients["other"]
    print(result, gaps, missed_after - missed_before)  # noqa: T201 - figures for the report
    assert result["answers"]
    assert set(result["answers"]) == {"830a"}
    assert all(gap <= POLL_S + SLACK_S for gap in gaps.values()), gaps
    assert missed_after == missed_before
    assert other.refused["unknown_unit"] == result["answers"]["830a"]
