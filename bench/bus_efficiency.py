"""How close the bus engine gets to the fastest polling the manuals allow.

Reference plant: one S10, one H10, two tecLine and one Reiss M0c on one line, simulated
in a separate process with wire pacing, so the line takes the time a real one would. The
gateway polls the process and status points of every device as fast as it may (poll
interval 1 ms, so the line is always busy) for --seconds.

Each line format of --formats in turn (default: 9600 8E1, 19200 8N1, 38400 8E1, 115200 8N1
and 9600 8N2); printed as a table, and written to bench/results/bus_efficiency.json:
- frames and bus time per cycle of the plan, against one request per point;
- sustained transactions and point values per second;
- efficiency: the theoretical minimum bus time of the measured transactions (gap before
  each request, request and answer on the wire, the simulated device's answer delay)
  divided by the bus time measured;
- gap lateness: how late each request started after its inter-frame gap was due
  (median and 99th percentile, ms);
- the gateway's CPU time per transaction (this process only; the simulator runs apart)
  and its peak resident memory;
- the floor: the CPU per transaction of a bare master with the same libraries and the same
  reads that does nothing else (bench/bare_master.py), run next on the same line, and
  the CPU of one sleep and wake of the event loop for the gap's time (two per transaction
  at least).

With --runs N each format is measured N times, the gateway and the bare master in turn
(gateway, bare, gateway, bare, ...), since on a shared machine one run's ratio proves
nothing: each run's ratio is printed, then per format the median and the spread (least to
most), and the target is judged by the median.

With --at-once the bare master runs at the same time as the gateway, in a process of its
own on a simulated line of its own, over the same seconds. Both then meet the same machine:
a virtual machine's speed moves twofold within a minute (the same code's CPU per
transaction measured 225 and 540 µs a minute apart), and in turns that move lands on one
side of a ratio only (ratios of one commit spread 1.21-2.53 in turns, 1.47-1.55 at once).
Each process sleeps nearly all the time (some 2 % of a core each), so neither waits for
the other on two cores.

Run from the repository root:
.venv/bin/python -m bench.bus_efficiency [--seconds 15] [--runs 5] [--at-once] [--formats 9600-E-1]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

from bench.bare_master import measure_bare, wake_cost
from gateway.line.engine.devices import DeviceTarget
from gateway.line.engine.plan import CostModel, plan_reads
from gateway.line.engine.worker import BusWorker
from gateway.line.transports.serial_line import SerialLine
from gateway.profiles import PollGroup, get_profile
from gateway.wire.timing import TYPICAL_PROCESSING_S, LineFormat

if TYPE_CHECKING:
    import cProfile
    from collections.abc import Iterator, Sequence
    from typing import Any

    from gateway.line.engine.plan import ReadBlock
    from gateway.line.samples import DeviceEvent, Sample
    from gateway.line.stats import LineStats
    from gateway.profiles import Point

PLANT = [
    ("s10", "jumo-digiline-odo-s10", 1),
    ("h10", "jumo-digiline-odo-h10", 2),
    ("cl2", "jumo-tecline-cl2", 20),
    ("clo2", "jumo-tecline-clo2", 80),
    ("m0c", "reiss-m0c", 10),
]
RESULTS = Path(__file__).parent / "results"
WARM_UP_S = 2.0  # the identity reads and the first cycles, not measured


class CountingSink:
    """Counts values per device; keeps nothing else."""

    def __init__(self) -> None:
        self.values: dict[str, int] = {}

    async def publish(self, samples: Sequence[Sample]) -> None:
        for sample in samples:
            self.values[sample.device] = self.values.get(sample.device, 0) + 1

    async def device_event(self, event: DeviceEvent) -> None:
        pass


def targets(interval: float) -> list[DeviceTarget]:
    result = []
    for name, profile_id, address in PLANT:
        profile = get_profile(profile_id)
        points = [p for p in profile.points_in(PollGroup.PROCESS, PollGroup.STATUS) if not p.view]
        result.append(
            DeviceTarget(
                name=name,
                address=address,
                profile=profile,
                intervals={p.name: interval for p in points},
            )
        )
    return result


def transaction_s(line: LineFormat, request_bytes: int, answer_bytes: int, gap_s: float) -> float:
    """The least bus time of one transaction: gap, request, the device's t1, answer.

    t1 is the simulated device's processing time, the manuals' typical 5 ms (which already
    includes the 3.5 characters a slave needs to see the end of the request).
    """
    return gap_s + line.wire_s(request_bytes) + TYPICAL_PROCESSING_S + line.wire_s(answer_bytes)


def planned_cycle(line: LineFormat) -> list[tuple[DeviceTarget, list[Point], list[ReadBlock]]]:
    """Each device of the plant at ``line``: its polled points and the reads of its plan."""
    cycle = []
    for target in targets(1.0):
        profile = target.profile
        points = [profile.point(n) for n in target.intervals]
        blocks = plan_reads(points, profile, CostModel.for_device(profile, line))
        cycle.append((target, points, list(blocks)))
    return cycle


def plan_figures(line: LineFormat) -> dict[str, float]:
    planned_frames = per_point_frames = 0
    planned_s = per_point_s = 0.0
    for target, points, blocks in planned_cycle(line):
        gap = line.frame_gap_s(target.profile.timing.min_gap_s)
        planned_frames += len(blocks)
        planned_s += sum(transaction_s(line, 8, 5 + 2 * b.count, gap) for b in blocks)
        per_point_frames += len(points)
        per_point_s += sum(transaction_s(line, 8, 5 + 2 * p.count, gap) for p in points)
    return {
        "frames_per_cycle": planned_frames,
        "frames_per_cycle_one_per_point": per_point_frames,
        "bus_s_per_cycle": planned_s,
        "bus_s_per_cycle_one_per_point": per_point_s,
    }


def planned_reads(line: LineFormat) -> list[tuple[int, int, int]]:
    """The reads of one cycle of the plan at ``line``: (device, address, count) of each."""
    return [
        (target.address, b.address, b.count)
        for target, _, blocks in planned_cycle(line)
        for b in blocks
    ]


def plan_gap_s(line: LineFormat) -> float:
    """The longest inter-frame gap of the plant's devices at ``line``."""
    return max(line.frame_gap_s(get_profile(pid).timing.min_gap_s) for _, pid, _ in PLANT)


def write_simulator_config(path: Path, line: LineFormat) -> None:
    devices = "".join(f"  - {{profile: {pid}, address: {address}}}\n" for _, pid, address in PLANT)
    path.write_text(
        f"line: {{baudrate: {line.baudrate}, parity: {line.parity}, stopbits: {line.stopbits}}}\n"
        f"pace: true\nseed: 1\ndevices:\n{devices}",
        encoding="utf-8",
    )


async def measure(
    port: Path,
    line_format: LineFormat,
    seconds: float,
    *,
    keep_stats: list[LineStats] | None = None,
    profile: cProfile.Profile | None = None,
) -> dict[str, float]:
    """Poll the plant on ``port`` for ``seconds`` after a warm-up (line stats to ``keep_stats``).

    ``profile`` runs over the measured seconds only (``bench/engine_calls.py``).
    """
    sink = CountingSink()
    line = SerialLine(port=str(port), line=line_format)
    worker = BusWorker(name="bench", line=line, devices=targets(0.001), sinks=[sink])
    task = asyncio.create_task(worker.run())
    await asyncio.sleep(WARM_UP_S)  # identity reads and warm-up are not measured
    stats = line.stats
    lateness: list[float] = []
    line.gap_lateness_s = lateness
    requests0, busy0 = sum(stats.requests.values()), stats.busy_s
    values0 = sum(sink.values.values())
    if profile is not None:
        profile.enable()
    cpu0, wall0 = time.process_time(), time.monotonic()
    await asyncio.sleep(seconds)
    cpu1, wall1 = time.process_time(), time.monotonic()
    if profile is not None:
        profile.disable()
    line.gap_lateness_s = None
    requests = sum(stats.requests.values()) - requests0
    values = sum(sink.values.values()) - values0
    busy = stats.busy_s - busy0
    errors = sum(stats.errors.values())
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    await line.close()
    if keep_stats is not None:
        keep_stats.append(stats)
    return {
        "wall_s": wall1 - wall0,
        "transactions": requests,
        "transactions_per_s": requests / (wall1 - wall0),
        "values_per_s": values / (wall1 - wall0),
        "busy_s": busy,
        "cpu_us_per_transaction": 1e6 * (cpu1 - cpu0) / max(requests, 1),
        "errors": errors,
        **lateness_figures(lateness),
    }


def lateness_figures(lateness_s: list[float]) -> dict[str, float]:
    """Median and 99th percentile of the requests' lateness after their gap, in ms."""
    if len(lateness_s) < 2:  # noqa: PLR2004 - quantiles need two
        return {"gap_late_ms_median": float("nan"), "gap_late_ms_p99": float("nan")}
    p99 = statistics.quantiles(lateness_s, n=100)[98]
    return {
        "gap_late_ms_median": 1000 * statistics.median(lateness_s),
        "gap_late_ms_p99": 1000 * p99,
    }


SWEEP = ("9600-E-1", "19200-N-1", "38400-E-1", "115200-N-1", "9600-N-2")
# Issue 38: CPU per transaction at most 1.30 times the bare master's at every format, by the
# median of the runs, and the wire's efficiency at least 0.97 (issue 23 asked 1.25 and 0.95
# when the bare master ran after the gateway in its process).
CPU_RATIO_TARGET = 1.30
EFFICIENCY_TARGET = 0.97


def target_met(results: Sequence[dict[str, Any]]) -> bool:
    """Whether every format kept both: the CPU ratio to the bare master and the efficiency."""
    return all(
        r["cpu_ratio_to_bare"] <= CPU_RATIO_TARGET and r["efficiency"] >= EFFICIENCY_TARGET
        for r in results
    )


def summary(runs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One format's runs: each ratio, their median and spread, and the verdict by the median.

    The median, not the best or the mean: a run that another process slowed down moves
    neither end of the comparison's verdict by itself.
    """
    ratios = [float(r["cpu_ratio_to_bare"]) for r in runs]
    efficiency = statistics.median(float(r["efficiency"]) for r in runs)
    median = statistics.median(ratios)
    return {
        "line": runs[0]["line"],
        "ratios": ratios,
        "ratio_median": median,
        "ratio_min": min(ratios),
        "ratio_max": max(ratios),
        "cpu_us_median": statistics.median(float(r["cpu_us_per_transaction"]) for r in runs),
        "bare_cpu_us_median": statistics.median(
            float(r["bare_cpu_us_per_transaction"]) for r in runs
        ),
        "efficiency_median": efficiency,
        "met": median <= CPU_RATIO_TARGET and efficiency >= EFFICIENCY_TARGET,
    }


@contextlib.contextmanager
def simulated_line(line: LineFormat) -> Iterator[tuple[Path, dict[str, object]]]:
    """The reference plant in a ``gateway simulate`` process: its port, and its referee.

    The referee's figures fill the dictionary once the simulator has stopped.
    """
    with tempfile.TemporaryDirectory() as tmp:
        config, port, stats = (
            Path(tmp) / "plant.yaml",
            Path(tmp) / "ttyBENCH",
            Path(tmp) / "stats.json",
        )
        write_simulator_config(config, line)
        simulator = subprocess.Popen(  # noqa: S603 - our own simulator
            [
                sys.executable,
                "-m",
                "gateway",
                "simulate",
                "--config",
                str(config),
                "--pty",
                str(port),
                "--stats",
                str(stats),
            ],
            stdout=subprocess.PIPE,
            text=True,
            env={**os.environ, "COLUMNS": "200"},
        )
        assert simulator.stdout is not None
        simulator.stdout.readline()  # ready
        referee: dict[str, object] = {}
        try:
            yield port, referee
        finally:
            simulator.terminate()
            simulator.wait(timeout=10)
            referee.update(json.loads(stats.read_text(encoding="utf-8")))


def one_format(line: LineFormat, seconds: float, *, at_once: bool = False) -> dict[str, object]:
    """Run the reference plant at one line format and work out its figures.

    ``at_once``: the bare master measured at the same time, in a process of its own.
    """
    figures = plan_figures(line)
    gap_s = plan_gap_s(line)
    if at_once:
        with simulated_line(line) as (port, referee), simulated_line(line) as (bare_port, _):
            bare = bare_process(bare_port, line, gap_s, seconds)
            try:
                measured = asyncio.run(measure(port, line, seconds))
                out, _ = bare.communicate(timeout=seconds + 60)
            finally:
                if bare.poll() is None:  # the gateway's run failed: the bare master goes too
                    bare.kill()
                    bare.wait()
        floor: dict[str, float] = json.loads(out.strip().splitlines()[-1])
    else:
        with simulated_line(line) as (port, referee):
            measured = asyncio.run(measure(port, line, seconds))
        # The bare master on a line of its own: it keeps no timing rule but its sleep, and
        # the referee's verdict above is the gateway's alone.
        with simulated_line(line) as (port, _):
            floor = asyncio.run(
                measure_bare(port, line.baudrate, gap_s, planned_reads(line), seconds)
            )
    floor |= asyncio.run(wake_cost(gap_s))
    cycles_per_s = measured["transactions_per_s"] / figures["frames_per_cycle"]
    measured_cycle_s = 1.0 / cycles_per_s
    return {
        "line": str(line),
        "devices": [pid for _, pid, _ in PLANT],
        **figures,
        "measured_s_per_cycle": measured_cycle_s,
        "cycles_per_s": cycles_per_s,
        **measured,
        **floor,
        "efficiency": figures["bus_s_per_cycle"] / measured_cycle_s,
        "cpu_ratio_to_bare": measured["cpu_us_per_transaction"]
        / floor["bare_cpu_us_per_transaction"],
        "gateway_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "timing_violations": referee["timing_violations"],
    }


def bare_process(
    port: Path, line: LineFormat, gap_s: float, seconds: float
) -> subprocess.Popen[str]:
    """The bare master on ``port`` in a process of its own, warming up as the gateway does."""
    return subprocess.Popen(  # noqa: S603 - our own bench
        [
            sys.executable,
            "-m",
            "bench.bare_master",
            "--port",
            str(port),
            "--baudrate",
            str(line.baudrate),
            "--gap-s",
            repr(gap_s),
            "--reads",
            json.dumps(planned_reads(line)),
            "--seconds",
            repr(seconds),
            "--warm-s",
            repr(WARM_UP_S),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument(
        "--runs",
        type=int,
        default=1,
        help="runs per format, the gateway and the bare master in turn (default: %(default)s)",
    )
    parser.add_argument(
        "--at-once",
        action="store_true",
        help="measure the bare master at the same time as the gateway, not in turns",
    )
    parser.add_argument(
        "--formats",
        default=",".join(SWEEP),
        help="BAUD-PARITY-STOPBITS list (default: %(default)s)",
    )
    args = parser.parse_args()
    results = []
    summaries = []
    for text in args.formats.split(","):
        baudrate, parity, stopbits = text.split("-")
        line = LineFormat(baudrate=int(baudrate), parity=parity, stopbits=int(stopbits))
        runs = []
        for _ in range(args.runs):
            runs.append(one_format(line, args.seconds, at_once=args.at_once))
            print(json.dumps(runs[-1]), flush=True)
        results.extend(runs)
        summaries.append(summary(runs))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bus_efficiency.json").write_text(
        json.dumps({"runs": results, "summaries": summaries}, indent=2), encoding="utf-8"
    )
    print(
        f"{'line':<12} {'frames/cycle':>13} {'min ms':>7} {'meas ms':>8} {'efficiency':>10} "
        f"{'late ms':>7} {'p99':>5} {'tx/s':>6} {'values/s':>8} {'µs CPU/tx':>9} "
        f"{'bare µs/tx':>10} {'ratio':>5} {'wake µs':>7} {'RSS MiB':>7} {'err':>4} {'viol':>4}"
    )
    for r in results:
        frames_text = f"{r['frames_per_cycle']}/{r['frames_per_cycle_one_per_point']}"
        print(
            f"{r['line']:<12} {frames_text:>13} {1000 * r['bus_s_per_cycle']:>7.1f} "  # type: ignore[operator]
            f"{1000 * r['measured_s_per_cycle']:>8.1f} {r['efficiency']:>10.3f} "  # type: ignore[operator]
            f"{r['gap_late_ms_median']:>7.3f} {r['gap_late_ms_p99']:>5.2f} "
            f"{r['transactions_per_s']:>6.1f} {r['values_per_s']:>8.1f} "
            f"{r['cpu_us_per_transaction']:>9.0f} {r['bare_cpu_us_per_transaction']:>10.0f} "
            f"{r['cpu_ratio_to_bare']:>5.2f} "
            f"{r['wake_cpu_us']:>7.0f} "
            f"{r['gateway_rss_mib']:>7.1f} "
            f"{r['errors']:>4} {r['timing_violations']:>4}"
        )
    if args.runs > 1:
        print_summaries(summaries)
        met = all(s["met"] for s in summaries)
        judged = f"by the median of {args.runs} runs"
    else:
        met = target_met(results)
        judged = "in one run"
    verdict = "met" if met else "not met"
    print(
        f"CPU per transaction <= {CPU_RATIO_TARGET}x the bare master's and efficiency >= "
        f"{EFFICIENCY_TARGET} at every format, {judged}: {verdict}"
    )


def print_summaries(summaries: Sequence[dict[str, Any]]) -> None:
    """Per format: every run's ratio, the median, the spread and the verdict by the median."""
    print(
        f"{'line':<12} {'ratios, run by run':<36} {'median':>6} {'min-max':>11} "
        f"{'µs CPU/tx':>9} {'bare µs/tx':>10} {'efficiency':>10} {'met':>4}"
    )
    for s in summaries:
        ratios = " ".join(f"{r:.2f}" for r in s["ratios"])
        spread = f"{s['ratio_min']:.2f}-{s['ratio_max']:.2f}"
        print(
            f"{s['line']:<12} {ratios:<36} {s['ratio_median']:>6.2f} {spread:>11} "
            f"{s['cpu_us_median']:>9.0f} {s['bare_cpu_us_median']:>10.0f} "
            f"{s['efficiency_median']:>10.3f} {'yes' if s['met'] else 'no':>4}"
        )


if __name__ == "__main__":
    main()
