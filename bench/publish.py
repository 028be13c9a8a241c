"""What the publishing side costs: MQTT and Prometheus throughput, latency, memory at scale.

1. Sink throughput: synthetic poll cycles of 256 devices (16 buses x 16 devices, 6 values
   each) through the MQTT sink to a local mosquitto until every message is acknowledged, and
   the time a Prometheus scrape takes to build its families from the latest samples.
2. Latency: the same plant polled by `gateway run` as its own process; a subscriber in this
   one takes the time each state document arrives minus the time of the poll cycle it
   describes (its first answer: the cycle's own bus time is in it), and minus the moment
   the bus task handed the decoded cycle over (noted by a wrapper around the sink's
   publish): what the publish path and the broker add.
3. Memory: 16 buses x 16 devices, each bus a simulated line on its own pseudo-terminal (the
   simulators in one process apart), polled at 1 s with MQTT and Prometheus on by `gateway run`
   as its own process, as a user runs it; that process's resident memory after the run (the
   harness's own, with part 1's queue and the subscriber, is not in it), and what
   `import gateway.app` alone takes.

Printed, and written to bench/results/publish.json.
Run from the repository root:
.venv/bin/python -m bench.publish [--seconds 20] [--buses 16] [--devices 16]
[--parts throughput,plant,memory] [--poll-phase 0]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import getpass
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import aiomqtt
from prometheus_client import CollectorRegistry, generate_latest

from bench.soak import process_figures
from gateway.config import MqttConfig
from gateway.line.samples import Quality, Sample
from gateway.profiles import get_profile
from gateway.publish.mqtt import MqttSink
from gateway.publish.prometheus import GatewayCollector
from gateway.shared.state import DeviceInfo, GatewayState, StateSink
from tests.mqtt_broker import free_port

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Iterator, Sequence

RESULTS = Path(__file__).parent / "results"
MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
WARM_BACKLOG = 50  # messages still queued when the latency measurement starts, at most
POINTS = ("oxygen", "temperature", "status", "concentration", "cell_current", "pressure")


@contextlib.contextmanager
def mosquitto(directory: Path) -> Iterator[int]:
    port = free_port()
    config = directory / "mosquitto.conf"
    config.write_text(
        f"user {getpass.getuser()}\nlistener {port} 127.0.0.1\nallow_anonymous true\n"
        "max_queued_messages 10000000\nmax_inflight_messages 1000\n",
        encoding="utf-8",
    )
    process = subprocess.Popen(  # noqa: S603 - our own broker configuration
        [MOSQUITTO, "-c", str(config)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    for _ in range(100):
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2):
            break
        time.sleep(0.05)
    try:
        yield port
    finally:
        process.terminate()
        process.wait(timeout=10)


def rss_mib(pid: int | str = "self", field: str = "VmRSS") -> float:
    """A process's resident memory (`VmRSS`) or its peak (`VmHWM`), from /proc."""
    for line in Path(f"/proc/{pid}/status").read_text(encoding="utf-8").splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024
    return float("nan")


IMPORT_ONLY = """
from pathlib import Path
import gateway.app
for line in Path("/proc/self/status").read_text(encoding="utf-8").splitlines():
    if line.startswith("VmRSS:"):
        print(int(line.split()[1]) / 1024)
"""


def percentile_ms(ordered: Sequence[float], fraction: float) -> float:
    return 1000 * ordered[int(fraction * (len(ordered) - 1))] if ordered else float("nan")


def synthetic_state(buses: int, devices: int) -> tuple[GatewayState, list[list[Sample]]]:
    """A state with every device registered, and one poll cycle of samples per device."""
    state = GatewayState()
    cycles = []
    now = time.monotonic()
    wall = datetime.now(tz=UTC)
    for b in range(buses):
        for d in range(devices):
            bus, device = f"bus{b}", f"dev{b}_{d}"
            state.add_device(
                DeviceInfo(
                    bus=bus,
                    name=device,
                    profile="jumo-digiline-odo-s10",
                    address=d + 1,
                    intervals=dict.fromkeys(POINTS, 1.0),
                )
            )
            cycle = [
                Sample(
                    bus=bus,
                    device=device,
                    profile="jumo-digiline-odo-s10",
                    point=p,
                    value=20.0 + i,
                    fault=None,
                    unit="°C",
                    quality=Quality.GOOD,
                    monotonic=now,
                    time=wall,
                    group="process",
                )
                for i, p in enumerate(POINTS)
            ]
            cycles.append(cycle)
    return state, cycles


async def sink_throughput(
    port: int, directory: Path, buses: int, devices: int, rounds: int
) -> dict[str, float]:
    state, cycles = synthetic_state(buses, devices)
    settings = MqttConfig(host="127.0.0.1", port=port, base_topic="bench", queue_max=10_000_000)
    sink = MqttSink(settings, state, state_dir=directory / "state")
    recorder = StateSink(state)
    task = asyncio.create_task(sink.run())
    while not state.mqtt.connected:  # noqa: ASYNC110 - the sink's task sets it
        await asyncio.sleep(0.01)
    start = time.perf_counter()
    for _ in range(rounds):
        for cycle in cycles:
            await recorder.publish(cycle)
            await sink.publish(cycle)
    queued = time.perf_counter() - start
    total = rounds * len(cycles) * (len(POINTS) + 1)
    while state.mqtt.published < total:  # noqa: ASYNC110 - the sink's task counts
        await asyncio.sleep(0.01)
    acked = time.perf_counter() - start
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    samples = rounds * len(cycles) * len(POINTS)
    registry = CollectorRegistry()
    registry.register(GatewayCollector(state))
    generate_latest(registry)  # the first scrape builds the naming tables once
    scrape_start = time.perf_counter()
    exposition = generate_latest(registry)
    scrape = time.perf_counter() - scrape_start
    return {
        "samples": samples,
        "mqtt_messages": total,
        "mqtt_samples_per_s_handed_over": samples / queued,
        "mqtt_samples_per_s_acknowledged": samples / acked,
        "prometheus_values_in_scrape": len(state.latest),
        "prometheus_scrape_ms": 1000 * scrape,
        "prometheus_exposition_bytes": len(exposition),
    }


SIMULATORS = """
import asyncio, sys
from pathlib import Path
from gateway.simulator import SimulatorServer, build_bus, parse_settings
PROFILES = ["jumo-digiline-odo-s10", "jumo-tecline-cl2", "reiss-m0c", "jumo-digiline-odo-h10"]
async def main(directory, buses, devices):
    servers = []
    for b in range(buses):
        devs = [{"profile": PROFILES[d % len(PROFILES)], "address": d + 1} for d in range(devices)]
        settings = parse_settings({"line": {"baudrate": 115200}, "devices": devs})
        server = SimulatorServer(build_bus(settings))
        server.open_pty(Path(directory) / f"ttyBUS{b}")
        servers.append(server)
    print("ready", flush=True)
    await asyncio.Event().wait()
asyncio.run(main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3])))
"""


@contextlib.asynccontextmanager
async def simulators(
    directory: Path, buses: int, devices: int
) -> AsyncIterator[tuple[list[Path], int]]:
    """All simulated buses in one process apart from the gateway; their ports and its pid."""
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        SIMULATORS,
        str(directory),
        str(buses),
        str(devices),
        stdout=asyncio.subprocess.PIPE,
    )
    assert process.stdout is not None
    await process.stdout.readline()
    try:
        yield [directory / f"ttyBUS{b}" for b in range(buses)], process.pid
    finally:
        process.terminate()
        await process.wait()


def plant_config(
    ports: list[Path], devices: int, broker: int, directory: Path, metrics_port: int = 0
) -> str:
    profiles = ["jumo-digiline-odo-s10", "jumo-tecline-cl2", "reiss-m0c", "jumo-digiline-odo-h10"]
    lines = ["buses:"]
    lines += [f"  - {{name: bus{b}, port: {p}, baudrate: 115200}}" for b, p in enumerate(ports)]
    lines.append("devices:")
    for b in range(len(ports)):
        for d in range(devices):
            lines.append(
                f"  - {{name: dev{b}_{d}, bus: bus{b}, address: {d + 1}, "
                f"profile: {profiles[d % len(profiles)]}, poll_interval: 1.0}}"
            )
    lines.append(f"mqtt: {{host: 127.0.0.1, port: {broker}, base_topic: bench}}")
    lines.append(f"prometheus: {{host: 127.0.0.1, port: {metrics_port or free_port()}}}")
    lines.append(f"state_dir: {directory / 'plant-state'}")
    return "\n".join(lines) + "\n"


def gateway_config(
    directory: Path, ports: list[Path], devices: int, broker: int
) -> tuple[Path, int]:
    """The plant's config for `gateway run` in ``directory``; its path and metrics port."""
    directory.mkdir(parents=True, exist_ok=True)
    metrics_port = free_port()
    config = directory / "gateway.yaml"
    config.write_text(
        plant_config(ports, devices, broker, directory, metrics_port), encoding="utf-8"
    )
    return config, metrics_port


TIMED_GATEWAY = """
import atexit, json, sys, time
from gateway.publish.mqtt import MqttSink
handed = []
hand_over = MqttSink.publish
async def timed(sink, samples):
    # When the bus task hands a decoded cycle over, keyed by the document's seq.
    if samples:
        device = samples[0].device
        handed.append((device, sink.topics.documents.sent(device) + 1, time.time()))
    await hand_over(sink, samples)
MqttSink.publish = timed
handed_file, config = sys.argv[1], sys.argv[2]
def dump():
    with open(handed_file, "w", encoding="utf-8") as out:
        json.dump(handed, out)
atexit.register(dump)
sys.argv = ["gateway", "run", "--config", config, "--no-print"]
from gateway.cli import main
main()
"""


async def plant(
    broker: int,
    directory: Path,
    buses: int,
    devices: int,
    seconds: float,
    *,
    poll_phase: float | None = None,
) -> dict[str, float]:
    """Poll to subscriber: `gateway run` as its own process, the subscriber in this one.

    The gateway notes when each cycle is handed over to MQTT (a wrapper around the
    sink's publish, written out at exit); the subscriber notes when each state document
    arrives. Both on the wall clock, one machine. ``poll_phase`` gives every device that
    phase (0: all due at once, as before phases were spread); None: the gateway's spread.
    The busiest 150 ms counts the cycles handed over in it: how bunched they reach MQTT.
    """
    arrivals: list[tuple[str, int, float, float]] = []  # device, seq, arrived, cycle time
    measuring = False

    async def subscribe() -> None:
        async with aiomqtt.Client("127.0.0.1", broker) as client:
            await client.subscribe("bench/+/state", qos=1)
            async for message in client.messages:
                payload = message.payload
                if measuring and isinstance(payload, bytes):
                    arrived = time.time()
                    document = json.loads(payload)
                    cycle = datetime.fromisoformat(document["time"]).timestamp()
                    device = message.topic.value.split("/")[1]
                    arrivals.append((device, document["seq"], arrived, cycle))

    handed_file, log = directory / "handed.json", directory / "plant.log"
    async with simulators(directory, buses, devices) as (ports, _):
        config, metrics_port = gateway_config(directory / "plant", ports, devices, broker)
        if poll_phase is not None:
            text = config.read_text(encoding="utf-8")
            phased = f"poll_interval: 1.0, poll_phase: {poll_phase}}}"
            config.write_text(text.replace("poll_interval: 1.0}", phased), encoding="utf-8")
        listener = asyncio.create_task(subscribe())
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-c",
            TIMED_GATEWAY,
            str(handed_file),
            str(config),
            stdout=asyncio.subprocess.DEVNULL,
            stderr=log.open("wb"),
        )
        try:
            await asyncio.sleep(5.0)  # identity reads, warm-up
            # ... and the backlog they leave (every point read at once) sent, so that the
            # latency measured is the steady state's.
            await settled(metrics_port)
            measuring = True
            cpu0 = process_figures(process.pid)[1]
            await asyncio.sleep(seconds)
            cpu = process_figures(process.pid)[1] - cpu0
            measuring = False
        finally:
            process.terminate()
            await process.wait()
            listener.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await listener
    if not handed_file.exists():
        raise RuntimeError(f"the gateway left no hand-over times:\n{log.read_text()[-3000:]}")
    handed = {(d, seq): at for d, seq, at in json.loads(handed_file.read_text(encoding="utf-8"))}
    latencies = sorted(arrived - cycle for _, _, arrived, cycle in arrivals)
    decoded = sorted(
        arrived - handed[d, seq] for d, seq, arrived, _ in arrivals if (d, seq) in handed
    )
    handovers = sorted(handed[d, seq] for d, seq, _, _ in arrivals if (d, seq) in handed)
    # From the cycle's first answer to its hand-over: the rest of the cycle's requests on
    # the line, and its decoding. What the first-answer latency holds besides publishing.
    in_cycle = sorted(handed[d, seq] - cycle for d, seq, _, cycle in arrivals if (d, seq) in handed)
    busiest, first = 0, 0
    for last, at in enumerate(handovers):
        while at - handovers[first] >= 0.150:  # noqa: PLR2004 - the window of the issue
            first += 1
        busiest = max(busiest, last - first + 1)
    return {
        "buses": buses,
        "devices": buses * devices,
        "state_documents_per_s": len(latencies) / seconds,
        "latency_p50_ms": percentile_ms(latencies, 0.5),
        "latency_p99_ms": percentile_ms(latencies, 0.99),
        "decoded_latency_p50_ms": percentile_ms(decoded, 0.5),
        "decoded_latency_p99_ms": percentile_ms(decoded, 0.99),
        "cycle_on_line_p50_ms": percentile_ms(in_cycle, 0.5),
        "cycle_on_line_p99_ms": percentile_ms(in_cycle, 0.99),
        "gateway_cpu_share": cpu / seconds,
        "busiest_150ms_cycles": busiest,
    }


async def settled(port: int) -> None:
    """Wait (30 s at most) until the gateway's MQTT queue is down to the warm backlog.

    Read from ``/healthz``: a scrape of ``/metrics`` at 16 x 16 is some 6 MB, and
    scraping it in a loop slowed the very drain it waited for.
    """
    settle_until = time.monotonic() + 30
    while time.monotonic() < settle_until:
        health = await asyncio.to_thread(healthz, port)
        if health["mqtt"]["queue_depth"] <= WARM_BACKLOG:
            return
        await asyncio.sleep(0.2)


def scrape(port: int) -> int:
    """One scrape of the gateway's /metrics; the size of the exposition in bytes."""
    url = f"http://127.0.0.1:{port}/metrics"
    with urllib.request.urlopen(url, timeout=30) as response:
        return len(response.read())


def healthz(port: int) -> dict[str, Any]:
    """The gateway's /healthz document (it answers 503 while unhealthy, with the same body)."""
    url = f"http://127.0.0.1:{port}/healthz"
    try:
        with urllib.request.urlopen(url, timeout=5) as response:
            return dict(json.load(response))
    except urllib.error.HTTPError as unhealthy:
        return dict(json.load(unhealthy))


async def memory(
    broker: int, directory: Path, buses: int, devices: int, seconds: float
) -> dict[str, float]:
    """`gateway run` as its own process, as a user runs it: its resident memory alone."""
    importer = await asyncio.create_subprocess_exec(
        sys.executable, "-c", IMPORT_ONLY, stdout=asyncio.subprocess.PIPE
    )
    imported, _ = await importer.communicate()
    async with simulators(directory, buses, devices) as (ports, _):
        config, metrics_port = gateway_config(directory / "memory", ports, devices, broker)
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "gateway",
            "run",
            "--config",
            str(config),
            "--no-print",
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.DEVNULL,
        )
        try:
            await asyncio.sleep(5.0)  # identity reads, warm-up
            await settled(metrics_port)
            await asyncio.sleep(seconds)
            # One scrape, as Prometheus makes every 15 s or so: its peak is in the figures.
            await asyncio.to_thread(scrape, metrics_port)
            rss = rss_mib(process.pid)
            peak = rss_mib(process.pid, "VmHWM")
        finally:
            process.terminate()
            await process.wait()
    return {
        "gateway_rss_mib": rss,
        "gateway_peak_rss_mib": peak,
        "import_gateway_app_rss_mib": float(imported.strip()),
    }


async def main_async(args: argparse.Namespace) -> dict[str, object]:
    parts = set(args.parts.split(","))
    result: dict[str, object] = {}
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        with mosquitto(directory) as broker:
            if "throughput" in parts:
                result["throughput"] = await sink_throughput(
                    broker, directory, args.buses, args.devices, args.rounds
                )
            if "plant" in parts:
                result["plant"] = await plant(
                    broker,
                    directory,
                    args.buses,
                    args.devices,
                    args.seconds,
                    poll_phase=args.poll_phase,
                )
            if "memory" in parts:
                result["memory"] = await memory(
                    broker, directory, args.buses, args.devices, args.seconds
                )
    result["profile_checked"] = get_profile("reiss-m0c").id
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--buses", type=int, default=16)
    parser.add_argument("--devices", type=int, default=16)
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument(
        "--parts", default="throughput,plant,memory", help="which parts (default: %(default)s)"
    )
    parser.add_argument(
        "--poll-phase",
        type=float,
        default=None,
        help="the latency part's poll_phase for every device (0: all due at once); "
        "default: the gateway's spread",
    )
    args = parser.parse_args()
    os.environ.setdefault("COLUMNS", "200")
    result = asyncio.run(main_async(args))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "publish.json").write_text(json.dumps(result, indent=2), encoding="utf-8")
    for section in ("throughput", "plant", "memory"):
        if section not in result:
            continue
        print(section)
        for key, value in result[section].items():  # type: ignore[attr-defined]
            print(
                f"  {key:<36} {value:,.2f}" if isinstance(value, float) else f"  {key:<36} {value}"
            )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
