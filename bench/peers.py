"""Side by side with a peer: modbus2mqtt 0.73 and our gateway on the same simulated line.

Five sensors of three families (S10, H10, two tecLine, Reiss M0c) on one simulated line
(9600 8E1 by default; frames take their wire time, a referee judges every gap), every
process and status point asked for each second, values held still so that the truth of
each is known. Each master runs as its users run it (``gateway run --config``; the peer's
``modbus2mqtt`` command from a venv the bench makes, see ``bench/peer_modbus2mqtt.py``) and
publishes to one local mosquitto under its own prefix, which the bench subscribes to.

Two phases, each master in turn: a clean line, then one with 2 % of the answers corrupted
(one bit flipped) and 2 % dropped. With --at-once the two masters of a phase run at the
same time, each on a simulated line of its own, so that the machine's pace, which moves
twofold within a minute on a virtual machine, is the same for both. After a warm-up
(start-up reads are not measured), for --seconds:

- frames per cycle: the different requests one poll of every point takes (frame log);
- transactions/s: answered requests per second; values/s: the compared values published
  per second, against the ones asked (a master that drifts polls less often than asked);
- CPU µs per transaction and CPU % of one core: the master's own control group counts
  its CPU (every thread and child, to the nanosecond; see bench/cgroups.py), or where
  none can be made, each of its threads' schedstat; utime + stime from /proc (10 ms
  ticks) beside it; RSS: resident memory, its peak;
- the gap from the end of an answer to the next request (minimum and median), against
  the 3.5 characters the line requires, and the referee's timing violations;
- with faults: published values that differ from the truth, of all published;
- whether the gateway uses no more CPU than the peer (target 2 of the engine-cost work)
  while it stays ahead on transactions, values, gaps and wrong values under faults.

Printed as a table and written to bench/results/peers.json.

With --against REF there is no peer: this tree's gateway and commit REF's run in the same
plant at once, each on its own line and base topic, and CPU new / old is printed per phase
(nothing written): a step of a few per cent, which the machine's pace hides between runs.

With --poll-phase P every device of this tree's gateway has ``poll_phase: P`` (the manual's
poll phases; by default the gateway spreads them over the interval), and with --qos Q every
message it publishes has QoS Q (by default 1; the peer publishes its values at 0). With
--against the commit's gateway keeps the defaults, so ``--against HEAD --poll-phase 0``
measures what the spread costs, at once, and ``--against HEAD --qos 0`` what the PUBACKs do.

Run from the repository root (as root, for the control groups):
.venv/bin/python -m bench.peers [--seconds 30] [--format 9600-E-1] [--at-once] [--keep DIR]
    [--poll-phase P] [--qos Q]
.venv/bin/python -m bench.peers --against REF [--seconds 30] [--format 9600-E-1] [--poll-phase P]
    [--qos Q]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import getpass
import itertools
import json
import math
import os
import shutil
import signal
import socket
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final, Protocol

import aiomqtt

from bench import cgroups
from bench import peer_modbus2mqtt as peer
from bench.cgroups import process_tree
from bench.engine_pairs import earlier_gateway as extracted
from bench.peer_line import wire_figures
from gateway.profiles import PollGroup, get_profile
from gateway.wire.timing import LineFormat, Parity

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable, Iterator, Mapping, Sequence

    from bench.cgroups import CpuGroup
    from gateway.profiles import Point, Profile

ROOT: Final = Path(__file__).resolve().parents[1]
RESULTS: Final = ROOT / "bench" / "results"
INTERVAL_S: Final = 1.0
WARM_UP_S: Final = 12.0  # start-up reads (identity, configuration, diagnostics) take ~8 s at 9600
STOP_S: Final = 10.0  # a process that has not stopped by then is killed
GATEWAY_PREFIX: Final = "gw"
PARITIES: Final[dict[str, Parity]] = {"N": "N", "E": "E", "O": "O"}
# Unbuffered, so that a master's log is complete however it is stopped.
CHILD_ENV: Final = {**os.environ, "PYTHONUNBUFFERED": "1"}

Figures = dict[str, Any]


@dataclass(frozen=True, slots=True)
class Sensor:
    """One simulated sensor and the values it holds: the truth published values must meet."""

    name: str
    profile_id: str
    address: int
    values: Mapping[str, float]

    @property
    def profile(self) -> Profile:
        """The sensor's register map."""
        return get_profile(self.profile_id)

    def points(self) -> tuple[Point, ...]:
        """The points both masters read: every process and status point of the profile."""
        polled = self.profile.points_in(PollGroup.PROCESS, PollGroup.STATUS)
        return tuple(p for p in polled if not p.view)


# No value equals another device's, so one attributed to the wrong device or request
# cannot pass; the floats are exact in float32. The status words carry a flag that is no
# error (S10 bit 10 cap replacement recommended, H10 bit 15 new values, H10 measurement
# status bit 0 continuous measurement), so a word read from the wrong place shows.
PLANT: Final = (
    Sensor(
        "s10", "jumo-digiline-odo-s10", 1, {"oxygen": 8.25, "temperature": 21.5, "status": 1024}
    ),
    Sensor(
        "h10",
        "jumo-digiline-odo-h10",
        2,
        {
            "oxygen": 3.125,
            "temperature": 18.75,
            "error_register": 0,
            "measurement_status": 1,
            "status": 32768,
        },
    ),
    Sensor(
        "cl2",
        "jumo-tecline-cl2",
        20,
        {"concentration": 0.625, "cell_current": 137.5, "temperature": 24.25},
    ),
    Sensor(
        "clo2",
        "jumo-tecline-clo2",
        80,
        {"concentration": 0.375, "cell_current": 52.0, "temperature": 23.75},
    ),
    Sensor(
        "m0c", "reiss-m0c", 10, {"concentration": 1.125, "cell_current": 210.5, "temperature": 24.5}
    ),
)
POINTS: Final = sum(len(s.values) for s in PLANT)


@dataclass(frozen=True, slots=True)
class Phase:
    """What the line does to the answers: a probability per answer of each fault."""

    name: str
    title: str
    crc: float = 0.0
    drop: float = 0.0


PHASES: Final = (
    Phase("clean", "clean line"),
    Phase("faults", "2 % corrupted + 2 % dropped answers", crc=0.02, drop=0.02),
)


# --- configurations ----------------------------------------------------------------------


def check_plant() -> None:
    """Every point read has a truth, and nothing else has one: a changed profile shows."""
    for sensor in PLANT:
        names = {p.name for p in sensor.points()}
        if names != set(sensor.values):
            raise SystemExit(
                f"{sensor.name}: points {sorted(names)}, truths {sorted(sensor.values)}"
            )


def simulator_config(line: LineFormat, phase: Phase) -> dict[str, Any]:
    """The simulated line: values held still, the phase's faults on every sensor."""
    return {
        "line": {"baudrate": line.baudrate, "parity": line.parity, "stopbits": line.stopbits},
        "pace": True,
        "seed": 1,
        "devices": [
            {
                "profile": s.profile_id,
                "address": s.address,
                "animate": False,
                "values": dict(s.values),
                "faults": {"crc": phase.crc, "drop": phase.drop},
            }
            for s in PLANT
        ],
    }


def gateway_config(
    port: Path,
    line: LineFormat,
    broker: int,
    work: Path,
    *,
    prefix: str = GATEWAY_PREFIX,
    poll_phase: float | None = None,
    qos: int | None = None,
) -> dict[str, Any]:
    """Our gateway as a user sets it up for these sensors: defaults but the slow groups.

    Diagnostics and configuration are read at start only (intervals of a day), so that
    both masters read the same points while measured. Timeouts, retries, publishing
    (every poll, values at QoS 1, a state document per device) and the Prometheus
    endpoint are the defaults. ``prefix``: its base topic (and client id), one per gateway
    on the broker. ``poll_phase``: every device's (the manual's poll phases); None: the
    gateway's own spread, the default. ``qos``: of every message, values too (``mqtt.qos``
    and ``mqtt.value_qos``); None: the default, 1.
    """
    day = 86_400
    phase = {} if poll_phase is None else {"poll_phase": poll_phase}
    return {
        "buses": [
            {
                "name": "line",
                "port": str(port),
                "baudrate": line.baudrate,
                "parity": line.parity,
                "stopbits": line.stopbits,
            }
        ],
        "devices": [
            {
                "name": s.name,
                "bus": "line",
                "address": s.address,
                "profile": s.profile_id,
                "poll_interval": INTERVAL_S,
                "diagnostics_interval": day,
                "configuration_interval": day,
                **phase,
            }
            for s in PLANT
        ],
        "mqtt": {
            "host": "127.0.0.1",
            "port": broker,
            "base_topic": prefix,
            "client_id": f"bench-{prefix}",
            **({} if qos is None else {"qos": qos, "value_qos": qos}),
        },
        "prometheus": {"host": "127.0.0.1", "port": free_port()},
        "state_dir": str(work / "state"),
        "logging": {"level": "WARNING"},
    }


def peer_devices() -> list[peer.PeerDevice]:
    """The plant as the peer's configuration holds it."""
    return [
        peer.PeerDevice(
            name=s.name,
            address=s.address,
            profile=s.profile,
            blocks=tuple(peer.hand_blocks(s.profile, s.points())),
        )
        for s in PLANT
    ]


# --- the masters -------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Master:
    """A master under test: how it starts on a line, and where its values appear."""

    name: str
    command: Callable[[Path, LineFormat, int, Path], list[str]]  # port, line, broker, work
    parse_topic: Callable[[str], tuple[str, str] | None]  # (device, point) of a value topic
    subscription: str


def gateway_master(
    name: str,
    prefix: str,
    program: Sequence[str],
    *,
    poll_phase: float | None = None,
    qos: int | None = None,
) -> Master:
    """A gateway started by ``program`` (its command line up to ``run``), under ``prefix``.

    ``poll_phase`` and ``qos``: as :func:`gateway_config` takes them.
    """

    def command(port: Path, line: LineFormat, broker: int, work: Path) -> list[str]:
        config = work / "gateway.yaml"  # JSON is YAML
        settings = gateway_config(
            port, line, broker, work, prefix=prefix, poll_phase=poll_phase, qos=qos
        )
        config.write_text(json.dumps(settings), encoding="utf-8")
        return [*program, "run", "--config", str(config)]

    def topic(topic: str) -> tuple[str, str] | None:
        """``(device, point)`` of a plain value topic ``{prefix}/{device}/{point}``, else None."""
        parts = topic.split("/")
        if len(parts) == 3 and parts[0] == prefix:  # noqa: PLR2004
            return parts[1], parts[2]
        return None

    return Master(name, command, topic, f"{prefix}/#")


def this_gateway() -> list[str]:
    """This tree's gateway, as installed (its console script)."""
    script = Path(sys.executable).parent / "gateway"
    return [str(script)] if script.exists() else [sys.executable, "-m", "gateway"]


def earlier_gateway_program(tree: Path) -> list[str]:
    """The gateway package extracted to ``tree`` (an earlier commit's), ahead of this one."""
    boot = (
        f"import sys; sys.path.insert(0, {str(tree)!r}); sys.argv[0] = 'gateway'; "
        "from gateway.cli import main; sys.exit(main())"
    )
    return [sys.executable, "-c", boot]


GATEWAY: Final = gateway_master("gateway", GATEWAY_PREFIX, this_gateway())


def peer_master(executable: Path) -> Master:
    def command(port: Path, line: LineFormat, broker: int, work: Path) -> list[str]:
        config = work / "modbus2mqtt.csv"
        config.write_text(peer.config_csv(peer_devices(), interval_s=INTERVAL_S), encoding="utf-8")
        return peer.command(executable, port=port, line=line, broker=broker, config=config)

    return Master(peer.PEER, command, peer.parse_topic, f"{peer.TOPIC}/#")


# --- processes ---------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@contextlib.asynccontextmanager
async def child(
    argv: Sequence[str], *, log: Path, ready: bytes | None = None
) -> AsyncIterator[asyncio.subprocess.Process]:
    """A process that is stopped (SIGTERM, then SIGKILL) however the block ends.

    With ``ready``, its first line of output must start with it before the block runs.
    """
    with log.open("wb") as sink:
        process = await asyncio.create_subprocess_exec(
            *argv,
            stdout=asyncio.subprocess.PIPE if ready else sink,
            stderr=sink,
            cwd=ROOT,
            env=CHILD_ENV,
            start_new_session=True,  # a Ctrl-C of the bench reaches it only through us
        )
        try:
            if ready is not None:
                assert process.stdout is not None
                first = await asyncio.wait_for(process.stdout.readline(), 30)
                if not first.startswith(ready):
                    raise RuntimeError(f"{argv[0]} did not start:\n{_tail(log)}")
            yield process
        finally:
            await stop(process)


async def stop(process: asyncio.subprocess.Process, timeout_s: float = STOP_S) -> None:
    """SIGTERM, a bounded wait, then SIGKILL: no process is left behind."""
    if process.returncode is not None:
        return
    process.terminate()
    try:
        await asyncio.wait_for(asyncio.shield(process.wait()), timeout_s)
    except TimeoutError:
        process.kill()
        await process.wait()


def _tail(log: Path, lines: int = 15) -> str:
    return "\n".join(log.read_text(encoding="utf-8", errors="replace").splitlines()[-lines:])


@contextlib.asynccontextmanager
async def mosquitto(work: Path) -> AsyncIterator[int]:
    """A broker of our own on a free local port."""
    binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    port = free_port()
    config = work / "mosquitto.conf"
    config.write_text(
        f"user {getpass.getuser()}\nlistener {port} 127.0.0.1\nallow_anonymous true\n",
        encoding="utf-8",
    )
    async with child([binary, "-c", str(config)], log=work / "mosquitto.log"):
        for _ in range(100):
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2):
                break
            await asyncio.sleep(0.05)
        yield port


@dataclass(frozen=True, slots=True)
class ProcessSample:
    """CPU seconds so far and memory of a process with its children."""

    cpu_s: float  # the fine clock: the master's cgroup, or its threads' schedstat
    ticks_cpu_s: float  # utime + stime (and waited-for children's) in 10 ms ticks
    rss_mib: float
    peak_rss_mib: float


class CpuClock(Protocol):
    """Where a master's CPU seconds are read: its control group, or its threads' schedstat."""

    def usage_s(self) -> float: ...


def sample_process(pid: int, clock: CpuClock) -> ProcessSample:
    """CPU from ``clock``, from /proc ticks beside it, and VmRSS/VmHWM over the tree."""
    ticks = os.sysconf("SC_CLK_TCK")
    ticked = rss = peak = 0.0
    for member in process_tree(pid):
        with contextlib.suppress(OSError):
            fields = Path(f"/proc/{member}/stat").read_text(encoding="utf-8")
            # utime, stime, cutime, cstime: proc(5) fields 14-17, [11:15] after the name.
            ticked += sum(int(f) for f in fields.rsplit(")", 1)[1].split()[11:15]) / ticks
            status = Path(f"/proc/{member}/status").read_text(encoding="utf-8")
            for line in status.splitlines():
                if line.startswith("VmRSS:"):
                    rss += int(line.split()[1]) / 1024
                elif line.startswith("VmHWM:"):
                    peak += int(line.split()[1]) / 1024
    return ProcessSample(cpu_s=clock.usage_s(), ticks_cpu_s=ticked, rss_mib=rss, peak_rss_mib=peak)


@contextlib.contextmanager
def cpu_group(name: str) -> Iterator[CpuGroup | None]:
    """A control group that counts the master's CPU in ns, or None where none can be made."""
    try:
        with cgroups.open_group(name) as group:
            yield group
    except cgroups.CgroupError as missing:
        print(f"CPU from each thread's schedstat (no control group: {missing})", flush=True)
        yield None


# --- what reaches the broker -------------------------------------------------------------


@dataclass(slots=True)
class Received:
    """Messages published while the bench listened: (monotonic time, topic, payload)."""

    messages: list[tuple[float, str, str]] = field(default_factory=list)
    lost: str | None = None  # why the subscription ended early: the figures would be short


_LISTENERS: Final = itertools.count()


@contextlib.asynccontextmanager
async def listen(broker: int, subscription: str) -> AsyncIterator[Received]:
    """Subscribe before the master starts; retained copies from an earlier run are skipped."""
    received = Received()
    # One client per subscription: two listening at once (--at-once) under one identifier
    # would take the session over from each other.
    identifier = f"bench-peers-{os.getpid()}-{next(_LISTENERS)}"
    async with aiomqtt.Client("127.0.0.1", broker, identifier=identifier) as client:
        await client.subscribe(subscription, qos=1)

        async def collect() -> None:
            try:
                async for message in client.messages:
                    if not message.retain and isinstance(message.payload, bytes):
                        text = message.payload.decode(errors="replace")
                        received.messages.append((time.monotonic(), message.topic.value, text))
            except aiomqtt.MqttError as exc:
                received.lost = str(exc)

        task = asyncio.create_task(collect(), name="bench.peers.listen")
        try:
            yield received
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


def value_figures(received: Received, master: Master, t0: float, t1: float) -> Figures:
    """The compared values published in the window: how many, and how many are wrong.

    An empty payload is a value withdrawn after a failed read (our gateway clears the
    retained value so no stale number lingers): no value, and not a wrong one.
    """
    if received.lost is not None:
        raise RuntimeError(f"the bench's subscription ended early: {received.lost}")
    truth = {(s.name, name): value for s in PLANT for name, value in s.values.items()}
    seen = wrong = withdrawn = 0
    examples: list[str] = []
    for at, topic, payload in received.messages:
        key = master.parse_topic(topic)
        if not t0 <= at <= t1 or key not in truth:
            continue
        if not payload:
            withdrawn += 1
        elif _matches(payload, truth[key]):
            seen += 1
        else:
            seen += 1
            wrong += 1
            examples.append(f"{topic}={payload} (true {truth[key]})")
    return {
        "values": seen,
        "values_asked": round(POINTS * (t1 - t0) / INTERVAL_S),
        "values_per_s": seen / (t1 - t0),
        "wrong_values": wrong,
        "withdrawn_values": withdrawn,
        "wrong_examples": examples[:5],
    }


def _matches(payload: str, truth: float) -> bool:
    try:
        value = float(payload)
    except ValueError:
        return False
    return math.isclose(value, truth, rel_tol=1e-6, abs_tol=1e-9)


# --- runs --------------------------------------------------------------------------------


async def one_run(
    master: Master, phase: Phase, *, line: LineFormat, seconds: float, broker: int, work: Path
) -> Figures:
    """One master on one phase of the line: start everything, measure, stop everything."""
    run = work / f"{master.name.split()[0]}-{phase.name}"
    run.mkdir()
    port, out, config = run / "tty", run / "line.json", run / "line.yaml"
    config.write_text(json.dumps(simulator_config(line, phase)), encoding="utf-8")
    simulate = [sys.executable, "-m", "bench.peer_line", "--config", str(config)]
    simulate += ["--pty", str(port), "--out", str(out)]
    async with contextlib.AsyncExitStack() as stack:
        await stack.enter_async_context(child(simulate, log=run / "line.log", ready=b"ready"))
        received = await stack.enter_async_context(listen(broker, master.subscription))
        argv = master.command(port, line, broker, run)
        group = stack.enter_context(cpu_group(f"gateway-bench-peers-{run.name}"))
        if group is not None:  # the master enters it before it runs: every thread counted
            argv = group.enter_argv(argv)
        process = await stack.enter_async_context(child(argv, log=run / "master.log"))
        clock: CpuClock = group if group is not None else cgroups.SchedstatClock(process.pid)
        await asyncio.sleep(WARM_UP_S)
        if process.returncode is not None:
            raise RuntimeError(f"{master.name} stopped:\n{_tail(run / 'master.log')}")
        t0, before = time.monotonic(), sample_process(process.pid, clock)
        await asyncio.sleep(seconds)
        t1, after = time.monotonic(), sample_process(process.pid, clock)
        cpu_clock = "cgroup" if group is not None else "schedstat"
    document = json.loads(out.read_text(encoding="utf-8"))
    required = {s.address: line.frame_gap_s(s.profile.timing.min_gap_s) for s in PLANT}
    wire = wire_figures(document, line, required_gap_s=required, t0=t0, t1=t1)
    cpu_s = after.cpu_s - before.cpu_s
    return {
        **wire,
        **value_figures(received, master, t0, t1),
        "window_s": t1 - t0,
        "cpu_s": cpu_s,
        "cpu_share": cpu_s / (t1 - t0),
        "cpu_us_per_transaction": 1e6 * cpu_s / max(wire["transactions"], 1),
        "cpu_clock": cpu_clock,
        "ticks_cpu_share": (after.ticks_cpu_s - before.ticks_cpu_s) / (t1 - t0),
        "rss_mib": after.rss_mib,
        "peak_rss_mib": after.peak_rss_mib,
    }


@contextlib.contextmanager
def workspace(keep: Path | None) -> Iterator[Path]:
    """Where runs put their configurations, logs and frame logs: ``keep``, or a temporary one."""
    if keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
        yield Path(tempfile.mkdtemp(prefix="bench-peers-", dir=keep))
        return
    with tempfile.TemporaryDirectory(prefix="bench-peers-") as tmp:
        yield Path(tmp)


async def run_all(
    masters: Sequence[Master],
    line: LineFormat,
    seconds: float,
    *,
    keep: Path | None,
    at_once: bool = False,
) -> dict[str, dict[str, Figures]]:
    """Every phase with every master in turn, on one broker; SIGTERM stops it all cleanly.

    ``at_once``: the masters of a phase run at the same time, each on a simulated line of
    its own, over the same seconds. A virtual machine's speed moves twofold within a minute
    (bench/README, 2026-12-05), and in turns that move lands on one master only; each
    master sleeps most of each second, so neither waits for the other on two cores.
    """
    task = asyncio.current_task()
    assert task is not None
    asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, task.cancel)
    results: dict[str, dict[str, Figures]] = {m.name: {} for m in masters}
    with workspace(keep) as work:
        async with mosquitto(work) as broker:
            for phase in PHASES:
                if at_once:
                    names = " and ".join(m.name for m in masters)
                    print(f"{names} at once, {phase.title}: {seconds:g} s", flush=True)
                    figures = await asyncio.gather(
                        *(
                            one_run(m, phase, line=line, seconds=seconds, broker=broker, work=work)
                            for m in masters
                        )
                    )
                    for master, measured in zip(masters, figures, strict=True):
                        results[master.name][phase.name] = measured
                    continue
                for master in masters:
                    print(f"{master.name}, {phase.title}: {seconds:g} s", flush=True)
                    results[master.name][phase.name] = await one_run(
                        master, phase, line=line, seconds=seconds, broker=broker, work=work
                    )
    return results


# --- report ------------------------------------------------------------------------------


def _number(key: str, fmt: str, scale: float = 1.0) -> Callable[[Figures], str]:
    return lambda figures: format(figures[key] * scale, fmt)


def _wrong(figures: Figures) -> str:
    return f"{figures['wrong_values']} of {figures['values']}"


def _injected(figures: Figures) -> str:
    injected = figures["faults_injected"]
    return f"{injected.get('crc', 0)} crc, {injected.get('drop', 0)} drop"


ROWS: Final[tuple[tuple[str, str, Callable[[Figures], str]], ...]] = (
    ("clean", "frames per cycle", _number("frames_per_cycle", ".0f")),
    ("clean", "transactions/s", _number("transactions_per_s", ".2f")),
    ("clean", f"values/s ({POINTS} asked)", _number("values_per_s", ".2f")),
    ("clean", "CPU µs per transaction", _number("cpu_us_per_transaction", ".0f")),
    ("clean", "CPU % of one core", _number("cpu_share", ".3f", 100)),
    ("clean", "CPU % (10 ms ticks)", _number("ticks_cpu_share", ".2f", 100)),
    ("clean", "RSS MiB (peak)", _number("peak_rss_mib", ".1f")),
    ("clean", "min gap ms", _number("min_gap_ms", ".2f")),
    ("clean", "median gap ms", _number("median_gap_ms", ".2f")),
    ("clean", "timing violations", _number("timing_violations", ".0f")),
    ("faults", "faults injected (run)", _injected),
    ("faults", "wrong values of published", _wrong),
    ("faults", f"values/s ({POINTS} asked)", _number("values_per_s", ".2f")),
    ("faults", "values withdrawn", _number("withdrawn_values", ".0f")),
    ("faults", "timing violations", _number("timing_violations", ".0f")),
)


def table(results: Mapping[str, Mapping[str, Figures]], line: LineFormat) -> str:
    """The figures side by side, one column per master."""
    names = list(results)
    lines = [f"{f'{line}, every {INTERVAL_S:g} s':<28}" + "".join(f"{n:>20}" for n in names)]
    for phase in PHASES:
        lines.append(f"-- {phase.title}")
        lines.extend(
            f"{label:<28}" + "".join(f"{show(results[n][phase.name]):>20}" for n in names)
            for which, label, show in ROWS
            if which == phase.name
        )
    blocks = sum(len(d.blocks) for d in peer_devices())
    lines.append(f"3.5 characters at {line}: {1000 * line.frame_gap_s():.2f} ms")
    lines.append(f"the peer's {blocks} poll blocks are written by hand (one per point: {POINTS})")
    return "\n".join(lines)


def verdicts(results: Mapping[str, Mapping[str, Figures]]) -> list[str]:
    """Target 2 of the engine-cost work, and the figures the gateway must stay ahead on.

    Ahead means: no more CPU than the peer (the target), and as now more transactions and
    values a second, a smaller least gap (closer to the 3.5 characters the line requires,
    none below it) and no more wrong values under faults.
    """
    ours, theirs = results[GATEWAY.name], results[peer.PEER]
    clean, faults = "clean", "faults"

    def line(label: str, ok: bool, shown: str) -> str:  # noqa: FBT001 - reads as a verdict
        return f"{label:<44} {shown:<28} {'yes' if ok else 'no'}"

    def pair(key: str, phase: str, fmt: str, scale: float = 1.0) -> str:
        return f"{ours[phase][key] * scale:{fmt}} vs {theirs[phase][key] * scale:{fmt}}"

    gaps_ok = all(ours[phase]["gaps_below_required"] == 0 for phase in (clean, faults))
    checks = [
        line(
            "target 2: CPU share <= the peer's",
            ours[clean]["cpu_share"] <= theirs[clean]["cpu_share"],
            pair("cpu_share", clean, ".3f", 100) + " %",
        ),
        line(
            "ahead on transactions/s",
            ours[clean]["transactions_per_s"] > theirs[clean]["transactions_per_s"],
            pair("transactions_per_s", clean, ".2f"),
        ),
        line(
            "ahead on values/s, clean",
            ours[clean]["values_per_s"] > theirs[clean]["values_per_s"],
            pair("values_per_s", clean, ".2f"),
        ),
        line(
            "ahead on values/s, with faults",
            ours[faults]["values_per_s"] > theirs[faults]["values_per_s"],
            pair("values_per_s", faults, ".2f"),
        ),
        # The smallest gap: how close to the 3.5 characters the master sends when it has
        # the next request ready. Not the median: with its devices' poll phases spread
        # across the second, the gateway leaves the line idle between devices on purpose
        # (the peer polls them all back to back), so its median gap tells that spread.
        line(
            "ahead on gaps (min; none too short)",
            gaps_ok and ours[clean]["min_gap_ms"] < theirs[clean]["min_gap_ms"],
            pair("min_gap_ms", clean, ".2f") + " ms",
        ),
        line(
            "no more wrong values under faults",
            ours[faults]["wrong_values"] <= theirs[faults]["wrong_values"],
            pair("wrong_values", faults, ".0f"),
        ),
    ]
    met = all(c.endswith("yes") for c in checks)
    clock = ours[clean].get("cpu_clock", "?")
    return [
        f"{'gateway vs ' + peer.PEER:<44} {'(CPU clock: ' + clock + ')':<28} met",
        *checks,
        f"target 2 and every lead kept: {'yes' if met else 'no'}",
    ]


def against(ref: str, line: LineFormat, seconds: float, *, new: Master, keep: Path | None) -> None:
    """This tree's gateway, ``new``, and commit ``ref``'s in one plant at once: CPU new / old.

    A step of a few per cent is lost in the pace of the machine between runs of the peer
    comparison; side by side, each on a line of its own, both gateways see the same pace.
    ``ref``'s gateway has the plant's defaults (neither ``--poll-phase`` nor ``--qos``).
    """
    with tempfile.TemporaryDirectory(prefix="bench-peers-against-") as tmp:
        old = gateway_master(
            f"gateway@{ref}", "gwold", earlier_gateway_program(extracted(ref, Path(tmp)))
        )
        try:
            results = asyncio.run(run_all([old, new], line, seconds, keep=keep, at_once=True))
        except (asyncio.CancelledError, KeyboardInterrupt):
            raise SystemExit("stopped: every process it started is stopped") from None
    print(table(results, line))
    for phase in PHASES:
        new_cpu = results[new.name][phase.name]["cpu_share"]
        old_cpu = results[old.name][phase.name]["cpu_share"]
        print(f"CPU new / old, {phase.title}: {new_cpu / old_cpu:.3f}")


def parse_format(text: str) -> LineFormat:
    """``9600-E-1`` as a line format; anything else ends the bench with a usage error."""
    baudrate, parity, stopbits = [*text.split("-"), "", "", ""][:3]
    if not baudrate.isdigit() or parity not in PARITIES or stopbits not in {"1", "2"}:
        raise SystemExit(f"--format {text!r}: expected BAUD-PARITY-STOPBITS, e.g. 9600-E-1")
    return LineFormat(baudrate=int(baudrate), parity=PARITIES[parity], stopbits=int(stopbits))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=30.0, help="measured per run")
    parser.add_argument("--format", default="9600-E-1", help="the line, BAUD-PARITY-STOPBITS")
    parser.add_argument(
        "--keep", type=Path, metavar="DIR", help="keep each run's configs and logs under DIR"
    )
    parser.add_argument(
        "--at-once", action="store_true", help="both masters at the same time, each on its line"
    )
    parser.add_argument(
        "--against",
        metavar="REF",
        help="no peer: this tree's gateway against commit REF's, at once (written nowhere)",
    )
    parser.add_argument(
        "--poll-phase",
        type=float,
        metavar="P",
        help="every device of this tree's gateway at poll phase P (0 <= P < 1; default: spread)",
    )
    parser.add_argument(
        "--qos",
        type=int,
        choices=(0, 1),
        help="every message of this tree's gateway at this QoS, values too (default: 1)",
    )
    args = parser.parse_args()
    line = parse_format(args.format)
    check_plant()
    if args.poll_phase is not None and not 0 <= args.poll_phase < 1:
        raise SystemExit(f"--poll-phase {args.poll_phase}: expected 0 <= P < 1")
    gateway = GATEWAY
    if args.poll_phase is not None or args.qos is not None:
        gateway = gateway_master(
            GATEWAY.name, GATEWAY_PREFIX, this_gateway(), poll_phase=args.poll_phase, qos=args.qos
        )
    if args.against:
        against(args.against, line, args.seconds, new=gateway, keep=args.keep)
        return
    masters = [peer_master(peer.ensure_venv()), gateway]
    try:
        results = asyncio.run(
            run_all(masters, line, args.seconds, keep=args.keep, at_once=args.at_once)
        )
    except (asyncio.CancelledError, KeyboardInterrupt):
        raise SystemExit(
            "stopped: every process it started is stopped, no figures written"
        ) from None
    RESULTS.mkdir(exist_ok=True)
    document = {
        "line": str(line),
        "interval_s": INTERVAL_S,
        "seconds": args.seconds,
        "at_once": args.at_once,
        "poll_phase": args.poll_phase,
        "qos": args.qos,
        "warm_up_s": WARM_UP_S,
        "peer": {"package": peer.PACKAGE, "dependencies": list(peer.DEPENDENCIES)},
        "peer_config": peer.config_csv(peer_devices(), interval_s=INTERVAL_S),
        "results": results,
    }
    (RESULTS / "peers.json").write_text(json.dumps(document, indent=2), encoding="utf-8")
    print(table(results, line))
    print("\n".join(verdicts(results)))


if __name__ == "__main__":
    main()
