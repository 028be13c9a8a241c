"""What the records cost a write: time and frames on the line, recorded against not.

One simulated S10 on a pseudo-terminal at 19200 8E1 (the simulator paces every frame at
its wire time and referees the timing rules). The same write of a RAM point
(``compensation_temperature``) goes out through ``SafeWriter`` three ways, in turn, round
after round (pairwise, so that the machine's noise falls on all three alike):

- **plain**: no record store (the write path before the records);
- **recorded**: the serial number and the value as found read first, the write's record
  on disk before it is sent and its outcome after (two SQLite transactions with
  ``synchronous=EXTRA``), the point read back;
- **feed**: a compensation feed (``feed=True``, no read-back): counted, not recorded.

Printed: the median and the 90th percentile of each way's time per write, its frames per
write on the line, and the store's append alone (per record, and its bytes on disk).
Written to bench/results/records.json.
Run from the repository root: .venv/bin/python -m bench.records [--rounds 40]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import tempfile
import time
from datetime import date
from pathlib import Path

from gateway.config import FlashPolicy
from gateway.control.flash import FlashLedger
from gateway.control.link import DeviceLink
from gateway.control.writes import SafeWriter
from gateway.line.engine.devices import DeviceTarget
from gateway.line.engine.worker import BusWorker
from gateway.line.transports.serial_line import SerialLine
from gateway.profiles import get_profile
from gateway.records import (
    Actor,
    Entry,
    FeedCounts,
    Kind,
    RecordStore,
    Result,
    Via,
    acting,
    records_path,
)
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire.timing import LineFormat

RESULTS = Path(__file__).parent / "results"
LINE = {"baudrate": 19200, "parity": "E", "stopbits": 1}
OPERATOR = Actor(user="bench", via=Via.CLI, reason="bench")
DAY = date(2026, 12, 2)


def _percentile(values: list[float], share: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(share * (len(ordered) - 1)))]


async def _measure(rounds: int, folder: Path) -> dict[str, object]:
    server = SimulatorServer(
        build_bus(
            parse_settings(
                {
                    "devices": [{"profile": "jumo-digiline-odo-s10", "address": 1}],
                    "line": LINE,
                    "pace": True,
                }
            )
        )
    )
    port = folder / "ttyRS485"
    server.open_pty(port)
    line = SerialLine(port=str(port), line=LineFormat(**LINE))  # type: ignore[arg-type]
    target = DeviceTarget(
        name="s10", address=1, profile=get_profile("jumo-digiline-odo-s10"), intervals={}
    )
    worker = BusWorker(name="line1", line=line, devices=[target], sinks=[])
    await line.open()
    store = RecordStore(records_path(folder / "state"))
    policy = FlashPolicy(allowed=frozenset(), daily_budget=4)
    ledger = FlashLedger(None)
    link = DeviceLink(worker, "s10")
    ways = {
        "plain": SafeWriter(link, policy=policy, ledger=ledger, today=lambda: DAY),
        "recorded": SafeWriter(
            link, policy=policy, ledger=ledger, today=lambda: DAY, records=store
        ),
        "feed": SafeWriter(
            link,
            policy=policy,
            ledger=ledger,
            today=lambda: DAY,
            records=store,
            feeds=FeedCounts(store, today=lambda: DAY),
        ),
    }
    point = link.profile.point("compensation_temperature")
    times: dict[str, list[float]] = {way: [] for way in ways}
    frames: dict[str, int] = dict.fromkeys(ways, 0)
    try:
        await ways["plain"].set(point, 20.0)  # the word order and response time, once
        with acting(OPERATOR):
            for round_ in range(rounds):
                for way, writer in ways.items():
                    before = len(server.bus.frame_log)
                    start = time.perf_counter()
                    value = 20.0 + round_ % 10
                    if way == "feed":
                        await writer.set(point, value, read_back=False, feed=True)
                    else:
                        await writer.set(point, value)
                    times[way].append(time.perf_counter() - start)
                    frames[way] += len(server.bus.frame_log) - before
        appends = []
        entry = Entry(kind=Kind.RELOAD, actor=OPERATOR, action="bench", result=Result.NOTED)
        for _ in range(200):
            start = time.perf_counter()
            store.append(entry)
            appends.append(time.perf_counter() - start)
        size = records_path(folder / "state").stat().st_size
        count = store.head.seq
        violations = len(server.bus.violations)
    finally:
        store.close()
        await line.close()
        await server.close()
    return {
        "rounds": rounds,
        "ways": {
            way: {
                "median_ms": statistics.median(values) * 1000,
                "p90_ms": _percentile(values, 0.9) * 1000,
                "frames_per_write": frames[way] / rounds,
            }
            for way, values in times.items()
        },
        "append_median_ms": statistics.median(appends) * 1000,
        "bytes_per_record": size / count,
        "timing_violations": violations,
    }


def main() -> None:
    """Measure, print, write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=40)
    options = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        result = asyncio.run(_measure(options.rounds, Path(folder)))
    print(f"{'way':<10} {'median ms':>10} {'p90 ms':>8} {'frames/write':>13}")
    ways = result["ways"]
    assert isinstance(ways, dict)
    for way, figures in ways.items():
        print(
            f"{way:<10} {figures['median_ms']:>10.1f} {figures['p90_ms']:>8.1f} "
            f"{figures['frames_per_write']:>13.1f}"
        )
    print(
        f"append alone: {result['append_median_ms']:.2f} ms a record, "
        f"{result['bytes_per_record']:.0f} bytes on disk; "
        f"timing violations on the line: {result['timing_violations']}"
    )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "records.json").write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
