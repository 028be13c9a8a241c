"""Memory that scales with the points, not with the libraries: `gateway run` at two plant sizes.

For each size (default 4 x 16 and 16 x 16 devices): that many simulated lines at 115200 8N1
(the simulators all in one process apart), every device polled at 1 s, MQTT to a local
mosquitto and metrics on, `gateway run --config` as its own process, as a user runs it.
After the warm-up (identity reads, the start's backlog sent) and --seconds more, /metrics is
scraped once (as Prometheus does every 15 s or so) and the process's resident memory read
from /proc; then it is stopped, and writes at its exit the modules it imported.

The import floor is a process that imports exactly those modules, in the order the gateway
imported them, and nothing else: the libraries and our code for that config, before any
config is read or any point polled. Printed, per size: the floor, RSS after the scrape, its
peak, RSS - floor; then bytes per polled point from the two sizes,
(RSS2 - RSS1) / (points2 - points1), and whether each target of issue 23 is met:
RSS at the larger size <= floor + 12 MiB, and <= 300 bytes per polled point.

With --trace N the gateway runs under tracemalloc, and at the scrape writes the N largest
allocation sites (by line) to bench/results/memory-trace-BxD.txt: where the memory above
the floor is. Tracing costs memory of its own, so a traced run's RSS is not a figure.

With --reference N, instead: a plain `gateway run` of the reference plant of bench/peers.py
(five sensors on one simulated line at 9600 8E1, every process and status point at 1 s, MQTT
and metrics on, nothing optional), started as a user starts it, N times in a row; the RSS
after the peers' warm-up and --seconds (default 30) more of polling, and its peak, every run
printed, then the median. Issue 29's target: <= 45 MiB. The gateway's modules are compiled to
bytecode first, as an installed gateway has them: a module edited since its bytecode was
written is compiled from source at every start, which costs memory the installed gateway
does not spend (about 1 MiB with all of them).

Printed, and written to bench/results/memory.json. Run from the repository root:
.venv/bin/python -m bench.memory [--sizes 4x16,16x16] [--seconds 10] [--trace 40]
.venv/bin/python -m bench.memory --reference 3 [--seconds 30]
"""

from __future__ import annotations

import argparse
import asyncio
import compileall
import json
import os
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Final

from bench import peers
from bench.publish import (
    gateway_config,
    healthz,
    mosquitto,
    rss_mib,
    scrape,
    settled,
    simulators,
)
from gateway.app import device_target
from gateway.config import load_config
from gateway.wire.timing import LineFormat

RESULTS = Path(__file__).parent / "results"
GATEWAY_SOURCE = Path(__file__).parents[1] / "gateway"
WARM_UP_S = 5.0  # identity reads: every point read once at the start
REFERENCE_TARGET_MIB: Final = 45.0  # issue 29: a plain run of the reference plant
REFERENCE_LINE: Final = LineFormat(baudrate=9600, parity="E", stopbits=1)  # as bench.peers
FLOOR_ALLOWANCE_MIB: Final = 12.0  # issue 23, target 3
BYTES_PER_POINT: Final = 300  # issue 23, target 3
MIB = 1024 * 1024

# `gateway run` through the command line's entry point, as `python -m gateway run` is;
# at exit (SIGTERM stops it cleanly) the names of its modules, in the order imported.
# With a trace file, tracemalloc from the start and the top sites written on SIGUSR1.
RUN = """
import atexit, json, signal, sys
modules_file, trace_file, top, config = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
def dump():
    with open(modules_file, "w", encoding="utf-8") as out:
        json.dump(list(sys.modules), out)
atexit.register(dump)
if trace_file:
    import tracemalloc
    tracemalloc.start()
    def trace(signum, frame):
        stats = tracemalloc.take_snapshot().statistics("lineno")
        total = sum(s.size for s in stats)
        with open(trace_file, "w", encoding="utf-8") as out:
            out.write(f"traced: {total / 2**20:.1f} MiB in {len(stats)} sites\\n")
            for stat in stats[:top]:
                out.write(f"{stat.size / 1024:10.1f} KiB {stat.count:8} {stat.traceback}\\n")
    signal.signal(signal.SIGUSR1, trace)
sys.argv = ["gateway", "run", "--config", config, "--no-print"]
from gateway.cli import main
main()
"""

# The floor: the same modules, imported in the same order, nothing run.
FLOOR = """
import importlib, json, sys
from pathlib import Path
failed = []
for name in json.loads(Path(sys.argv[1]).read_text(encoding="utf-8")):
    if name in sys.modules or name == "__main__":
        continue
    try:
        importlib.import_module(name)
    except Exception as exc:
        failed.append(f"{name}: {exc!r}")
for line in Path("/proc/self/status").read_text(encoding="utf-8").splitlines():
    if line.startswith("VmRSS:"):
        print(json.dumps({"rss_mib": int(line.split()[1]) / 1024, "failed": failed}))
"""


def polled_points(config: Path) -> int:
    """The points the gateway polls for this config: periodic ones and those read on connect."""
    settings = load_config(config)
    return sum(
        len(device_target(device, bus).intervals)
        for bus in settings.buses
        for device in settings.devices_on(bus.name)
    )


async def import_floor(modules_file: Path) -> float:
    """RSS of a process that imports the modules in ``modules_file`` and stops."""
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-c", FLOOR, str(modules_file), stdout=asyncio.subprocess.PIPE
    )
    out, _ = await process.communicate()
    result = json.loads(out)
    if result["failed"]:
        print("floor: not imported:", *result["failed"], sep="\n  ", file=sys.stderr)
    return float(result["rss_mib"])


async def serving(port: int, timeout_s: float = 120.0) -> None:
    """Wait until /healthz answers: a traced gateway takes a while to import and start."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            await asyncio.to_thread(healthz, port)
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.5)
        else:
            return


async def one(
    broker: int, directory: Path, buses: int, devices: int, seconds: float, *, trace: int
) -> dict[str, float]:
    """One plant size: the gateway's RSS after a scrape, its peak, its floor, its points."""
    run_dir = directory / f"{buses}x{devices}"
    run_dir.mkdir()
    modules_file = run_dir / "modules.json"
    trace_file = RESULTS / f"memory-trace-{buses}x{devices}.txt" if trace else None
    async with simulators(run_dir, buses, devices) as (ports, _):
        config, metrics_port = gateway_config(run_dir, ports, devices, broker)
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-c",
            RUN,
            str(modules_file),
            str(trace_file or ""),
            str(trace),
            str(config),
            stdout=asyncio.subprocess.DEVNULL,
            stderr=(run_dir / "gateway.log").open("wb"),
        )
        try:
            await serving(metrics_port)
            await asyncio.sleep(WARM_UP_S)
            await settled(metrics_port)
            settled_rss = rss_mib(process.pid)
            await asyncio.sleep(seconds)
            before = rss_mib(process.pid)
            exposition = await asyncio.to_thread(scrape, metrics_port)
            rss = rss_mib(process.pid)
            peak = rss_mib(process.pid, "VmHWM")
            if trace_file is not None:
                process.send_signal(signal.SIGUSR1)
                await asyncio.sleep(5.0)  # the snapshot of a large heap takes a while
        finally:
            process.terminate()
            await process.wait()
    if not modules_file.exists():
        log = (run_dir / "gateway.log").read_text(encoding="utf-8")
        raise RuntimeError(f"the gateway left no list of modules:\n{log[-3000:]}")
    floor = await import_floor(modules_file)
    return {
        "buses": buses,
        "devices": buses * devices,
        "polled_points": polled_points(config),
        "exposition_bytes": exposition,
        "import_floor_mib": floor,
        "rss_backlog_sent_mib": settled_rss,
        "rss_before_scrape_mib": before,
        "rss_after_scrape_mib": rss,
        "peak_rss_mib": peak,
        "rss_above_floor_mib": rss - floor,
    }


def verdict(sizes: list[dict[str, float]]) -> dict[str, object]:
    """Bytes per polled point between the smallest and the largest size; the targets met."""
    small, large = sizes[0], sizes[-1]
    points = large["polled_points"] - small["polled_points"]
    per_point = (
        (large["rss_after_scrape_mib"] - small["rss_after_scrape_mib"]) * MIB / points
        if points
        else float("nan")
    )
    return {
        "bytes_per_polled_point": per_point,
        "per_point_target_bytes": BYTES_PER_POINT,
        "per_point_met": per_point <= BYTES_PER_POINT,
        "floor_allowance_mib": FLOOR_ALLOWANCE_MIB,
        "floor_met": large["rss_above_floor_mib"] <= FLOOR_ALLOWANCE_MIB,
    }


def reference_line(directory: Path) -> tuple[Path, list[str]]:
    """The peers' simulated line on a clean phase, in ``directory``: its port and command."""
    directory.mkdir()
    port, frames, line = directory / "tty", directory / "line.json", directory / "line.yaml"
    line.write_text(
        json.dumps(peers.simulator_config(REFERENCE_LINE, peers.PHASES[0])), encoding="utf-8"
    )
    simulate = [sys.executable, "-m", "bench.peer_line", "--config", str(line)]
    return port, [*simulate, "--pty", str(port), "--out", str(frames)]


async def reference_run(broker: int, directory: Path, seconds: float) -> dict[str, float]:
    """One plain `gateway run` of the peers' plant on a clean line: its RSS and peak."""
    port, simulate = reference_line(directory)
    log = directory / "gateway.log"
    async with peers.child(simulate, log=directory / "line.log", ready=b"ready"):
        argv = peers.GATEWAY.command(port, REFERENCE_LINE, broker, directory)
        async with peers.child(argv, log=log) as process:
            await asyncio.sleep(peers.WARM_UP_S + seconds)
            if process.returncode is not None:
                raise RuntimeError(f"the gateway stopped:\n{log.read_text(encoding='utf-8')}")
            return {
                "rss_mib": rss_mib(process.pid),
                "peak_rss_mib": rss_mib(process.pid, "VmHWM"),
            }


async def reference(runs: int, seconds: float) -> dict[str, object]:
    """``runs`` plain runs of the reference plant, one after the other on one broker."""
    compileall.compile_dir(GATEWAY_SOURCE, quiet=1)  # as installed: no module from source
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        async with peers.mosquitto(directory) as broker:
            for index in range(runs):
                result = await reference_run(broker, directory / f"run-{index}", seconds)
                print(
                    f"run {index + 1}: RSS {result['rss_mib']:.1f} MiB, "
                    f"peak {result['peak_rss_mib']:.1f}",
                    flush=True,
                )
                results.append(result)
    median = statistics.median(r["rss_mib"] for r in results)
    return {
        "runs": results,
        "seconds": seconds,
        "median_rss_mib": median,
        "target_mib": REFERENCE_TARGET_MIB,
        "met": median <= REFERENCE_TARGET_MIB,
    }


async def main_async(args: argparse.Namespace) -> dict[str, object]:
    sizes = [tuple(int(n) for n in size.split("x")) for size in args.sizes.split(",")]
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        with mosquitto(directory) as broker:
            for buses, devices in sizes:
                results.append(
                    await one(broker, directory, buses, devices, args.seconds, trace=args.trace)
                )
    return {"sizes": results, "targets": verdict(results), "traced": bool(args.trace)}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", default="4x16,16x16", help="BUSESxDEVICES, smallest first")
    parser.add_argument(
        "--seconds", type=float, help="after the warm-up (default 10; 30 with --reference)"
    )
    parser.add_argument("--trace", type=int, default=0, help="top allocation sites to write")
    parser.add_argument(
        "--reference", type=int, default=0, metavar="N", help="N plain runs of the reference plant"
    )
    args = parser.parse_args()
    os.environ.setdefault("COLUMNS", "200")
    RESULTS.mkdir(exist_ok=True)
    if args.reference:
        plain = asyncio.run(reference(args.reference, args.seconds or 30.0))
        (RESULTS / "memory-reference.json").write_text(json.dumps(plain, indent=2), "utf-8")
        print(f"median RSS {plain['median_rss_mib']:.1f} MiB (target <= {REFERENCE_TARGET_MIB:g})")
        return
    args.seconds = args.seconds or 10.0
    result = asyncio.run(main_async(args))
    (RESULTS / "memory.json").write_text(json.dumps(result, indent=2), encoding="utf-8")
    if result["traced"]:
        print("traced run: RSS includes tracemalloc's own; see bench/results/memory-trace-*")
    for size in result["sizes"]:  # type: ignore[attr-defined]
        print(f"{size['buses']} buses, {size['devices']} devices")
        for key, value in size.items():
            if key not in {"buses", "devices"}:
                print(f"  {key:<28} {value:,.1f}")
    print("targets")
    for key, value in result["targets"].items():  # type: ignore[attr-defined]
        print(f"  {key:<28} {value:,.1f}" if isinstance(value, float) else f"  {key:<28} {value}")


if __name__ == "__main__":
    main()
