"""A Pi-class budget: the gateway under a CPU quota of a quarter of one core.

``gateway run --config`` runs as its own process inside a control group of its own with a
CPU quota (``--quota``, 25 % of one core by default: 25 ms of every 100 ms, as
``systemd-run -p CPUQuota=25%`` or cgroup v2's ``cpu.max`` "25000 100000" set it; see
bench/cgroups.py). The simulated lines (one process apart), the broker and this bench's
subscriber stay outside the quota. Two plants by default (``--plants``), every device
polled at 1 s:

- **reference**: the soak's three lines (9600 8E1, 19200 8N1, 38400 8E1) with all the
  families, 8 sensors: S10, H10, H20, tecLine Cl2, ClO2 and TC, Reiss M0c and M3c;
- **16x16**: 16 lines at 115200 8N1 with 16 sensors each (S10, tecLine Cl2, Reiss M0c and
  H10 in turn), the plant of bench/publish.py and bench/scale.py; any other
  ``BUSESxDEVICES`` (``4x16``) is the same at another size.

The simulators pace every frame (it takes its wire time) and referee the master's timing.
After the start (identity reads, the first read of every point and the messages it leaves
queued; the quota slows that too), for ``--seconds``, with a scrape of ``/metrics`` every
``--scrape-every`` seconds (15 s, as a Prometheus might; 0: only before and after):

- deadlines missed, from the gateway's ``gateway_missed_deadlines_total`` (and the worst
  ``gateway_poll_lag_seconds`` seen), in the window and since the start;
- timing violations, from the simulators' referees, in the window and since the start;
- the transactions that failed in the window, by kind (``gateway_errors_total``): a
  missed deadline after a timeout is a device held for its late-answer window, not a
  gateway short of CPU;
- the CPU the group used (share of one core, and of the quota) and the throttling:
  periods in which the quota ran out, and the time the gateway was held for it;
- latency p50 / p99 from the cycle's first answer (the state document's ``time``) to the
  subscriber, as bench/publish.py measures it;
- transactions a second, and the simulators' own CPU (they share this machine).

Target 5 of the engine-cost work: 0 deadlines missed and 0 violations for both plants.
Printed as a table and written to bench/results/budget.json. Creating the control group
needs root (or a delegated cgroup); the bench stops and says what it needs where it cannot.

Run from the repository root: .venv/bin/python -m bench.budget [--seconds 30]
[--quota 25] [--plants reference,16x16] [--scrape-every 15] [--profile FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import re
import signal
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

import aiomqtt

from bench import cgroups, peers
from bench.publish import healthz, mosquitto, percentile_ms, plant_config
from bench.soak import LINES, process_figures, total
from gateway.wire.timing import LineFormat
from tests.mqtt_broker import free_port

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable, Mapping

ROOT: Final = Path(__file__).resolve().parents[1]
RESULTS: Final = ROOT / "bench" / "results"
INTERVAL_S: Final = 1.0
BASE: Final = "bench"  # the topics of bench/publish.py's plant_config
WARM_UP_S: Final = 8.0  # identity reads and the first read of every point, at least
SETTLE_S: Final = 90.0  # at most, for the start's queued messages to be sent
SETTLED_QUEUE: Final = 50  # messages still queued when the window opens, at most
SCRAPE_EVERY_S: Final = 15.0  # as Prometheus does (its default is 1 min; ours 15 s)
STOP_S: Final = 20.0
PROFILES_16: Final = (
    "jumo-digiline-odo-s10",
    "jumo-tecline-cl2",
    "reiss-m0c",
    "jumo-digiline-odo-h10",
)

Figures = dict[str, Any]


# --- plants ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SimLine:
    """One simulated line: the bus name, its pseudo-terminal and the simulator's settings."""

    name: str
    pty: Path
    settings: dict[str, Any]


@dataclass(frozen=True, slots=True)
class Plant:
    """A plant to poll: its simulated lines and the gateway's config for them."""

    name: str
    title: str
    lines: Callable[[Path], list[SimLine]]
    config: Callable[[Path, list[SimLine], int, int], str]  # directory, lines, broker, metrics


def reference_lines(directory: Path) -> list[SimLine]:
    """The soak's three lines and eight sensors, paced, values held still."""
    return [
        SimLine(
            name=f"line_{line.name}",
            pty=directory / f"tty{line.name}",
            settings={
                "line": line.line,
                "pace": True,
                "seed": 1,
                "devices": [
                    {"profile": s.profile, "address": s.address, "animate": False}
                    for s in line.sensors
                ],
            },
        )
        for line in LINES
    ]


def reference_config(directory: Path, lines: list[SimLine], broker: int, metrics: int) -> str:
    """Every sensor at 1 s with the defaults otherwise: MQTT (QoS 1, state documents), metrics."""
    buses = "".join(
        f"  - {{name: {sim.name}, port: {sim.pty}, baudrate: {spec.line['baudrate']}, "
        f"parity: {spec.line['parity']}, stopbits: {spec.line['stopbits']}}}\n"
        for sim, spec in zip(lines, LINES, strict=True)
    )
    devices = "".join(
        f"  - {{name: {s.name}, bus: line_{spec.name}, address: {s.address}, "
        f"profile: {s.profile}, poll_interval: {INTERVAL_S}}}\n"
        for spec in LINES
        for s in spec.sensors
    )
    return (
        f"buses:\n{buses}devices:\n{devices}"
        f"mqtt: {{host: 127.0.0.1, port: {broker}, base_topic: {BASE}}}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics}}}\n"
        f"state_dir: {directory / 'state'}\n"
        "logging: {level: WARNING}\n"
    )


def grid_lines(buses: int, devices: int) -> Callable[[Path], list[SimLine]]:
    """``buses`` lines at 115200 8N1 with ``devices`` sensors each, paced."""

    def lines(directory: Path) -> list[SimLine]:
        return [
            SimLine(
                name=f"bus{b}",
                pty=directory / f"ttyBUS{b}",
                settings={
                    "line": {"baudrate": 115200},
                    "pace": True,
                    "seed": 1,
                    "devices": [
                        {"profile": PROFILES_16[d % len(PROFILES_16)], "address": d + 1}
                        for d in range(devices)
                    ],
                },
            )
            for b in range(buses)
        ]

    return lines


def grid_config(devices: int) -> Callable[[Path, list[SimLine], int, int], str]:
    """bench/publish.py's plant: every device at 1 s, MQTT and metrics on."""

    def config(directory: Path, lines: list[SimLine], broker: int, metrics: int) -> str:
        ports = [sim.pty for sim in lines]
        return plant_config(ports, devices, broker, directory, metrics) + (
            "logging: {level: WARNING}\n"
        )

    return config


REFERENCE: Final = Plant(
    "reference",
    "reference plant: 3 lines (9600, 19200, 38400), 8 sensors",
    reference_lines,
    reference_config,
)


def plant_named(name: str) -> Plant:
    """``reference``, or ``BUSESxDEVICES`` (``16x16``: bench/publish.py's plant)."""
    if name == REFERENCE.name:
        return REFERENCE
    buses, _, devices = name.partition("x")
    if not (buses.isdigit() and devices.isdigit() and int(buses) and int(devices)):
        raise SystemExit(f"--plants: {name!r} is neither 'reference' nor BUSESxDEVICES, e.g. 16x16")
    b, d = int(buses), int(devices)
    return Plant(name, f"{b} lines at 115200 x {d} sensors", grid_lines(b, d), grid_config(d))


# --- the simulators: one process outside the quota ---------------------------------------


async def serve(document: Mapping[str, Any]) -> None:
    """Serve every line of ``document`` until SIGTERM, then write each bus's stats to its out."""
    # Imported here: only the simulators' process needs them.
    from gateway.simulator import SimulatorServer, build_bus, parse_settings  # noqa: PLC0415

    servers = {}
    for line in document["lines"]:
        server = SimulatorServer(build_bus(parse_settings(line["settings"])))
        server.open_pty(Path(line["pty"]))
        servers[line["name"]] = server
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    print("ready", flush=True)
    await stop.wait()
    stats = {}
    for name, server in servers.items():
        await server.close()
        stats[name] = {"started": server.bus.started, **server.bus.stats()}
    out = Path(document["out"])
    temporary = out.with_suffix(".tmp")
    temporary.write_text(json.dumps(stats), encoding="utf-8")
    temporary.replace(out)


@contextlib.asynccontextmanager
async def simulators(lines: list[SimLine], directory: Path) -> AsyncIterator[tuple[int, Path]]:
    """The lines served by one process of their own; its PID and where its stats will be."""
    spec, out = directory / "lines.json", directory / "lines-stats.json"
    spec.write_text(
        json.dumps(
            {
                "out": str(out),
                "lines": [
                    {"name": s.name, "pty": str(s.pty), "settings": s.settings} for s in lines
                ],
            }
        ),
        encoding="utf-8",
    )
    with (directory / "lines.log").open("wb") as log:  # the settings' warnings (115200)
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "bench.budget",
            "--serve",
            str(spec),
            stdout=asyncio.subprocess.PIPE,
            stderr=log,
            cwd=ROOT,
        )
    assert process.stdout is not None
    try:
        first = await asyncio.wait_for(process.stdout.readline(), 60)
        if not first.startswith(b"ready"):
            raise RuntimeError("the simulators did not start")
        yield process.pid, out
    finally:
        await stop(process)


async def stop(process: asyncio.subprocess.Process) -> None:
    """SIGTERM, a bounded wait (a gateway of 256 devices takes a while), then SIGKILL."""
    await peers.stop(process, STOP_S)


def violations(stats: Mapping[str, Any], t0: float, t1: float) -> dict[str, Any]:
    """The referees' violations since the start, in the window, and unjudged frames."""
    in_window = run = unjudged = 0
    rules: dict[str, int] = {}
    for bus in stats.values():
        run += int(bus["timing_violations"])
        unjudged += int(bus["counters"].get("unjudged", 0))
        for violation in bus["violations"]:
            if t0 <= bus["started"] + violation["time"] <= t1:
                in_window += 1
                rules[violation["rule"]] = rules.get(violation["rule"], 0) + 1
    return {
        "violations": in_window,
        "violations_by_rule": rules,
        "violations_run": run,
        "unjudged_frames": unjudged,
    }


# --- the gateway in its group ------------------------------------------------------------


# `gateway run` under a profiler that counts CPU time (not the wall clock, which would
# give the event loop's idle waits in epoll most of it), on from SIGUSR1 to SIGUSR2: the
# bench sends them at the window's start and end, so the start's work is left out.
PROFILED_GATEWAY: Final = """
import cProfile, signal, sys, time
profiler, out = cProfile.Profile(time.process_time), sys.argv[1]
def toggle(signum, frame):
    if signum == signal.SIGUSR1:
        profiler.enable()
    else:
        profiler.disable()
        profiler.dump_stats(out)
signal.signal(signal.SIGUSR1, toggle)
signal.signal(signal.SIGUSR2, toggle)
sys.argv = ["gateway", *sys.argv[2:]]
from gateway.cli import main
main()
"""


def gateway_argv(config: Path, profile: Path | None) -> list[str]:
    """``gateway run`` as users run it; under cProfile (``profile``) to see where CPU goes."""
    if profile is not None:
        head = [sys.executable, "-c", PROFILED_GATEWAY, str(profile)]
    else:
        script = Path(sys.executable).parent / "gateway"
        head = [str(script)] if script.exists() else [sys.executable, "-m", "gateway"]
    return [*head, "run", "--config", str(config), "--no-print"]


@dataclass(slots=True)
class Documents:
    """State documents seen while measuring: (arrival, the cycle's first answer), wall clock."""

    measuring: bool = False
    arrivals: list[tuple[float, float]] = field(default_factory=list)


@contextlib.asynccontextmanager
async def subscriber(broker: int) -> AsyncIterator[Documents]:
    """State documents of every device, timed on arrival while ``measuring``."""
    documents = Documents()

    async def listen() -> None:
        async with aiomqtt.Client("127.0.0.1", broker) as client:
            await client.subscribe(f"{BASE}/+/state", qos=1)
            async for message in client.messages:
                if documents.measuring and isinstance(message.payload, bytes):
                    arrived = time.time()
                    cycle = datetime.fromisoformat(json.loads(message.payload)["time"])
                    documents.arrivals.append((arrived, cycle.timestamp()))

    task = asyncio.create_task(listen(), name="bench.budget.subscriber")
    try:
        yield documents
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def queue_depth(metrics: int) -> int | None:
    """Messages the gateway holds for MQTT (``/healthz``); None when it does not answer."""
    with contextlib.suppress(OSError, KeyError, ValueError):
        return int((await asyncio.to_thread(healthz, metrics))["mqtt"]["queue_depth"])
    return None


async def started(metrics: int, process: asyncio.subprocess.Process, log: Path) -> float:
    """Wait for the start's reads and queued messages; the seconds it took."""
    began = time.monotonic()
    await asyncio.sleep(WARM_UP_S)
    while time.monotonic() - began < SETTLE_S:
        if process.returncode is not None:
            raise RuntimeError(f"the gateway stopped:\n{_tail(log)}")
        depth = await queue_depth(metrics)
        if depth is not None and depth <= SETTLED_QUEUE:
            break
        await asyncio.sleep(0.5)
    return time.monotonic() - began


def _tail(log: Path) -> str:
    return log.read_text(encoding="utf-8", errors="replace")[-3000:]


Scrape = dict[tuple[str, tuple[tuple[str, str], ...]], float]


WANTED: Final = (
    "gateway_missed_deadlines_total",
    "gateway_requests_total",
    "gateway_poll_lag_",
    "gateway_errors_total",
)
SAMPLE: Final = re.compile(r"([a-z_:]+)(?:\{(.*)\})? (\S+)")


def scrape(port: int) -> Scrape:
    """The few series the bench reads from one scrape of ``/metrics``.

    The whole scrape is fetched, as Prometheus does, but only the lines wanted are parsed:
    at 16 x 16 the exposition is 6 MB, and parsing all of it (bench/soak.py's scrape) took
    this process a second of a core the simulators and the gateway need.
    """
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=30) as answer:
        text = answer.read().decode()
    metrics: Scrape = {}
    for line in text.splitlines():
        if line.startswith(WANTED) and (match := SAMPLE.fullmatch(line)) is not None:
            labels = tuple(sorted(re.findall(r'(\w+)="([^"]*)"', match[2] or "")))
            metrics[match[1], labels] = float(match[3])
    return metrics


def failed_by_kind(before: Scrape, after: Scrape) -> dict[str, int]:
    """The transactions that failed between two scrapes, by kind (none: left out)."""
    kinds = {
        dict(labels)["kind"]
        for name, labels in after
        if name == "gateway_errors_total" and "kind" in dict(labels)
    }
    failed = {
        kind: int(
            total(after, "gateway_errors_total", kind=kind)
            - total(before, "gateway_errors_total", kind=kind)
        )
        for kind in sorted(kinds)
    }
    return {kind: n for kind, n in failed.items() if n}


def worst_lag(metrics: Scrape) -> float:
    return max(
        (v for (name, _), v in metrics.items() if name == "gateway_poll_lag_seconds"),
        default=0.0,
    )


async def one_plant(
    plant: Plant,
    *,
    quota: float,
    seconds: float,
    broker: int,
    work: Path,
    profile: Path | None,
    scrape_every_s: float,
) -> Figures:
    """One plant under the quota: start, settle, measure, stop; the figures."""
    directory = work / plant.name
    directory.mkdir()
    lines = plant.lines(directory)
    metrics = free_port()
    config = directory / "gateway.yaml"
    config.write_text(plant.config(directory, lines, broker, metrics), encoding="utf-8")
    log = directory / "gateway.log"
    profile_file = profile.with_suffix(f".{plant.name}.prof") if profile else None
    async with contextlib.AsyncExitStack() as stack:
        sim_pid, stats_file = await stack.enter_async_context(simulators(lines, directory))
        documents = await stack.enter_async_context(subscriber(broker))
        group = stack.enter_context(
            cgroups.open_group(f"gateway-bench-budget-{plant.name}", quota=quota)
        )
        process = await asyncio.create_subprocess_exec(
            *group.enter_argv(gateway_argv(config, profile_file)),
            stdout=asyncio.subprocess.DEVNULL,
            stderr=stack.enter_context(log.open("wb")),
            cwd=ROOT,
        )
        stack.push_async_callback(stop, process)
        start_s = await started(metrics, process, log)
        depth0 = await queue_depth(metrics)
        before = await asyncio.to_thread(scrape, metrics)
        t0, wall0 = time.monotonic(), time.time()
        cpu0, throttle0 = group.usage_s(), group.throttling()
        sim0 = process_figures(sim_pid)[1]
        documents.measuring = True
        if profile_file is not None:
            process.send_signal(signal.SIGUSR1)
        lag = worst_lag(before)
        while (remaining := seconds - (time.monotonic() - t0)) > 0:
            await asyncio.sleep(min(scrape_every_s, remaining))
            if time.monotonic() - t0 < seconds:
                lag = max(lag, worst_lag(await asyncio.to_thread(scrape, metrics)))
        documents.measuring = False
        if profile_file is not None:
            process.send_signal(signal.SIGUSR2)
        # The window's figures before the last scrape: what it costs falls after them.
        t1 = time.monotonic()
        cpu1, throttle1 = group.usage_s(), group.throttling()
        sim1 = process_figures(sim_pid)[1]
        depth1 = await queue_depth(metrics)
        after = await asyncio.to_thread(scrape, metrics)
        lag = max(lag, worst_lag(after))
        rss = process_figures(process.pid)[0]
        if process.returncode is not None:
            raise RuntimeError(f"the gateway stopped:\n{_tail(log)}")
    window = t1 - t0
    stats = json.loads(stats_file.read_text(encoding="utf-8"))
    latencies = sorted(arrived - cycle for arrived, cycle in documents.arrivals)
    devices = sum(len(s.settings["devices"]) for s in lines)

    def delta(name: str) -> float:
        return total(after, name) - total(before, name)

    cpu = cpu1 - cpu0
    periods = throttle1.periods - throttle0.periods
    return {
        "plant": plant.name,
        "title": plant.title,
        "devices": devices,
        "lines": [str(LineFormat(**s.settings["line"])) for s in lines],
        "quota": quota,
        "scrape_every_s": scrape_every_s,
        "start_s": start_s,
        "window_s": window,
        "measured_from_wall": wall0,
        "transactions_per_s": delta("gateway_requests_total") / window,
        "deadlines_missed": int(delta("gateway_missed_deadlines_total")),
        "deadlines_missed_run": int(total(after, "gateway_missed_deadlines_total")),
        "worst_poll_lag_s": lag,
        "errors_by_kind": failed_by_kind(before, after),
        **violations(stats, t0, t1),
        "cpu_share": cpu / window,
        "cpu_share_of_quota": cpu / window / quota,
        "cpu_us_per_transaction": 1e6 * cpu / max(delta("gateway_requests_total"), 1),
        "periods": periods,
        "throttled_periods": throttle1.throttled - throttle0.throttled,
        "throttled_share": (throttle1.throttled - throttle0.throttled) / max(periods, 1),
        "throttled_s": throttle1.throttled_s - throttle0.throttled_s,
        "state_documents_per_s": len(latencies) / window,
        "mqtt_queue_at_start": depth0,
        "mqtt_queue_at_end": depth1,
        "latency_p50_ms": percentile_ms(latencies, 0.5),
        "latency_p99_ms": percentile_ms(latencies, 0.99),
        "gateway_rss_mib": rss,
        "simulators_cpu_share": (sim1 - sim0) / window,
        "met": int(delta("gateway_missed_deadlines_total")) == 0
        and violations(stats, t0, t1)["violations"] == 0,
    }


async def run_all(
    plants: list[Plant],
    *,
    quota: float,
    seconds: float,
    profile: Path | None,
    scrape_every_s: float,
) -> list[Figures]:
    """Each plant in turn, one broker for all; SIGTERM stops it all cleanly."""
    task = asyncio.current_task()
    assert task is not None
    asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, task.cancel)
    results = []
    with tempfile.TemporaryDirectory(prefix="bench-budget-") as tmp, mosquitto(Path(tmp)) as broker:
        for plant in plants:
            print(f"{plant.title}, quota {quota:.0%} of one core: {seconds:g} s", flush=True)
            results.append(
                await one_plant(
                    plant,
                    quota=quota,
                    seconds=seconds,
                    broker=broker,
                    work=Path(tmp),
                    profile=profile,
                    scrape_every_s=scrape_every_s,
                )
            )
    return results


# --- report ------------------------------------------------------------------------------


def _kinds(errors: dict[str, int]) -> str:
    return ", ".join(f"{n} {kind}" for kind, n in errors.items()) or "none"


def table(results: list[Figures]) -> str:
    """One row per plant, and the verdict on target 5."""
    header = (
        f"{'plant':<10} {'devices':>7} {'quota':>6} {'tx/s':>6} {'CPU':>6} {'of quota':>8} "
        f"{'throttled':>13} {'missed':>6} {'viol':>4} {'lag ms':>7} "
        f"{'p50 ms':>7} {'p99 ms':>7} {'RSS MiB':>7} {'sim CPU':>7}"
    )
    rows = [header]
    for r in results:
        throttled = f"{r['throttled_share']:.0%} {r['throttled_s']:.2f}s"
        rows.append(
            f"{r['plant']:<10} {r['devices']:>7} {r['quota']:>6.0%} "
            f"{r['transactions_per_s']:>6.0f} {r['cpu_share']:>6.1%} "
            f"{r['cpu_share_of_quota']:>8.0%} {throttled:>13} "
            f"{r['deadlines_missed']:>6} {r['violations']:>4} "
            f"{1000 * r['worst_poll_lag_s']:>7.1f} {r['latency_p50_ms']:>7.1f} "
            f"{r['latency_p99_ms']:>7.1f} {r['gateway_rss_mib']:>7.1f} "
            f"{r['simulators_cpu_share']:>7.0%}"
        )
    rows.append(
        "throttled: share of the quota's periods in which it ran out, and the time held; "
        "missed/viol in the window"
    )
    rows.extend(
        f"{r['plant']}: since the start {r['deadlines_missed_run']} missed, "
        f"{r['violations_run']} violations, {r['unjudged_frames']} frames unjudged "
        f"(in the window by rule: {r['violations_by_rule'] or 'none'}); "
        f"failed transactions in the window: {_kinds(r['errors_by_kind'])}; "
        f"start took {r['start_s']:.0f} s; MQTT queue {r['mqtt_queue_at_start']} at the "
        f"window's start, {r['mqtt_queue_at_end']} at its end; "
        f"{r['state_documents_per_s']:.0f} state documents/s"
        for r in results
    )
    met = all(r["met"] for r in results)
    names = ", ".join(r["plant"] for r in results)
    rows.append(
        f"target 5 (0 missed deadlines, 0 violations; {names}) at "
        f"{results[0]['quota']:.0%}: {'met' if met else 'not met'}"
    )
    return "\n".join(rows)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=30.0, help="measured per plant")
    parser.add_argument("--quota", type=float, default=25.0, help="percent of one core")
    parser.add_argument(
        "--plants",
        default="reference,16x16",
        help="reference and/or BUSESxDEVICES at 115200 (default: %(default)s)",
    )
    parser.add_argument(
        "--profile",
        type=Path,
        metavar="FILE",
        help="profile the gateway's CPU over the window (cProfile): FILE.PLANT.prof",
    )
    parser.add_argument(
        "--scrape-every",
        type=float,
        default=SCRAPE_EVERY_S,
        metavar="SECONDS",
        help="scrape /metrics this often while measuring; 0: only before and after",
    )
    parser.add_argument("--serve", type=Path, help=argparse.SUPPRESS)  # the simulators' process
    args = parser.parse_args()
    if args.serve is not None:
        asyncio.run(serve(json.loads(args.serve.read_text(encoding="utf-8"))))
        return
    plants = [plant_named(name) for name in args.plants.split(",")]
    try:
        with cgroups.open_group("gateway-bench-budget-probe", quota=args.quota / 100):
            pass
    except cgroups.CgroupError as missing:
        raise SystemExit(f"bench.budget: {missing}") from None
    try:
        results = asyncio.run(
            run_all(
                plants,
                quota=args.quota / 100,
                seconds=args.seconds,
                profile=args.profile,
                scrape_every_s=args.scrape_every or math.inf,
            )
        )
    except (asyncio.CancelledError, KeyboardInterrupt):
        raise SystemExit(
            "stopped: every process it started is stopped, no figures written"
        ) from None
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "budget.json").write_text(json.dumps(results, indent=2), encoding="utf-8")
    print(table(results))


if __name__ == "__main__":
    main()
