"""Fleet: how the broker's and the gateways' CPU grow from 1 to 16 gateways on one machine.

For each fleet size, ``gateway demo --fleet N`` as a user starts it (issue 39): N gateways,
each a ``gateway run`` process of its own with the single demo's six simulated sensors on a
line of its own (19200 8E1, every device at 1 s), its own ``/metrics``, web page and shared
bus, all into one local mosquitto (started afresh for each size; the demo takes the broker
that answers on its port). The simulated sensors run in the demo's own process, apart from
the gateways. Once every gateway's ``/healthz`` says ``ok`` and a warm-up has passed, the
CPU time (user + system, from ``/proc/PID/stat``, with any children they have) of each
process is read at both ends of a window of --seconds. Printed per size, and written to
bench/results/fleet.json:

- the broker's CPU: percent of one core, and seconds per minute;
- the gateways': all together, per gateway (the mean) and the busiest one;
- the simulated sensors' (the demo's own process: N lines, 6N sensors);
- MQTT messages the gateways had acknowledged per second, and the poll deadlines they
  missed in the window (``/metrics``, read at both ends: a CPU figure of gateways that fall
  behind would flatter them);
- each gateway's resident memory, the mean.

Run from the repository root: .venv/bin/python -m bench.fleet [--seconds 60]
[--sizes 1,2,4,8,16] [--warm-up 15]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import re
import signal
import socket
import sys
import tempfile
import time
import urllib.request
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from bench.publish import mosquitto, rss_mib
from bench.soak import scrape
from tests.mqtt_broker import free_port

if TYPE_CHECKING:
    from collections.abc import Iterable

RESULTS = Path(__file__).parent / "results"
START_S = 120.0  # the slowest start seen: 16 interpreters importing on 2 cores, with margin
STOP_S = 60.0
TICKS = os.sysconf("SC_CLK_TCK")
ROW = re.compile(r"^cabinet-\d+\s+(\d+)\s+http://\S+:(\d+)/metrics", re.MULTILINE)


def own_cpu_s(pid: int) -> float:
    """CPU seconds (user + system, every thread) of one process, from /proc; 0 once gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text(encoding="ascii").rsplit(")", 1)[1]
    except OSError:
        return 0.0
    utime, stime = fields.split()[11:13]  # fields 14 and 15 of proc(5)
    return (int(utime) + int(stime)) / TICKS


def cpu_s(pid: int) -> float:
    """CPU seconds of a process and of its live descendants."""
    return sum(own_cpu_s(each) for each in (pid, *descendants(pid)))


def descendants(pid: int) -> list[int]:
    """Every live process below ``pid``."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                parent = int(
                    (entry / "stat").read_text(encoding="ascii").rsplit(")", 1)[1].split()[1]
                )
                children.setdefault(parent, []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        below = children.get(todo.pop(), [])
        found += below
        todo += below
    return found


def child_named(name: str) -> int:
    """The pid of this process's child running ``name`` (the broker bench.publish started)."""
    for pid in descendants(os.getpid()):
        with contextlib.suppress(OSError):
            if Path(f"/proc/{pid}/comm").read_text(encoding="ascii").strip() == name:
                return pid
    raise LookupError(f"no child process {name!r}")


def free_block(count: int, taken: Iterable[int] = ()) -> int:
    """The first of ``count`` consecutive ports on 127.0.0.1, free a moment ago."""
    avoid = set(taken)
    while True:
        first = free_port()
        block = range(first, first + count)
        if avoid & set(block):
            continue
        try:
            for port in block:
                with socket.socket() as probe:
                    probe.bind(("127.0.0.1", port))
        except OSError:
            continue
        return first


def healthy(port: int) -> bool:
    """Whether a gateway's ``/healthz`` says ``ok``."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=5) as answer:
            return bool(json.loads(answer.read())["status"] == "ok")
    except (OSError, ValueError, KeyError):
        return False


def counter(port: int, name: str) -> float:
    """A counter of a gateway's ``/metrics``, summed over its labels."""
    return sum(value for (family, _), value in scrape(port).items() if family == name)


async def one(size: int, seconds: float, warm_up_s: float, directory: Path) -> Figures:
    """Run a fleet of ``size`` against a fresh mosquitto; its figures over the window."""
    run_dir = directory / f"fleet-{size}"
    run_dir.mkdir()
    with mosquitto(run_dir) as broker_port:
        broker = child_named("mosquitto")
        metrics_port = free_block(size, [broker_port])
        web_port = free_block(size, [broker_port, *range(metrics_port, metrics_port + size)])
        taken = [broker_port, *range(metrics_port, metrics_port + size)]
        modbus_port = free_block(size, [*taken, *range(web_port, web_port + size)])
        demo = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "gateway",
            "demo",
            "--fleet",
            str(size),
            "--no-live",
            "--mqtt-port",
            str(broker_port),
            "--metrics-port",
            str(metrics_port),
            "--web-port",
            str(web_port),
            "--modbus-port",
            str(modbus_port),
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT,
        )
        try:
            return await _measure(demo, broker, size, seconds, warm_up_s)
        finally:
            if demo.returncode is None:
                demo.send_signal(signal.SIGINT)
            await asyncio.wait_for(demo.communicate(), timeout=STOP_S)


@dataclass(frozen=True, slots=True)
class Figures:
    """One fleet size's figures over the window; CPU as shares of one core."""

    gateways: int
    sensors: int
    window_s: float
    broker_cpu_share: float
    gateways_cpu_share: float  # all of them together
    per_gateway_cpu_share: float  # the mean
    busiest_gateway_cpu_share: float
    sensors_cpu_share: float  # the demo's own process: every cabinet's simulated line
    mqtt_messages_per_s: float  # acknowledged by the broker, all gateways
    missed_deadlines: int
    missed_by_gateway: list[int]  # one busy moment of the machine, or one cabinet
    bus_errors: int  # failed transactions (timeouts, CRC, ...), all gateways
    gateway_rss_mib: float  # the mean, at the end of the window


async def _measure(
    demo: asyncio.subprocess.Process, broker: int, size: int, seconds: float, warm_up_s: float
) -> Figures:
    assert demo.stdout is not None
    table = ""
    async with asyncio.timeout(START_S):
        while "Ctrl-C" not in table:
            line = await demo.stdout.readline()
            if not line:
                raise RuntimeError(f"the fleet ended before its table:\n{table}")
            table += line.decode()
        gateways = [(int(pid), int(port)) for pid, port in ROW.findall(table)]
        assert len(gateways) == size, table
        # Polled: the gateways are other processes, with no event of theirs to wait on.
        while not all(await asyncio.gather(*(asyncio.to_thread(healthy, p) for _, p in gateways))):  # noqa: ASYNC110
            await asyncio.sleep(1.0)
    # The demo's further output (warnings of the gateways) is drained, not left to fill a pipe.
    drain = asyncio.create_task(demo.stdout.read())
    await asyncio.sleep(warm_up_s)
    before = _Reading.take(demo.pid, broker, gateways)
    await asyncio.sleep(seconds)
    after = _Reading.take(demo.pid, broker, gateways)
    rss = [rss_mib(pid) for pid, _ in gateways]
    drain.cancel()
    wall = after.wall_s - before.wall_s
    each = [(b - a) / wall for a, b in zip(before.gateways_s, after.gateways_s, strict=True)]
    missed = [int(b - a) for a, b in zip(before.missed, after.missed, strict=True)]
    return Figures(
        gateways=size,
        sensors=6 * size,
        window_s=round(wall, 1),
        broker_cpu_share=(after.broker_s - before.broker_s) / wall,
        gateways_cpu_share=sum(each),
        per_gateway_cpu_share=sum(each) / size,
        busiest_gateway_cpu_share=max(each),
        sensors_cpu_share=(after.sensors_s - before.sensors_s) / wall,
        mqtt_messages_per_s=(after.published - before.published) / wall,
        missed_deadlines=sum(missed),
        missed_by_gateway=missed,
        bus_errors=int(after.errors - before.errors),
        gateway_rss_mib=sum(rss) / size,
    )


@dataclass(frozen=True, slots=True)
class _Reading:
    """CPU seconds and counters at one moment, at either end of the window."""

    wall_s: float
    broker_s: float
    sensors_s: float
    gateways_s: list[float]
    published: float
    missed: list[float]
    errors: float

    @classmethod
    def take(cls, demo: int, broker: int, gateways: list[tuple[int, int]]) -> _Reading:
        return cls(
            wall_s=time.monotonic(),
            broker_s=cpu_s(broker),
            # The demo's own process is the simulated sensors (and the relay of the
            # gateways' output): the gateways below it are counted apart.
            sensors_s=own_cpu_s(demo),
            gateways_s=[cpu_s(pid) for pid, _ in gateways],
            published=sum(counter(port, "gateway_mqtt_published_total") for _, port in gateways),
            missed=[counter(port, "gateway_missed_deadlines_total") for _, port in gateways],
            errors=sum(counter(port, "gateway_errors_total") for _, port in gateways),
        )


async def main_async(sizes: list[int], seconds: float, warm_up_s: float) -> list[Figures]:
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in sizes:
            results.append(await one(size, seconds, warm_up_s, Path(tmp)))
            print(json.dumps(asdict(results[-1])), flush=True)
    return results


def per_minute(share: float) -> str:
    """A share of one core as CPU seconds a minute."""
    return f"{60 * share:.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=60.0, help="the measured window")
    parser.add_argument("--sizes", default="1,2,4,8,16", help="fleet sizes, in gateways")
    parser.add_argument("--warm-up", type=float, default=15.0, help="seconds after all are up")
    args = parser.parse_args()
    sizes = [int(size) for size in args.sizes.split(",")]
    results = asyncio.run(main_async(sizes, args.seconds, args.warm_up))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "fleet.json").write_text(
        json.dumps([asdict(r) for r in results], indent=2), encoding="utf-8"
    )
    print(
        f"{'gateways':>8} {'broker':>7} {'s/min':>6} {'gateways':>8} {'s/min':>6} "
        f"{'each':>6} {'s/min':>6} {'busiest':>7} {'sensors':>7} {'msg/s':>6} {'missed':>6} "
        f"{'errors':>6} {'RSS MiB':>7}"
    )
    for r in results:
        print(
            f"{r.gateways:>8} {r.broker_cpu_share:>7.1%} {per_minute(r.broker_cpu_share):>6} "
            f"{r.gateways_cpu_share:>8.1%} {per_minute(r.gateways_cpu_share):>6} "
            f"{r.per_gateway_cpu_share:>6.1%} {per_minute(r.per_gateway_cpu_share):>6} "
            f"{r.busiest_gateway_cpu_share:>7.1%} {r.sensors_cpu_share:>7.1%} "
            f"{r.mqtt_messages_per_s:>6.0f} {r.missed_deadlines:>6} {r.bus_errors:>6} "
            f"{r.gateway_rss_mib:>7.1f}"
        )


if __name__ == "__main__":
    main()
