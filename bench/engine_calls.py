"""The function calls of one transaction: a count that resolves a step of 1 %, where CPU cannot.

The engine's CPU per transaction moves with the machine by far more than a step of a few
per cent (``bench/engine_pairs.py`` measures two engines at once to see through that), but
the calls it makes do not move at all. Between the gateway and the bare master of
``bench/bare_master.py`` the two agreed: the gateway made 1.49 times the bare master's
calls a transaction (337 and 226 at 19200 8N1) when its CPU was 1.46-1.54 times the bare
master's. Within the engine they are not in proportion: a tenth of its calls taken off
was 4-6 % of its CPU (2026-12-05; the calls left cost more each, the event loop's wakes
most). So this count says exactly what a step takes off the path of a transaction, and
the pairs what that is worth.

The reference plant of ``bench/bus_efficiency.py`` is polled on a simulated line as there
(poll interval 1 ms, the line always busy) for --seconds under :mod:`cProfile`, after the
warm-up; the calls are counted per transaction, by where the called code lives: the
gateway's own, asyncio's (with the event loop's selector and the port's transport), other
libraries', and built-in functions and methods. The gateway's functions called most are
listed, per transaction. The bare master is counted the same way.

cProfile makes every call slower, so no time it reports is a figure; only the counts are.

Run from the repository root:
.venv/bin/python -m bench.engine_calls [--seconds 8] [--format 19200-N-1] [--top 25]
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import pstats
from collections import Counter
from typing import TYPE_CHECKING

from bench.bare_master import measure_bare
from bench.bus_efficiency import measure, plan_gap_s, planned_reads, simulated_line
from bench.engine_pairs import line_format

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.wire.timing import LineFormat

KINDS = ("gateway", "asyncio", "library", "built-in")


def kind_of(filename: str) -> str:
    """Where a profiled function lives, by its file (``~``: built into the interpreter)."""
    if filename == "~":
        return "built-in"
    if "/gateway/" in filename and "site-packages" not in filename:
        return "gateway"
    if "asyncio" in filename or filename.endswith("selectors.py"):
        return "asyncio"  # the event loop, its selector, and the port's asyncio transport
    return "library"


def counted(profile: cProfile.Profile) -> pstats.Stats:
    """The calls ``profile`` saw."""
    return pstats.Stats(profile)


def per_transaction(stats: pstats.Stats, transactions: float) -> Counter[str]:
    """Calls per transaction by kind, and by function for the gateway's own."""
    calls: Counter[str] = Counter()
    raw: dict[tuple[str, int, str], tuple[int, int, float, float, object]] = stats.stats  # type: ignore[attr-defined]
    for (filename, line, name), (_, ncalls, _, _, _) in raw.items():
        kind = kind_of(filename)
        calls[kind] += ncalls
        if kind == "gateway":
            where = filename.rsplit("/gateway/", 1)[1]
            calls[f"gateway/{where}:{line} {name}"] += ncalls
    return Counter({key: n / transactions for key, n in calls.items()})


async def gateway_calls(port: Path, line: LineFormat, seconds: float) -> Counter[str]:
    """The gateway's calls per transaction polling the plant on ``port``.

    Counted over the measured seconds only, after the warm-up (the identity reads).
    """
    profile = cProfile.Profile()
    figures = await measure(port, line, seconds, profile=profile)
    return per_transaction(counted(profile), figures["transactions"])


async def bare_calls(port: Path, line: LineFormat, seconds: float) -> Counter[str]:
    """The bare master's calls per transaction reading the plant's reads on ``port``.

    Counted over a second run of it: the first one warms up, as the gateway's does.
    """
    gap_s, reads = plan_gap_s(line), planned_reads(line)
    await measure_bare(port, line.baudrate, gap_s, reads, 2.0)
    profile = cProfile.Profile()
    profile.enable()
    try:
        figures = await measure_bare(port, line.baudrate, gap_s, reads, seconds)
    finally:
        profile.disable()
    return per_transaction(counted(profile), figures["bare_transactions_per_s"] * seconds)


def report(name: str, calls: Counter[str], top: int) -> float:
    """Print one master's calls per transaction; return their total."""
    total = sum(calls[k] for k in KINDS)
    kinds = ", ".join(f"{k} {calls[k]:.1f}" for k in KINDS)
    print(f"{name}: {total:.1f} calls a transaction ({kinds})")
    own = [(n, k) for k, n in calls.items() if k.startswith("gateway/")]
    for n, key in sorted(own, reverse=True)[:top]:
        print(f"  {n:6.2f}  {key}")
    return total


def main() -> None:
    """Count both masters' calls at one line format and print them."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--format", default="19200-N-1")
    parser.add_argument("--top", type=int, default=25, help="the gateway's functions listed")
    args = parser.parse_args()
    line = line_format(args.format)
    with simulated_line(line) as (port, _):
        gateway = asyncio.run(gateway_calls(port, line, args.seconds))
    with simulated_line(line) as (port, _):
        bare = asyncio.run(bare_calls(port, line, args.seconds))
    ours = report("gateway", gateway, args.top)
    floor = report("bare master", bare, 0)
    print(f"gateway / bare master: {ours / floor:.2f}")


if __name__ == "__main__":
    main()
