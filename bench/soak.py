"""Soak with faults: the gateway as a real process, held to the product's figures.

Three simulated lines (9600 8E1, 19200 8N1, 38400 8E1) with every sensor family, a real
mosquitto broker and ``gateway run`` as its own process, for ``--minutes`` (10 by default;
the CI runs one). Meanwhile the harness

- moves every sensor's temperature to a new value every 2 s, each device in its own range,
  so a value published for the wrong device or from a stale answer cannot pass unnoticed;
- keeps two compensation feeds busy (an S10 from a Reiss temperature on another line, an H10
  from an MQTT topic) and sends set commands (RAM, volatile, flash within and past its
  budget, and invalid ones);
- injects corrupted CRCs, dropped, late, noisy and misaddressed answers on every line, a
  sensor that goes silent, ports that disappear and come back, and two broker restarts.

It checks, from the simulators' own registers, write logs and referees and from a
subscriber that records everything: no wrong value published; no state document lost (each
carries a per-device ``seq``) and none duplicated beyond what QoS 1 allows at a broker
restart; zero timing violations; every injected fault counted in the metrics; every ok
command's bytes in the sensor's write log and no write without a command or a feed; the
recovery time after each fault; memory flat; a clean exit on SIGTERM; no asyncio exception
nobody retrieved in the gateway's log.

Printed as a table, written to bench/results/soak.json; exit status 1 if a check fails.
Run from the repository root: .venv/bin/python -m bench.soak [--minutes 10] [--seed 1]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import re
import signal
import struct
import sys
import tempfile
import time
import urllib.request
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import aiomqtt

from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.simulator.bus import FaultPlan
from tests.mqtt_broker import Broker, free_port, recording
from tests.unretrieved import reported_in

if TYPE_CHECKING:
    from tests.mqtt_broker import Recorder

RESULTS = Path(__file__).parent / "results"
BASE = "soak"
POLL_S = 0.5
VALUE_EVERY_S = 2.0
COMMAND_EVERY_S = 2.5
PRESSURE_TOPIC = "site/air_pressure"
QUIET_TAIL_S = 8.0  # faults stop this long before the end, so everything settles
FAULTS = FaultPlan(crc=0.01, drop=0.005, late=0.005, late_s=0.3, noise=0.005, wrong_address=0.003)
MAX_RECOVERY_S = 12.0
# Frames the referee may skip after its own loop was held up (3 ms or more), so that the
# violations check still covers 97 % of them. The count follows the machine, not the
# gateway: 2 and 2 in a quiet minute, 39 of 1,585 once in CI right after the timing tests,
# in an hour when the bare master's CPU per transaction was 1.5 times its usual.
MAX_UNJUDGED_SHARE = 0.03
MAX_UNJUDGED_FLOOR = 30  # ... or this many: the start and the end each hold it up briefly
VIOLATION_CONTEXT_S = 0.06  # frames shown either side of a timing violation
MAX_RSS_GROWTH_MIB = 8.0
OUTAGE_MARGIN_S = 5.0  # commands sent this long before a broker stop may be lost with it
MIN_SAMPLES = 4  # memory samples needed to judge growth
FLASH_BUDGET = 2  # the pool's flash_write_budget in the config below
CONTROL_BYTE = 0x25AF  # S10 compensation control byte, set by the feed
DRAIN_BATCH = 100  # gateway.publish.mqtt.outbox.BATCH: what a broker restart may send twice


@dataclass(frozen=True)
class Sensor:
    name: str
    profile: str
    address: int


@dataclass(frozen=True)
class LineSpec:
    name: str
    line: dict[str, Any]
    sensors: tuple[Sensor, ...]


LINES = (
    LineSpec(
        "a",
        {"baudrate": 9600, "parity": "E", "stopbits": 1},
        (
            Sensor("aeration", "jumo-digiline-odo-s10", 1),
            Sensor("digester", "jumo-digiline-odo-h10", 2),
            Sensor("pool", "jumo-tecline-cl2", 20),
        ),
    ),
    LineSpec(
        "b",
        {"baudrate": 19200, "parity": "N", "stopbits": 1},
        (
            Sensor("fermenter", "jumo-digiline-odo-h20", 3),
            Sensor("basin", "reiss-m0c", 10),
            Sensor("dioxide", "jumo-tecline-clo2", 80),
        ),
    ),
    LineSpec(
        "c",
        {"baudrate": 38400, "parity": "E", "stopbits": 1},
        (Sensor("outlet", "reiss-m3c", 30), Sensor("spa", "jumo-tecline-tc", 40)),
    ),
)
SENSORS = {s.name: s for line in LINES for s in line.sensors}
LINE_OF = {s.name: line for line in LINES for s in line.sensors}


def temperature(index: int, epoch: int) -> float:
    """Device ``index``'s temperature in ``epoch``: its own whole degrees, a 1/16 step.

    10 + 2 * index whole degrees tell the device; sixteenths are exact in float32.
    """
    return 10.0 + 2 * index + (epoch % 16) / 16


def cdab(value: float) -> tuple[int, int]:
    high, low = struct.unpack(">HH", struct.pack(">f", value))
    return low, high


# --- the plant ----------------------------------------------------------------------------


def gateway_config(directory: Path, broker: int, metrics: int) -> str:
    buses = "".join(
        f"  - {{name: line_{line.name}, port: {directory / f'tty{line.name}'}, "
        f"baudrate: {line.line['baudrate']}, parity: {line.line['parity']}, "
        f"stopbits: {line.line['stopbits']}, reconnect_max_s: 2}}\n"
        for line in LINES
    )
    devices = ""
    for line in LINES:
        for sensor in line.sensors:
            extra = (
                ", flash_writes: [x_span], flash_write_budget: 2" if sensor.name == "pool" else ""
            )
            devices += (
                f"  - {{name: {sensor.name}, bus: line_{line.name}, address: {sensor.address}, "
                f"profile: {sensor.profile}, poll_interval: {POLL_S}, offline_after: 3{extra}}}\n"
            )
    return (
        f"buses:\n{buses}devices:\n{devices}"
        "feeds:\n"
        "  - {device: aeration, point: compensation_temperature, interval: 10, deadband: 0.01,"
        " max_age: 30, source: {device: basin, point: temperature}}\n"
        "  - {device: digester, point: compensation_pressure, interval: 10, max_age: 30,"
        f" source: {{topic: {PRESSURE_TOPIC}}}}}\n"
        f"mqtt: {{host: 127.0.0.1, port: {broker}, base_topic: {BASE}, reconnect_max_s: 2}}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics}}}\n"
        f"state_dir: {directory / 'state'}\n"
        "logging: {level: WARNING}\n"
    )


def simulator(line: LineSpec, seed: int) -> SimulatorServer:
    devices = [{"profile": s.profile, "address": s.address, "animate": False} for s in line.sensors]
    settings = parse_settings({"line": line.line, "pace": True, "seed": seed, "devices": devices})
    return SimulatorServer(build_bus(settings))


@dataclass
class Command:
    """A set command the harness sent, and what came of it."""

    id: str
    device: str
    point: str
    value: float
    valid: bool  # the harness expects the gateway to accept it
    sent_at: float
    result: dict[str, Any] | None = None


@dataclass
class Soak:
    """The running soak: what was set, sent, injected and sampled."""

    directory: Path
    broker: Broker
    servers: dict[str, SimulatorServer]
    started: float = field(default_factory=time.monotonic)
    held: dict[str, set[float]] = field(default_factory=lambda: defaultdict(set))
    basin_values: set[float] = field(default_factory=set)
    pressures: set[float] = field(default_factory=set)
    commands: list[Command] = field(default_factory=list)
    events: list[tuple[str, str, float, float]] = field(default_factory=list)  # kind, what, t0, t1
    broker_restarts: int = 0
    rss: list[tuple[float, float]] = field(default_factory=list)
    cpu_s: float = 0.0
    unplugged: set[str] = field(default_factory=set)

    def now(self) -> float:
        return time.monotonic() - self.started


# --- what the harness does while the gateway runs -----------------------------------------


async def move_values(soak: Soak, stop: asyncio.Event) -> None:
    index = {name: i for i, name in enumerate(SENSORS)}
    epoch = 0
    while not stop.is_set():
        for name, sensor in SENSORS.items():
            value = temperature(index[name], epoch)
            soak.servers[LINE_OF[name].name].bus.devices[sensor.address].hold("temperature", value)
            soak.held[name].add(value)
            if name == "basin":
                soak.basin_values.add(value)
        epoch += 1
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), VALUE_EVERY_S)


async def send_commands(soak: Soak, seen: Recorder, stop: asyncio.Event) -> None:
    """RAM, volatile, flash (two allowed a day, the third refused) and invalid commands."""
    plan = [
        ("fermenter", "compensation_temperature", True),
        ("aeration", "compensation_salinity", True),
        ("pool", "x_span", True),
        ("basin", "temperature", False),  # read-only
        ("fermenter", "compensation_pressure", True),
    ]
    number = 0
    pressure = 950.0
    await seen.wait_for(f"{BASE}/status", "online", within_s=30)  # subscribed by then
    while not stop.is_set():
        with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
            async with aiomqtt.Client("127.0.0.1", soak.broker.port, identifier="soak-plant") as c:
                while not stop.is_set():
                    device, point, valid = plan[number % len(plan)]
                    value = {
                        "compensation_temperature": 20.0 + (number % 40) / 4,
                        "compensation_salinity": (number % 30) / 2,
                        "x_span": 50.0 + number,
                        "temperature": 1.0,
                        "compensation_pressure": 900.0 + number,
                    }[point]
                    command = Command(f"c{number}", device, point, value, valid, soak.now())
                    pressure = 950.0 + (number % 64) / 4
                    # Each id once, whatever fails after: a publish that failed when the
                    # broker went away (the pressure's, after the command's went) sent the
                    # same id again after the reconnection, and both got their results.
                    number += 1
                    payload = json.dumps({"value": value, "id": command.id})
                    await c.publish(f"{BASE}/{device}/{point}/set", payload, qos=1)
                    soak.commands.append(command)
                    await c.publish(PRESSURE_TOPIC, json.dumps({"value": pressure}), qos=1)
                    soak.pressures.add(pressure)
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(stop.wait(), COMMAND_EVERY_S)
        await asyncio.sleep(0.5)  # the broker is away: try again
    for command in soak.commands:
        results = [
            json.loads(p)
            for p in seen.on(f"{BASE}/{command.device}/{command.point}/set/result")
            if p and json.loads(p).get("id") == command.id
        ]
        command.result = results[0] if len(results) == 1 else {"results": len(results)}


async def inject(soak: Soak, seconds: float) -> None:
    """Probabilistic faults on every line, then the scheduled ones, then a quiet tail."""
    for server in soak.servers.values():
        for address in server.bus.devices:
            server.bus.faults[address] = FAULTS
    schedule = [
        (0.20, "silence", "spa", 6.0),
        (0.35, "unplug", "c", 5.0),
        (0.50, "broker", "", 4.0),
        (0.65, "unplug", "a", 3.0),
        (0.80, "broker", "", 3.0),
    ]
    faults_end = seconds - QUIET_TAIL_S
    for fraction, kind, what, duration in schedule:
        at = fraction * faults_end
        await asyncio.sleep(max(0.0, at - soak.now()))
        start = soak.now()
        if kind == "silence":
            sensor = SENSORS[what]
            bus = soak.servers[LINE_OF[what].name].bus
            bus.silence(sensor.address, duration, asyncio.get_running_loop().time())
            await asyncio.sleep(duration)
        elif kind == "unplug":
            soak.unplugged.add(what)
            soak.servers[what].unplug_pty()
            await asyncio.sleep(duration)
            soak.servers[what].replug_pty()
            soak.unplugged.discard(what)
        else:
            soak.broker.stop()
            await asyncio.sleep(duration)
            soak.broker.start()
            soak.broker_restarts += 1
        soak.events.append((kind, what, start, soak.now()))
    await asyncio.sleep(max(0.0, faults_end - soak.now()))
    for server in soak.servers.values():
        server.bus.faults.clear()


def process_figures(pid: int) -> tuple[float, float]:
    """Resident memory (MiB) and CPU seconds of a process, from /proc."""
    rss = 0.0
    for line in Path(f"/proc/{pid}/status").read_text(encoding="utf-8").splitlines():
        if line.startswith("VmRSS:"):
            rss = int(line.split()[1]) / 1024
    fields = Path(f"/proc/{pid}/stat").read_text(encoding="utf-8").rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return rss, (int(fields[11]) + int(fields[12])) / ticks


async def sample_process(soak: Soak, pid: int, stop: asyncio.Event) -> None:
    while not stop.is_set():
        with contextlib.suppress(OSError):
            rss, cpu = process_figures(pid)
            soak.rss.append((soak.now(), rss))
            soak.cpu_s = cpu
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), 2.0)


def scrape(port: int) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    metrics = {}
    for line in text.splitlines():
        match = re.fullmatch(r"([a-z_:]+)(?:\{(.*)\})? (\S+)", line)
        if match is None or line.startswith("#"):
            continue
        labels = tuple(sorted(re.findall(r'(\w+)="([^"]*)"', match[2] or "")))
        metrics[match[1], labels] = float(match[3])
    return metrics


def total(
    metrics: dict[tuple[str, tuple[tuple[str, str], ...]], float], name: str, **where: str
) -> float:
    return sum(
        value
        for (metric, labels), value in metrics.items()
        if metric == name and all((k, v) in labels for k, v in where.items())
    )


# --- the run ------------------------------------------------------------------------------


async def run_soak(seconds: float, seed: int, directory: Path) -> dict[str, Any]:
    broker_dir = directory / "broker"
    broker_dir.mkdir()
    broker = Broker(broker_dir)
    broker.start()
    servers = {line.name: simulator(line, seed) for line in LINES}
    for line in LINES:
        servers[line.name].open_pty(directory / f"tty{line.name}")
    soak = Soak(directory=directory, broker=broker, servers=servers)
    metrics_port = free_port()
    config = directory / "gateway.yaml"
    config.write_text(gateway_config(directory, broker.port, metrics_port), encoding="utf-8")
    log = (directory / "gateway.log").open("w", encoding="utf-8")
    stop = asyncio.Event()
    try:
        async with recording(broker.port, f"{BASE}/#", name="soak-recorder") as seen:
            gateway = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "gateway", "run", "--config", str(config), "--no-print",
                stdout=log, stderr=log,
            )  # fmt: skip
            tasks = [
                asyncio.create_task(move_values(soak, stop)),
                asyncio.create_task(send_commands(soak, seen, stop)),
                asyncio.create_task(sample_process(soak, gateway.pid, stop)),
            ]
            await inject(soak, seconds)
            await asyncio.sleep(max(0.0, seconds - soak.now()))
            metrics = await asyncio.to_thread(scrape, metrics_port)
            deadline = time.monotonic() + 20
            while total(metrics, "gateway_mqtt_queue_depth") and time.monotonic() < deadline:
                await asyncio.sleep(0.5)
                metrics = await asyncio.to_thread(scrape, metrics_port)
            stop.set()
            await asyncio.gather(*tasks)
            gateway.send_signal(signal.SIGTERM)
            exit_code = await asyncio.wait_for(gateway.wait(), timeout=20)
            await asyncio.sleep(0.5)  # the last messages reach the recorder
            return evaluate(soak, seen, metrics, exit_code, seconds)
    finally:
        log.close()
        for server in servers.values():
            await server.close()
        broker.stop()


Metrics = dict[tuple[str, tuple[tuple[str, str], ...]], float]


@dataclass
class Verdict:
    """Figures for the report and the checks that failed."""

    figures: dict[str, Any] = field(default_factory=dict)
    failures: list[str] = field(default_factory=list)

    def check(self, ok: bool, failure: str) -> None:  # noqa: FBT001 - reads as an assertion
        if not ok:
            self.failures.append(failure)


def evaluate(
    soak: Soak, seen: Recorder, metrics: Metrics, exit_code: int, seconds: float
) -> dict[str, Any]:
    verdict = Verdict()
    verdict.figures |= {
        "seconds": seconds,
        "lines": [f"{line.name}: {line.line}" for line in LINES],
        "devices": len(SENSORS),
    }
    check_values(soak, seen, verdict)
    check_documents(soak, seen, verdict)
    check_faults(soak, metrics, verdict)
    check_commands(soak, seen, verdict)
    check_feeds(soak, verdict)
    check_recovery(soak, seen, verdict)
    check_process(soak, exit_code, verdict)
    return verdict.figures | {"failures": verdict.failures}


def check_values(soak: Soak, seen: Recorder, verdict: Verdict) -> None:
    """Every published temperature is one its device really had."""
    wrong: list[str] = []
    published = 0
    for name in SENSORS:
        for payload in seen.on(f"{BASE}/{name}/temperature"):
            if payload:
                published += 1
                if float(payload) not in soak.held[name]:
                    wrong.append(f"{name}: {payload}")
    verdict.figures |= {"values_published": published, "wrong_values": len(wrong)}
    verdict.check(published > 0, "no value was published")
    verdict.check(not wrong, f"{len(wrong)} wrong values published: {wrong[:5]}")


def check_documents(soak: Soak, seen: Recorder, verdict: Verdict) -> None:
    """State documents: per-device sequence numbers without a gap, few duplicates."""
    lost: dict[str, int] = {}
    duplicated = documents = 0
    for name in SENSORS:
        sequence = [json.loads(p)["seq"] for p in seen.on(f"{BASE}/{name}/state")]
        documents += len(sequence)
        counts = Counter(sequence)
        duplicated += sum(n - 1 for n in counts.values())
        missing = set(range(1, max(sequence, default=0) + 1)) - set(counts)
        if missing or not sequence:
            lost[name] = len(missing)
    verdict.figures |= {
        "state_documents": documents,
        "lost_documents": sum(lost.values()),
        "duplicated_documents": duplicated,
    }
    verdict.check(not lost, f"state documents lost (or none at all): {lost}")
    verdict.check(
        duplicated <= DRAIN_BATCH * soak.broker_restarts,
        f"{duplicated} duplicated state documents (QoS 1 allows a batch per broker restart)",
    )


def check_faults(soak: Soak, metrics: Metrics, verdict: Verdict) -> None:
    """Zero timing violations; every injected fault shows in the gateway's metrics."""
    violations = sum(len(s.bus.violations) for s in soak.servers.values())
    injected: Counter[str] = Counter()
    transactions = collisions = unjudged = 0
    for server in soak.servers.values():
        injected.update(server.bus.injected)
        transactions += server.bus.counters.get("frames", 0)
        collisions += server.bus.counters.get("collisions", 0)
        unjudged += server.bus.counters.get("unjudged", 0)
    counted = {
        kind: total(metrics, "gateway_errors_total", kind=kind)
        for kind in ("timeout", "crc", "wrong_address", "stale_frame", "noise", "malformed")
    }
    counted["port_failures"] = total(metrics, "gateway_bus_port_failures_total")
    events = Counter(kind for kind, *_ in soak.events)
    verdict.figures |= {
        "transactions": transactions,
        "faults_injected": dict(injected)
        | {"unplug": events["unplug"], "broker": events["broker"]},
        "errors_counted": counted,
        "collisions_with_late_answers": collisions,
        "timing_violations": violations,
        "frames_not_judged": unjudged,
    }
    verdict.check(not violations, f"{violations} timing violations")
    # Frames that came in while the simulators' loop (this process) was held up are not
    # refereed: their arrival times are unknown. Too many, and the check above means little.
    verdict.check(
        unjudged <= max(MAX_UNJUDGED_SHARE * transactions, MAX_UNJUDGED_FLOOR),
        f"{unjudged} of {transactions} frames not judged: the harness held its simulators up",
    )
    for name, server in soak.servers.items():
        for violation in server.bus.violations:
            # With the frames around it: what the master did just before tells why.
            around = [
                f"{r.start:.4f} dev {r.device} fn {r.function} @{r.address:#06x} {r.outcome}"
                f"{'' if r.answer_at is None else f' answered {r.answer_at:.4f}'}"
                for r in server.bus.frame_log
                if abs(r.start - violation.time) < VIOLATION_CONTEXT_S
            ]
            print(f"violation on {name}: {json.dumps(violation.as_dict())}", file=sys.stderr)
            print("  " + "\n  ".join(around), file=sys.stderr)
    # A corrupted answer can fail as a CRC error, as malformed, or (a corrupted byte count
    # promises more bytes than come) as a timeout; a late one as a timeout and later a
    # stale frame: each kind is shown, and every fault must have failed something.
    failed = counted["timeout"] + counted["crc"] + counted["wrong_address"] + counted["malformed"]
    must_fail = injected["crc"] + injected["drop"] + injected["late"] + injected["wrong_address"]
    verdict.check(
        failed >= must_fail,
        f"{must_fail} answers corrupted, dropped, late or misaddressed; {failed} failures counted",
    )
    verdict.check(
        counted["port_failures"] >= events["unplug"],
        f"{events['unplug']} ports unplugged, {counted['port_failures']} port failures counted",
    )


def check_process(soak: Soak, exit_code: int, verdict: Verdict) -> None:
    """Memory flat, CPU per transaction, a clean exit, no unretrieved asyncio exception.

    The last is read from the gateway's log: an unplugged port used to leave one there.
    """
    rss = [r for _, r in soak.rss]
    half = len(rss) // 2
    growth = (max(rss[half:]) - min(rss[half // 2 : half])) if len(rss) >= MIN_SAMPLES else 0.0
    transactions = verdict.figures.get("transactions", 0)
    verdict.figures |= {
        "rss_mib_last": rss[-1] if rss else 0.0,
        "rss_growth_second_half_mib": growth,
        "gateway_cpu_s": soak.cpu_s,
        "cpu_us_per_transaction": 1e6 * soak.cpu_s / max(transactions, 1),
        "exit_code": exit_code,
    }
    verdict.check(growth <= MAX_RSS_GROWTH_MIB, f"memory grew by {growth:.1f} MiB")
    verdict.check(exit_code == 0, f"the gateway exited with {exit_code} on SIGTERM")
    unretrieved = reported_in((soak.directory / "gateway.log").read_text(encoding="utf-8"))
    verdict.figures["unretrieved_exceptions"] = len(unretrieved)
    verdict.check(not unretrieved, f"{len(unretrieved)} unretrieved asyncio exceptions logged")


def write_logs(soak: Soak) -> dict[str, list[tuple[int, tuple[int, ...]]]]:
    """What every sensor accepted: (register, words), in order."""
    logs = {}
    for name, sensor in SENSORS.items():
        device = soak.servers[LINE_OF[name].name].bus.devices[sensor.address]
        logs[name] = [(w.address, w.values) for w in device.write_log if w.exception is None]
    return logs


def in_broker_outage(soak: Soak, seen: Recorder, at: float) -> bool:
    """Whether a command sent at ``at`` may have been lost with a broker restart.

    The gateway's session is clean: a command in flight when the broker stops, or sent
    before the gateway has subscribed again, never reaches it (QoS 1 holds between a
    client and the broker, not for a client that is not connected).
    """
    for kind, _, start, end in soak.events:
        if kind != "broker":
            continue
        back = [
            m.at - soak.started
            for m in seen.messages
            if m.topic == f"{BASE}/status" and m.payload == "online" and m.at - soak.started >= end
        ]
        if start - OUTAGE_MARGIN_S <= at <= min(back, default=end + MAX_RECOVERY_S):
            return True
    return False


def check_commands(soak: Soak, seen: Recorder, verdict: Verdict) -> None:
    """One result per command; ok ones in the write log; the budget; no unasked write."""
    logs = write_logs(soak)
    ok = flash_ok = 0
    for command in soak.commands:
        result = command.result or {}
        status = result.get("status")
        if status is None:
            verdict.check(
                in_broker_outage(soak, seen, command.sent_at) and result.get("results", 0) == 0,
                f"command {command.id} ({command.device} {command.point}, sent"
                f" @{command.sent_at:.1f}s): {result.get('results', 0)} results",
            )
            continue
        ok += status == "ok"
        flash_ok += command.point == "x_span" and status == "ok"
        verdict.check(
            command.valid or status == "error",
            f"command {command.id} to read-only {command.point} was accepted",
        )
        if status == "ok" and result.get("written"):
            verdict.check(
                result.get("value") == command.value,
                f"command {command.id}: read back {result.get('value')}",
            )
            verdict.check(
                any(values == cdab(command.value) for _, values in logs[command.device]),
                f"command {command.id}: ok, but not in the write log",
            )
    verdict.figures |= {"commands": len(soak.commands), "commands_ok": ok}
    verdict.check(
        flash_ok <= FLASH_BUDGET,
        f"{flash_ok} flash writes accepted against a budget of {FLASH_BUDGET}",
    )
    commanded = {(c.device, cdab(c.value)) for c in soak.commands if c.valid}
    fed = {("aeration", cdab(v)) for v in soak.basin_values}
    fed |= {("digester", cdab(v)) for v in soak.pressures}
    for name, log in logs.items():
        for address, values in log:
            asked = (name, values) in commanded or (name, values) in fed
            control = name == "aeration" and address == CONTROL_BYTE  # the feed selects RAM
            verdict.check(asked or control, f"{name}: {address:#06x} {values} nobody asked for")


def check_feeds(soak: Soak, verdict: Verdict) -> None:
    """The S10 uses the basin's temperature from RAM; the H10 the pressure sent."""
    failures = verdict.failures
    aeration = soak.servers["a"].bus.devices[1]
    digester = soak.servers["a"].bus.devices[2]
    fed = aeration.get("compensation_temperature")
    if fed not in soak.basin_values:
        failures.append(f"the S10's fed temperature {fed} was never the basin's")
    control = aeration.get("compensation_control")
    if not getattr(control, "raw", 0) & 1:
        failures.append("the S10 does not use its RAM compensation temperature")
    if digester.get("compensation_pressure") not in soak.pressures:
        failures.append(
            f"the H10's fed pressure {digester.get('compensation_pressure')} was never sent"
        )


def check_recovery(soak: Soak, seen: Recorder, verdict: Verdict) -> None:
    """Each fault is over within MAX_RECOVERY_S of its end."""
    recovery = recovery_times(soak, seen)
    slow = {k: v for k, v in recovery.items() if v is None or v > MAX_RECOVERY_S}
    verdict.figures |= {
        "recovery_s": recovery,
        "worst_recovery_s": max((v for v in recovery.values() if v is not None), default=0.0),
    }
    verdict.check(not slow, f"slow or no recovery: {slow}")


def recovery_times(soak: Soak, seen: Recorder) -> dict[str, float | None]:
    """Seconds from the end of each fault to the first fresh message it had stopped."""
    result: dict[str, float | None] = {}
    for kind, what, _, end in soak.events:
        end_abs = soak.started + end
        if kind == "broker":
            topics = [f"{BASE}/{name}/state" for name in SENSORS]
        elif kind == "unplug":
            line = next(line for line in LINES if line.name == what)
            topics = [f"{BASE}/{sensor.name}/availability" for sensor in line.sensors]
        else:
            topics = [f"{BASE}/{what}/availability"]
        wanted = "online" if kind != "broker" else None
        arrivals = [
            m.at
            for m in seen.messages
            if m.topic in topics and m.at >= end_abs and (wanted is None or m.payload == wanted)
        ]
        result[f"{kind} {what}".strip() + f" @{end:.0f}s"] = (
            min(arrivals) - end_abs if arrivals else None
        )
    return result


def main() -> None:
    # The harness's own MQTT clients lose the broker on purpose: no tracebacks for that.
    logging.getLogger("mqtt").addHandler(logging.NullHandler())
    logging.getLogger("mqtt").propagate = False
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--keep", type=Path, help="keep the run's files (the gateway's log, its config) here"
    )
    args = parser.parse_args()
    seconds = args.minutes * 60
    if args.keep is not None:
        args.keep.mkdir(parents=True, exist_ok=False)
        result = asyncio.run(run_soak(seconds, args.seed, args.keep))
    else:
        with tempfile.TemporaryDirectory(prefix="soak-") as tmp:
            result = asyncio.run(run_soak(seconds, args.seed, Path(tmp)))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "soak.json").write_text(json.dumps(result, indent=2), encoding="utf-8")
    rows = [
        ("duration", f"{seconds:.0f} s, {result['devices']} devices on {len(LINES)} lines"),
        ("transactions", str(result["transactions"])),
        ("faults injected", json.dumps(result["faults_injected"])),
        ("errors counted", json.dumps(result["errors_counted"])),
        ("values published / wrong", f"{result['values_published']} / {result['wrong_values']}"),
        (
            "state documents / lost / duplicated",
            (
                f"{result['state_documents']} / {result['lost_documents']} / "
                f"{result['duplicated_documents']}"
            ),
        ),
        ("timing violations", str(result["timing_violations"])),
        ("frames not judged (simulators held up)", str(result["frames_not_judged"])),
        ("commands / ok", f"{result['commands']} / {result['commands_ok']}"),
        (
            "recovery, s",
            json.dumps(
                {k: None if v is None else round(v, 2) for k, v in result["recovery_s"].items()}
            ),
        ),
        (
            "gateway RSS last / growth in the second half, MiB",
            f"{result['rss_mib_last']:.1f} / {result['rss_growth_second_half_mib']:.1f}",
        ),
        ("collisions with late answers", str(result["collisions_with_late_answers"])),
        ("gateway CPU per transaction, µs", f"{result['cpu_us_per_transaction']:.0f}"),
    ]
    width = max(len(label) for label, _ in rows)
    for label, value in rows:
        print(f"{label:<{width}}  {value}")
    for failure in result["failures"]:
        print(f"FAILED: {failure}")
    print("soak: OK" if not result["failures"] else "soak: FAILED")
    sys.exit(1 if result["failures"] else 0)


if __name__ == "__main__":
    main()
