"""The simulated line of the peers bench: ``gateway simulate`` with its frame log, and its reading.

``gateway simulate --stats`` keeps counters and the referee's violations, but not when each
frame came and when its answer went, which the bench needs for frames per cycle and for the
gaps a master leaves on the wire. So this runs the same simulator (the package's public
names, as the command does) in a process of its own, so that no master shares its event
loop, and on SIGTERM or SIGINT writes one JSON file: ``started`` (the bus's start on the
monotonic clock, which every process of the machine shares), ``stats`` (what ``--stats``
holds) and ``frames`` (``[start_s, device, function, address, quantity, outcome,
answer_at_s]`` each, seconds since ``started``; ``answer_at_s`` is when the answer's last
byte is on the line, null when none went out).

Run: .venv/bin/python -m bench.peer_line --config FILE --pty PATH --out FILE
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import signal
import statistics
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.wire.timing import LineFormat


async def serve(config: Path, pty: Path, out: Path) -> None:
    """Serve the line until told to stop, then write what happened on it."""
    # Imported here: the bench reads logs with this module and needs no simulator for it.
    from gateway.simulator import SimulatorServer, build_bus, load_settings  # noqa: PLC0415

    bus = build_bus(load_settings(config))
    server = SimulatorServer(bus)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    try:
        server.open_pty(pty)
        print(f"ready {pty}", flush=True)  # the bench waits for this line
        await stop.wait()
    finally:
        await server.close()
    frames = [
        [r.start, r.device, r.function, r.address, r.quantity, r.outcome, r.answer_at]
        for r in bus.frame_log
    ]
    document = {"started": bus.started, "stats": bus.stats(), "frames": frames}
    temporary = out.with_suffix(out.suffix + ".tmp")
    temporary.write_text(json.dumps(document), encoding="utf-8")
    temporary.replace(out)  # the bench never reads half a file


@dataclass(frozen=True, slots=True)
class Frame:
    """One request as the simulator logged it; times in seconds on the monotonic clock."""

    start: float
    device: int
    function: int
    address: int
    quantity: int
    outcome: str
    answer_at: float | None


def frames_in(document: Mapping[str, Any], t0: float, t1: float) -> list[Frame]:
    """The requests whose first byte came between ``t0`` and ``t1`` (monotonic seconds)."""
    started = float(document["started"])
    frames = []
    for start, device, function, address, quantity, outcome, answer in document["frames"]:
        at = None if answer is None else started + answer
        frames.append(Frame(started + start, device, function, address, quantity, outcome, at))
    return [f for f in frames if t0 <= f.start <= t1]


def wire_figures(
    document: Mapping[str, Any],
    line: LineFormat,
    *,
    required_gap_s: Mapping[int, float],
    t0: float,
    t1: float,
) -> dict[str, Any]:
    """Requests, transactions, line occupancy and gaps in a window, and the referee's view.

    A gap runs from the end of an answer to the first byte of the next request: what the
    master waited after hearing the line fall silent. ``required_gap_s`` is the least one
    per device address (3.5 characters, or a family's larger minimum).
    """
    frames = frames_in(document, t0, t1)
    answered = [f for f in frames if f.answer_at is not None]
    gaps = [
        (b.start - a.answer_at, b.device) for a, b in pairwise(frames) if a.answer_at is not None
    ]
    stats = document["stats"]
    window = t1 - t0
    return {
        "frames_per_cycle": len({(f.device, f.function, f.address, f.quantity) for f in frames}),
        "requests": len(frames),
        "transactions": len(answered),
        "transactions_per_s": len(answered) / window,
        "line_busy": sum(f.answer_at - f.start for f in answered if f.answer_at is not None)
        / window,
        "min_gap_ms": 1000 * min((g for g, _ in gaps), default=math.nan),
        "median_gap_ms": 1000 * statistics.median(g for g, _ in gaps) if gaps else math.nan,
        "required_gap_ms": 1000 * line.frame_gap_s(),
        "gaps_below_required": sum(1 for g, d in gaps if g < required_gap_s.get(d, 0.0)),
        "timing_violations": stats["timing_violations"],
        "violations_by_rule": stats["violations_by_rule"],
        "faults_injected": stats["faults_injected"],
        "unjudged_frames": stats["counters"].get("unjudged", 0),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--config", type=Path, required=True, help="simulator YAML file")
    parser.add_argument("--pty", type=Path, required=True, help="where to link the line")
    parser.add_argument("--out", type=Path, required=True, help="JSON file written at the end")
    args = parser.parse_args()
    asyncio.run(serve(args.config, args.pty, args.out))


if __name__ == "__main__":
    main()
