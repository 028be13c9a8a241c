"""The shared bus under load: other masters hammer reads while the gateway polls its sensors.

Five simulated sensors (S10, H10, H20, tecLine Cl2, Reiss M0c) on one line at 9600 8E1, in
a simulator process that referees the timing of everything on its line, polled at 1 s by
``gateway run`` as its own process with the shared bus on (Modbus TCP on localhost, the
default share of a quarter of the bus). Three clients in this process send reads back to
back (each waits for its answer, then asks again), spread over the five sensors, for
``--seconds``. Printed:

- polling deadlines missed (goal 0) and the simulator's timing violations (goal 0);
- the clients' requests: answered by the device, exception 06 (no bus time), others; the
  latency of answered requests, p50 and p99, as the clients measured it on the socket;
- bus time: the share of the line the gateway's polls and the other masters took, against
  their share; the line's utilisation: the share of the wall time it carried a transaction.

With ``--flood unknown`` (or ``cache``) one client instead pipelines requests as fast as
TCP takes them, for ``--seconds``: reads of a unit id no device has (each refused with
exception 0A by the gateway itself), or reads the cache answers (the client granted a
``cache_max_age``). Printed: the polls' lateness (the deadlines missed, and the gateway's
warnings of a poll over an interval late, with the latest such lateness), what the client
sent and got, and what the gateway shed and held back. ``--rate-limit`` sets the
gateway's ``shared_bus.rate_limit`` (10000 leaves the yield per answer alone at work).

Written to bench/results/shared_bus.json (shared_bus_flood_KIND.json with ``--flood``).
Run from the repository root:
.venv/bin/python -m bench.shared_bus [--seconds 60] [--clients 3]
    [--flood unknown|cache [--rate-limit N]]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import re
import socket
import struct
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from bench.soak import scrape, total
from tests.flood_client import flood

if TYPE_CHECKING:
    from collections.abc import Iterator

RESULTS = Path(__file__).parent / "results"
CLIENTS = 3  # as the figure asks; --clients more to see exception 06 at work
# (unit, first register, count): each sensor's measured values, as a SCADA would read them.
READS = (
    (1, 0x2600, 2),  # S10: oxygen
    (2, 0x2001, 4),  # H10: oxygen, temperature
    (3, 0x2001, 4),  # H20
    (20, 0x0000, 6),  # tecLine Cl2: concentration, cell current, temperature
    (10, 0x0000, 6),  # Reiss M0c
)
SIMULATOR = """\
line: {baudrate: 9600, parity: E, stopbits: 1}
pace: true
seed: 1
devices:
  - {profile: jumo-digiline-odo-s10, address: 1}
  - {profile: jumo-digiline-odo-h10, address: 2}
  - {profile: jumo-digiline-odo-h20, address: 3}
  - {profile: jumo-tecline-cl2, address: 20}
  - {profile: reiss-m0c, address: 10}
"""


FLOODS = {  # what a flooding client asks: (unit, PDU)
    "unknown": (99, bytes.fromhex("0300000002")),  # a unit no device has: 0A
    "cache": (20, bytes.fromhex("0300000006")),  # the tecLine's values, fresh in the cache
}
CACHE_CLIENT = "  clients: [{name: scada, networks: [127.0.0.0/8], cache_max_age: 5.0}]\n"


def gateway_config(port: Path, metrics: int, shared: int, state: Path, *, clients: str = "") -> str:
    """Five sensors polled at 1 s, MQTT off, Prometheus and the shared bus on localhost."""
    devices = "".join(
        f"  - {{name: {name}, bus: line, address: {address}, profile: {profile}}}\n"
        for name, address, profile in (
            ("s10", 1, "jumo-digiline-odo-s10"),
            ("h10", 2, "jumo-digiline-odo-h10"),
            ("h20", 3, "jumo-digiline-odo-h20"),
            ("cl2", 20, "jumo-tecline-cl2"),
            ("m0c", 10, "reiss-m0c"),
        )
    )
    return (
        f"buses: [{{name: line, port: {port}, baudrate: 9600, parity: E}}]\n"
        f"devices:\n{devices}"
        "mqtt: {enabled: false}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics}}}\n"
        f"shared_bus:\n  listen: [{{host: 127.0.0.1, port: {shared}}}]\n{clients}"
        f"state_dir: {state}\n"
        "logging: {level: WARNING}\n"
    )


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@dataclass
class ClientFigures:
    latencies_s: list[float] = field(default_factory=list)  # answered by the device
    busy: int = 0  # exception 06
    other: dict[str, int] = field(default_factory=dict)


async def hammer(port: int, first: int, until: float, figures: ClientFigures) -> None:
    """Read back to back, the next request once the answer is in."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    transaction = 0
    try:
        while time.monotonic() < until:
            unit, address, count = READS[(first + transaction) % len(READS)]
            transaction = (transaction + 1) & 0xFFFF
            pdu = struct.pack(">BHH", 3, address, count)
            request = struct.pack(">HHHB", transaction, 0, len(pdu) + 1, unit) + pdu
            sent = time.monotonic()
            writer.write(request)
            head = await reader.readexactly(6)
            body = await reader.readexactly(int.from_bytes(head[4:6], "big"))
            if body[1] == 3:  # noqa: PLR2004 - the read's own function: the device answered
                figures.latencies_s.append(time.monotonic() - sent)
            elif body[2] == 6:  # noqa: PLR2004 - exception 06, device busy
                figures.busy += 1
            else:
                code = f"{body[2]:02X}"
                figures.other[code] = figures.other.get(code, 0) + 1
    finally:
        writer.close()


@contextlib.contextmanager
def processes(work: Path, metrics: int, shared: int, *, clients: str = "") -> Iterator[Path]:
    """The simulator and the gateway, each its own process; yields the simulator's stats."""
    pty, stats = work / "ttySIM", work / "stats.json"
    (work / "sim.yaml").write_text(SIMULATOR, encoding="utf-8")
    (work / "gateway.yaml").write_text(
        gateway_config(pty, metrics, shared, work / "state", clients=clients), encoding="utf-8"
    )
    simulate = [sys.executable, "-m", "gateway", "simulate", "--config", str(work / "sim.yaml")]
    with subprocess.Popen(  # noqa: S603 - the gateway's own command line
        [*simulate, "--pty", str(pty), "--stats", str(stats)], stdout=subprocess.PIPE, text=True
    ) as simulator:
        assert simulator.stdout is not None
        simulator.stdout.readline()  # "simulating ...": the pty is there
        with subprocess.Popen(  # noqa: S603 - the gateway's own command line
            [sys.executable, "-m", "gateway", "run", "--config", str(work / "gateway.yaml")],
            stderr=(work / "gateway.log").open("w"),
        ) as gateway:
            try:
                yield stats
            finally:
                gateway.terminate()
                gateway.wait(timeout=15)
                simulator.terminate()
                simulator.wait(timeout=15)


def wait_healthy(metrics: int, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError, urllib.error.URLError):
            url = f"http://127.0.0.1:{metrics}/healthz"
            with urllib.request.urlopen(url, timeout=2) as answer:
                if json.loads(answer.read())["status"] == "ok":
                    return
        time.sleep(0.2)
    raise SystemExit("the gateway did not become healthy")


def percentile_ms(values: list[float], fraction: float) -> float:
    ordered = sorted(values)
    return 1000 * ordered[min(len(ordered) - 1, int(fraction * len(ordered)))] if ordered else 0.0


async def measure(seconds: float, clients: int = CLIENTS) -> dict[str, Any]:
    metrics, shared = free_port(), free_port()
    with (
        tempfile.TemporaryDirectory() as directory,
        processes(Path(directory), metrics, shared) as stats,
    ):
        wait_healthy(metrics)
        await asyncio.sleep(5.0)  # identity and the first slow reads are through
        before, started = scrape(metrics), time.monotonic()
        figures = [ClientFigures() for _ in range(clients)]
        until = started + seconds
        await asyncio.gather(*(hammer(shared, n * 2, until, figures[n]) for n in range(clients)))
        after, elapsed = scrape(metrics), time.monotonic() - started
        await asyncio.sleep(0.4)  # the simulator writes its stats every 250 ms
        simulated = json.loads(stats.read_text(encoding="utf-8"))

    def delta(name: str) -> float:
        return total(after, name) - total(before, name)

    latencies = [s for f in figures for s in f.latencies_s]
    foreign_s = delta("gateway_shared_bus_busy_seconds_total")
    polling_s = delta("gateway_bus_busy_seconds_total") - foreign_s
    other: dict[str, int] = {}
    for f in figures:
        for code, count in f.other.items():
            other[code] = other.get(code, 0) + count
    return {
        "seconds": round(elapsed, 1),
        "clients": clients,
        "deadlines_missed": int(delta("gateway_missed_deadlines_total")),
        "timing_violations": len(simulated.get("violations", [])),
        "requests_answered": len(latencies),
        "requests_busy_06": sum(f.busy for f in figures),
        "requests_other_exceptions": other,
        "latency_p50_ms": round(percentile_ms(latencies, 0.5), 1),
        "latency_p99_ms": round(percentile_ms(latencies, 0.99), 1),
        "bus_share_polling": round(polling_s / elapsed, 3),
        "bus_share_foreign": round(foreign_s / elapsed, 3),
        "bus_share_allowed": total(after, "gateway_shared_bus_share"),
        "line_utilisation": round((polling_s + foreign_s) / elapsed, 3),
    }


@dataclass
class FloodFigures:
    sent: int = 0  # requests the kernel took
    answers: dict[str, int] = field(default_factory=dict)  # by function or exception


def flood_client(port: int, kind: str, seconds: float, figures: FloodFigures) -> None:
    """Pipeline one request over and over for ``seconds``; tally the answers meanwhile.

    The load tests' client (``tests.flood_client``): blocking sockets in threads of their
    own, so the flood does not wait on this process's event loop (the one that scrapes).
    """
    unit, pdu = FLOODS[kind]
    with contextlib.redirect_stdout(io.StringIO()):  # its "connected" line is for tests
        result = flood(port, unit, pdu, seconds)
    figures.sent = int(cast("int", result["sent"]))
    answers = cast("dict[str, int]", result["answers"])
    figures.answers = {key: n for key, n in answers.items() if key != "eof"}


async def measure_flood(seconds: float, kind: str, rate_limit: float | None) -> dict[str, Any]:
    metrics, shared = free_port(), free_port()
    clients = CACHE_CLIENT if kind == "cache" else ""
    if rate_limit is not None:
        clients += f"  rate_limit: {rate_limit}\n"
    with tempfile.TemporaryDirectory() as directory:
        work = Path(directory)
        with processes(work, metrics, shared, clients=clients):
            wait_healthy(metrics)
            await asyncio.sleep(5.0)  # identity and the first slow reads are through
            before = scrape(metrics)
            figures = FloodFigures()
            await asyncio.to_thread(flood_client, shared, kind, seconds, figures)
            await asyncio.sleep(1.5)  # a poll after the flood shows how late the last was
            after = scrape(metrics)
        log = (work / "gateway.log").read_text(encoding="utf-8")

    def delta(name: str) -> float:
        return total(after, name) - total(before, name)

    late = [line for line in log.splitlines() if " late (interval " in line]
    lags = [float(m[1]) for line in late if (m := re.search(r" is ([\d.]+) s late", line))]
    return {
        "seconds": seconds,
        "flood": kind,
        "rate_limit": rate_limit if rate_limit is not None else "default",
        "requests_sent": figures.sent,
        "answers": figures.answers,
        "deadlines_missed": int(delta("gateway_missed_deadlines_total")),
        "late_warnings": len(late),  # a device's first poll over an interval late
        "latest_poll_late_s": max(lags, default=0.0),
        "first_late_warning": late[0].split(": ", 1)[-1] if late else "",
        "shed": int(delta("gateway_shared_bus_shed_total")),
        "throttled_s": round(delta("gateway_shared_bus_throttled_seconds_total"), 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--clients", type=int, default=CLIENTS)
    parser.add_argument("--flood", choices=sorted(FLOODS), default=None)
    parser.add_argument("--rate-limit", type=float, default=None, help="shared_bus.rate_limit")
    args = parser.parse_args()
    if args.flood is None:
        figures = asyncio.run(measure(args.seconds, args.clients))
        name = "shared_bus.json"
    else:
        figures = asyncio.run(measure_flood(args.seconds, args.flood, args.rate_limit))
        name = f"shared_bus_flood_{args.flood}.json"
    for key, value in figures.items():
        print(f"{key:28} {value}")
    RESULTS.mkdir(exist_ok=True)
    figures["date"] = datetime.now(UTC).isoformat(timespec="seconds")
    (RESULTS / name).write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
