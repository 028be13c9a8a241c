"""What an FTDI adapter's USB latency timer costs one line: polling through a latency shim.

An FTDI adapter hands received bytes to the host when its latency timer runs out (16 ms by
default, ``ftdi_sio``), so every answer reaches the gateway up to a tick late. The
simulator's pseudo-terminal shim (``gateway.simulator.shim.LineShim``) holds the bytes from
the line to the master to such ticks; requests pass at once, as on a real adapter.

The reference plant of ``bench/bus_efficiency.py`` (one S10, one H10, two tecLine and one
Reiss M0c, simulated in a separate process with wire pacing) is polled as fast as it may
(poll interval 1 ms) for --seconds, at each line format of --formats, four ways: straight
to the simulator's pty; through the shim passing bytes at once (the relay's own cost: it
runs in the gateway's process); through the shim at 1 ms ticks (the udev rule's setting)
and at 16 ms (the driver's default). Printed as a table and written to
bench/results/latency_timer.json: transactions and values per second, the share of the
relay's throughput at 0 ms (so the relay's own cost is left out), the
mean request-to-answer latency and the errors counted (timeouts where a tick pushes an
answer past the response timeout).

Run from the repository root:
.venv/bin/python -m bench.latency_timer [--seconds 10] [--formats 9600-E-1,19200-N-1]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from bench.bus_efficiency import RESULTS, measure, simulated_line
from gateway.simulator.shim import FTDI_LATENCY_S, LineShim
from gateway.wire.timing import LineFormat

if TYPE_CHECKING:
    from collections.abc import AsyncIterator

    from gateway.line.stats import LineStats

FORMATS = ("9600-E-1", "19200-N-1", "38400-E-1", "115200-N-1")
# None: no shim, the simulator's pty itself; 0: the shim passing bytes at once (what the
# relay itself costs, in this process); then the udev rule's 1 ms and the default 16 ms.
LATENCIES_S = (None, 0.0, 0.001, FTDI_LATENCY_S)


@contextlib.asynccontextmanager
async def through_shim(upstream: Path, latency_s: float | None) -> AsyncIterator[Path]:
    """The port the gateway opens: the simulator's own, or the shim's at ``latency_s``."""
    if latency_s is None:
        yield upstream
        return
    with tempfile.TemporaryDirectory() as tmp:
        shim = LineShim(upstream=upstream, path=Path(tmp) / "ttyUSB0", latency_s=latency_s)
        shim.open()
        try:
            yield shim.path
        finally:
            shim.close()


def mean_latency_ms(stats: LineStats) -> float:
    """The mean request-to-answer time (to the answer's last byte) of the whole run."""
    answers = sum(stats.responses.values())
    return 1000 * sum(stats.latency_sum_s.values()) / answers if answers else math.nan


async def one_run(
    upstream: Path, line: LineFormat, latency_s: float | None, seconds: float
) -> dict[str, object]:
    """Poll the plant through the shim (or not) and keep the line's figures."""
    async with through_shim(upstream, latency_s) as port:
        kept: list[LineStats] = []
        figures = await measure(port, line, seconds, keep_stats=kept)
    return {
        "line": str(line),
        "latency_timer_ms": None if latency_s is None else 1000 * latency_s,
        **figures,
        "latency_ms_mean": mean_latency_ms(kept[0]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--formats", default=",".join(FORMATS))
    args = parser.parse_args()
    results: list[dict[str, object]] = []
    for text in args.formats.split(","):
        baudrate, parity, stopbits = text.split("-")
        line = LineFormat(baudrate=int(baudrate), parity=parity, stopbits=int(stopbits))
        for latency_s in LATENCIES_S:
            with simulated_line(line) as (port, referee):
                result = asyncio.run(one_run(port, line, latency_s, args.seconds))
            result["timing_violations"] = referee["timing_violations"]
            results.append(result)
            print(json.dumps(result), flush=True)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "latency_timer.json").write_text(json.dumps(results, indent=2), encoding="utf-8")
    print(
        f"{'line':<12} {'timer':>7} {'tx/s':>7} {'values/s':>9} {'share':>6} "
        f"{'latency ms':>10} {'errors':>6} {'viol':>4}"
    )
    relay: dict[str, float] = {}
    for r in results:
        tx = float(r["transactions_per_s"])  # type: ignore[arg-type]
        if r["latency_timer_ms"] == 0:
            relay[str(r["line"])] = tx
        timer = "no shim" if r["latency_timer_ms"] is None else f"{r['latency_timer_ms']:g} ms"
        print(
            f"{r['line']!s:<12} {timer:>7} {tx:>7.1f} {r['values_per_s']:>9.1f} "
            f"{tx / relay.get(str(r['line']), math.nan):>6.2f} {r['latency_ms_mean']:>10.1f} "
            f"{r['errors']:>6} {r['timing_violations']:>4}"
        )


if __name__ == "__main__":
    main()
