"""A wall clock stepped forward and back while the gateway runs, with a real time shift.

The gateway runs as ``gateway run`` under Debian's libfaketime, whose offset is a file the
test rewrites: the process's wall clock (``time.time``, ``datetime.now``) jumps by hours or
days at once, as when NTP steps a Raspberry Pi that booted with the time it last saved,
while its monotonic clock runs on untouched (``FAKETIME_DONT_FAKE_MONOTONIC``), as the
kernel's does. Everything else is real: the simulator as its own process on a
pseudo-terminal (its stats file counts every request and keeps every write), mosquitto,
a persistent QoS 1 subscriber, ``/metrics``.

What must hold (README: A clock you can trust):

- no burst of polls and no missed-deadline storm: the requests per second of each sensor
  after each step are those before it, and ``gateway_missed_deadlines_total`` counts no
  deadline that did not come on the monotonic clock (:func:`assert_no_missed_deadline_storm`);
- store and forward across a broker outage that spans the step: every state document
  arrives, in order, without a gap (``seq`` 1, 2, 3, ...);
- the timestamps published follow the wall clock: after a step, the documents carry the
  stepped time, and in ``seq`` order the time jumps once by the step and nowhere else;
- the daily flash-write budget is neither reset nor doubled by a step across midnight,
  while a midnight passed without a step opens the next day's budget as before.

libfaketime 0.9.10 (Debian 12) mistreats the monotonic clock where it is not faked, in
two calls: ``clock_nanosleep`` on it fails with EINVAL (so a process under it must not
call ``time.sleep``: the gateway does not, its waits are the event loop's), and
``timerfd_settime`` moves an absolute deadline on it by the wall clock's offset (a step
back of a day would hold the inter-frame gap's timer, :mod:`gateway.line.transports.timer`, for a
day). Neither happens under an NTP step, which leaves the monotonic clock alone; so the
gateway under test calls the C library's own ``timerfd_settime``, as without libfaketime
(:data:`REAL_TIMERFD`), and the kernel's timer runs on the monotonic clock as it does on
a plant.
"""

from __future__ import annotations

import itertools
import json
import os
import signal
import sqlite3
import struct
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from gateway.shared.host_clock import TRUST_VARIABLE
from tests.mqtt_broker import free_port
from tests.rigs import simulate_process, stats_of
from tests.storage_rig import Subscriber, get, metric
from tests.waiting import wait_until

if TYPE_CHECKING:
    from collections.abc import Iterator

    from tests.mqtt_broker import Broker

pytestmark = [pytest.mark.line, pytest.mark.timing, pytest.mark.broker, pytest.mark.timeout(180)]

BASE = "cs"
S10, CL2 = 1, 20
SIMULATED = (
    "line: {baudrate: 38400, parity: E, stopbits: 1}\n"
    "devices:\n"
    f"  - {{profile: jumo-digiline-odo-s10, address: {S10}}}\n"
    f"  - {{profile: jumo-tecline-cl2, address: {CL2}, values: {{cell_current: 76.5}}}}\n"
)
FLASH_BUDGET = 2  # x_zero's writes per day
X_ZERO = 0x0206  # tecLine X_Zero, the flash-backed point the budget test writes
FORWARD_S = 26 * 3600  # a step across midnight: the clock was a day and more behind
BACK_S = -3 * 3600  # then 29 hours back
# Requests per second after a step against before it: a quarter either way, and two
# requests more for the stats file's age at each end of a window (it is rewritten every
# 250 ms). A burst is hundreds (a day of 0.2 s polls caught up), a stall none.
RATE_TOLERANCE = 0.25
SHORT_TOLERANCE = 0.4  # the first 2 s after a step
WINDOW_S = 5.0  # a rate is measured over this long
LATE_S = 5.0  # the most a document's time may lag its predecessor's but at a step
# The budget test's clock starts this long before a midnight: the start and the day's
# three writes must come before it (1.5 s of it on the 2-core test machine, 2026-12-04).
BEFORE_MIDNIGHT_S = 10
INTERVALS = {"aeration": 0.2, "cl2": 0.5}  # each sensor's poll interval, seconds
# The simulator is a Python process: on a loaded test machine it answers a hundred
# milliseconds late now and then, past the 78 ms the gateway waits for the S10 at 38400
# baud by default, and each timeout holds the sensor for the late-answer window, a second:
# a dip in a rate window. This test is about the clock, not the line's timing: the bus
# waits as long as the config allows (no longer than the shortest poll interval).
TIMEOUT_S = 0.2


# ``gateway run``, its inter-frame timer on the C library's own ``timerfd_settime`` (dlsym
# on libc's handle finds libc's symbol, not libfaketime's, which is preloaded before it).
REAL_TIMERFD = (
    "import ctypes\n"
    "import gateway.line.transports.timer as timer\n"
    "libc = ctypes.CDLL('libc.so.6', use_errno=True)\n"
    "libc.timerfd_create.argtypes = (ctypes.c_int, ctypes.c_int)\n"
    "libc.timerfd_settime.argtypes = (ctypes.c_int, ctypes.c_int,"
    " ctypes.POINTER(timer._Itimerspec), ctypes.c_void_p)\n"
    "timer._LIBC = libc\n"
    "from gateway.cli import main\n"
    "main()\n"
)


def libfaketime() -> Path:
    """Debian's libfaketime (the thread-safe one): ``scripts/setup test`` installs it."""
    found = sorted(Path("/usr/lib").glob("*/faketime/libfaketimeMT.so.1"))
    assert found, "libfaketime is missing: run scripts/setup test (apt-get install faketime)"
    return found[0]


@dataclass
class FakedClock:
    """The offset of the gateway's wall clock from the real one, in libfaketime's file."""

    path: Path
    steps: list[tuple[float, float]] = field(default_factory=list)  # (real time, offset)

    def set(self, offset_s: float) -> None:
        """Step the wall clock to ``offset_s`` from the real one, at once (a rename)."""
        part = self.path.with_suffix(".new")
        part.write_text(f"{offset_s:+.0f}\n", encoding="ascii")
        part.replace(self.path)
        self.steps.append((time.time(), offset_s))

    @property
    def offset_s(self) -> float:
        return self.steps[-1][1]

    def at(self, real: float) -> float:
        """The offset in force at the real time ``real``."""
        offset = 0.0
        for when, value in self.steps:
            if when <= real:
                offset = value
        return offset

    def now(self) -> datetime:
        """The gateway's wall clock now."""
        return datetime.fromtimestamp(time.time() + self.offset_s, UTC)


@dataclass
class FakedGateway:
    """``gateway run`` under libfaketime, its log in a file."""

    config: Path
    log: Path
    clock: FakedClock
    trust_clock: bool = True
    process: subprocess.Popen[bytes] | None = None
    started_at: float = 0.0  # time.monotonic() at the start: the counters begin there

    def start(self) -> None:
        env = {
            **os.environ,
            "LD_PRELOAD": str(libfaketime()),
            "FAKETIME_TIMESTAMP_FILE": str(self.clock.path),
            "FAKETIME_NO_CACHE": "1",  # the file is read at every call: a step is at once
            "FAKETIME_DONT_FAKE_MONOTONIC": "1",  # as NTP: the monotonic clock runs on
        }
        env.pop(TRUST_VARIABLE, None)
        if self.trust_clock:
            env[TRUST_VARIABLE] = "true"
        self.started_at = time.monotonic()
        with self.log.open("ab") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-c", REAL_TIMERFD, "run", "--config", str(self.config)],
                stdout=subprocess.DEVNULL,
                stderr=log,
                env=env,
            )

    def stop(self) -> int:
        assert self.process is not None
        self.process.send_signal(signal.SIGTERM)
        code = self.process.wait(timeout=15)
        self.process = None
        return code

    def kill(self) -> None:
        if self.process is not None:
            self.process.kill()
            self.process.wait(timeout=10)
            self.process = None

    def log_text(self) -> str:
        return self.log.read_text(encoding="utf-8", errors="replace")


def config_text(tmp_path: Path, port: Path, broker_port: int, metrics_port: int) -> str:
    return (
        f"buses:\n  - {{name: line1, port: {port}, baudrate: 38400, parity: E,"
        f" timeout: {TIMEOUT_S}}}\n"
        "devices:\n"
        f"  - {{name: aeration, bus: line1, address: {S10}, profile: jumo-digiline-odo-s10,"
        f" poll_interval: {INTERVALS['aeration']}}}\n"
        f"  - {{name: cl2, bus: line1, address: {CL2}, profile: jumo-tecline-cl2,"
        f" poll_interval: {INTERVALS['cl2']}, flash_writes: [x_zero],"
        f" flash_write_budget: {FLASH_BUDGET}}}\n"
        f"mqtt: {{host: 127.0.0.1, port: {broker_port}, base_topic: {BASE},"
        " reconnect_max_s: 0.5}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics_port}}}\n"
        f"state_dir: {tmp_path / 'state'}\n"
    )


@dataclass(frozen=True)
class Rate:
    per_s: dict[int, float]  # requests per second, by sensor address
    seconds: float  # over this long


@dataclass
class Plant:
    tmp_path: Path
    stats: Path
    clock: FakedClock
    gateway: FakedGateway
    subscriber: Subscriber
    metrics_port: int

    def requests(self) -> Counter[int]:
        """Every request the simulator has answered or seen, by sensor address."""
        devices = stats_of(self.stats)["devices"]
        return Counter({int(address): int(d["requests"]) for address, d in devices.items()})

    def rate(self, seconds: float = WINDOW_S) -> Rate:
        """Requests per second of each sensor, over ``seconds`` from now."""
        before, started = self.requests(), time.monotonic()
        time.sleep(seconds)
        after = self.requests()
        elapsed = time.monotonic() - started
        per_s = {address: (after[address] - before[address]) / elapsed for address in (S10, CL2)}
        return Rate(per_s=per_s, seconds=elapsed)

    def missed(self, device: str) -> float:
        """The sensor's missed deadlines since the gateway started."""
        name = "gateway_missed_deadlines_total"
        return metric(self.metrics_port, name, bus="line1", device=device) or 0.0

    def polled_points(self, device: str) -> int:
        """How many points of the sensor the gateway polls: each has a value age."""
        _, text = get(f"http://127.0.0.1:{self.metrics_port}/metrics")
        label = f'device="{device}"'
        return sum(
            1
            for line in text.splitlines()
            if line.startswith("gateway_value_age_seconds{") and label in line
        )

    def writes_of_x_zero(self) -> list[dict[str, Any]]:
        devices = stats_of(self.stats)["devices"]
        return [w for w in devices[str(CL2)]["writes"] if w["address"] == X_ZERO]


@pytest.fixture
def plant(tmp_path: Path, broker: Broker) -> Iterator[Plant]:
    clock = FakedClock(tmp_path / "faketime")
    clock.set(0)
    metrics_port = free_port()
    with simulate_process(tmp_path, SIMULATED) as (port, stats):
        config = tmp_path / "gateway.yaml"
        config.write_text(config_text(tmp_path, port, broker.port, metrics_port), encoding="utf-8")
        gateway = FakedGateway(config=config, log=tmp_path / "gateway.log", clock=clock)
        topics = f"{BASE}/#"
        with Subscriber(broker.port, topics, name="clock-step-recorder") as subscriber:
            yield Plant(tmp_path, stats, clock, gateway, subscriber, metrics_port)
            gateway.kill()


def started(plant: Plant) -> None:
    """Start the gateway and wait for both sensors' first state documents."""
    plant.gateway.start()
    for device in ("aeration", "cl2"):
        plant.subscriber.wait_for(f"{BASE}/{device}/state", within_s=20)


def assert_same_rate(
    before: Rate, after: Rate, when: str, tolerance: float = RATE_TOLERANCE
) -> None:
    for address, rate in before.per_s.items():
        assert rate > 0, f"sensor {address} was not polled before"
        allowed = tolerance * rate + 2 / after.seconds
        assert abs(after.per_s[address] - rate) <= allowed, (
            f"sensor {address}: {after.per_s[address]:.1f} requests/s {when}, {rate:.1f} before"
        )


def assert_no_missed_deadline_storm(plant: Plant, when: str) -> None:
    """Every missed deadline the gateway counted since its start came in that time.

    A poll that comes late skips, once each, the deadlines of its points that passed
    meanwhile on the monotonic clock: since the start, at most that time over the interval
    for each point polled (the slow points' intervals are longer still). That happens on a
    loaded machine whatever the clock does: the gateway's process or the simulator's not
    given the CPU for a few tenths of a second, or a timeout's late-answer window of a
    second (five of the S10's deadlines for each of its points). A schedule on the wall
    clock would count the step instead: 26 h over 0.2 s is 468,000 for every point.
    """
    elapsed = time.monotonic() - plant.gateway.started_at
    for device, interval in INTERVALS.items():
        missed = plant.missed(device)
        came = plant.polled_points(device) * (elapsed / interval + 1)
        assert missed <= came, (
            f"{device}: {missed:.0f} missed deadlines counted {when}, "
            f"but only {came:.0f} came in the {elapsed:.0f} s since the start"
        )


# --- timing, store and forward, timestamps ------------------------------------------------


def test_a_stepped_wall_clock_changes_no_timing_loses_no_message_and_stamps_the_new_time(
    plant: Plant, broker: Broker
) -> None:
    started(plant)
    time.sleep(3.0)  # settled: identity and the first diagnostics are read at the start
    baseline = plant.rate()

    # A broker outage that spans a step forward across midnight.
    broker.stop()
    time.sleep(1.0)
    plant.clock.set(FORWARD_S)
    first = plant.rate(2.0)
    assert_same_rate(baseline, first, "in the 2 s after the step forward", SHORT_TOLERANCE)
    assert_same_rate(baseline, plant.rate(), "after the step forward")
    assert_no_missed_deadline_storm(plant, "after the step forward")
    broker.start()
    time.sleep(1.0)
    assert_same_rate(baseline, plant.rate(), "after the broker came back")

    # Connected, a step back across two midnights.
    plant.clock.set(BACK_S)
    first = plant.rate(2.0)
    assert_same_rate(baseline, first, "in the 2 s after the step back", SHORT_TOLERANCE)
    assert_same_rate(baseline, plant.rate(), "after the step back")
    assert_no_missed_deadline_storm(plant, "after the step back")
    assert plant.gateway.stop() == 0
    time.sleep(0.5)  # the subscriber's last messages

    for device in ("aeration", "cl2"):
        documents = state_documents(plant.subscriber, device)
        seqs = [seq for seq, _, _ in documents]
        assert seqs == list(range(1, len(seqs) + 1)), f"{device}: a gap or a reorder"
        assert_times_follow_the_wall_clock(plant.clock, documents, device)
    log = plant.gateway.log_text()
    assert "Traceback" not in log, log


def state_documents(subscriber: Subscriber, device: str) -> list[tuple[int, datetime, float]]:
    """``(seq, the document's time, when it arrived)`` in arrival order, repeats left out.

    A repeat is the broker's (DUP, to a subscriber that was away): the first copy counts.
    """
    seen: set[int] = set()
    found = []
    for arrival in subscriber.received():
        if arrival.topic != f"{BASE}/{device}/state":
            continue
        body = json.loads(arrival.payload)
        seq = int(body["seq"])
        if seq in seen:
            assert arrival.dup, f"{device}: seq {seq} sent twice by the gateway"
            continue
        seen.add(seq)
        found.append((seq, datetime.fromisoformat(body["time"]), arrival.at))
    return found


def assert_times_follow_the_wall_clock(
    clock: FakedClock, documents: list[tuple[int, datetime, float]], device: str
) -> None:
    """In ``seq`` order the time moves on by a poll, but at each step by the step.

    A document that arrived at once (not from the queue) carries the wall clock of the
    gateway at its arrival, give or take its travel.
    """
    jumps = [
        (later[1] - earlier[1]).total_seconds() for earlier, later in itertools.pairwise(documents)
    ]
    steps = [b - a for (_, a), (_, b) in itertools.pairwise(clock.steps)]
    # A poll comes late under load, by seconds at most; a step is a day.
    big = [jump for jump in jumps if not -0.05 <= jump <= LATE_S]
    assert len(big) == len(steps), f"{device}: time jumps {big}, steps {steps}"
    for jump, step in zip(big, steps, strict=True):
        assert step - 0.05 <= jump <= step + LATE_S, f"{device}: a jump of {jump} s for {step} s"
    live = 0
    for _, stamped, arrived in documents:
        offset = clock.at(arrived)
        if any(abs(arrived - when) < 2.0 for when, _ in clock.steps[1:]):
            continue  # made around a step: either side of it
        expected = datetime.fromtimestamp(arrived + offset, UTC)
        lag = (expected - stamped).total_seconds()
        if lag < 1.5:  # arrived at once; what the queue held arrives later
            live += 1
            assert lag >= -0.05, f"{device}: stamped {stamped}, the clock said {expected}"
    assert live > 20, f"{device}: too few documents arrived at once to judge ({live})"


# --- the daily flash-write budget across midnight -------------------------------------------


@dataclass
class Commands:
    """``…/cl2/x_zero/set`` as a plant system sends it, and its result."""

    subscriber: Subscriber
    sent: int = 0

    def set_x_zero(self, value: float) -> dict[str, Any]:
        self.sent += 1
        ident = f"w{self.sent}"
        after = time.time()
        self.subscriber.client.publish(
            f"{BASE}/cl2/x_zero/set", json.dumps({"value": value, "id": ident}), qos=1
        )
        topic = f"{BASE}/cl2/x_zero/set/result"

        def answered() -> dict[str, Any] | None:
            for arrival in self.subscriber.received():
                if arrival.topic == topic and arrival.at >= after:
                    body: dict[str, Any] = json.loads(arrival.payload)
                    if body.get("id") == ident:
                        return body
            return None

        result: dict[str, Any] = wait_until(answered, within_s=15)
        return result


def midnight_after(moment: datetime) -> datetime:
    return datetime.combine(moment.date() + timedelta(days=1), datetime.min.time(), tzinfo=UTC)


def test_a_step_across_midnight_neither_resets_nor_doubles_the_flash_budget(
    plant: Plant,
) -> None:
    # The gateway's clock starts just before a midnight, ten days from now.
    day = datetime.now(UTC).date() + timedelta(days=10)
    midnight = datetime.combine(day, datetime.min.time(), tzinfo=UTC)
    before_midnight = midnight - timedelta(seconds=BEFORE_MIDNIGHT_S)
    plant.clock.set(round(before_midnight.timestamp() - time.time()))
    started(plant)
    commands = Commands(plant.subscriber)
    refused = f"budget of {FLASH_BUDGET} writes per day for cl2/x_zero is spent"

    assert plant.clock.now().date() == day - timedelta(days=1)
    for value in (1.0, 2.0):
        assert commands.set_x_zero(value)["written"] is True
    over = commands.set_x_zero(3.0)
    assert over["status"] == "error"
    assert refused in over["reason"]
    assert plant.clock.now() < midnight, (
        f"the start and the writes took more than BEFORE_MIDNIGHT_S ({BEFORE_MIDNIGHT_S} s)"
    )

    # Midnight passes without a step: the new day has its budget, as it always had.
    wait_until(
        lambda: plant.clock.now() > midnight + timedelta(seconds=0.5),
        within_s=BEFORE_MIDNIGHT_S + 5,
    )
    for value in (3.0, 4.0):
        assert commands.set_x_zero(value)["written"] is True
    assert refused in commands.set_x_zero(5.0)["reason"]

    # Stepped back across two midnights (the clock had run ahead): a day with no writes
    # on disk, but the writes of the last seconds are since its midnight: no reset.
    plant.clock.set(plant.clock.offset_s - 2 * 86_400 - 120)
    back = commands.set_x_zero(5.0)
    assert back["status"] == "error", f"the step back reset the budget: {back}"
    assert refused in back["reason"]

    # Stepped forward to 08:00 three days on: no second budget of the same real minute.
    ahead = midnight_after(plant.clock.now()) + timedelta(days=2, hours=8)
    plant.clock.set(plant.clock.offset_s + (ahead - plant.clock.now()).total_seconds())
    forward = commands.set_x_zero(5.0)
    assert forward["status"] == "error", f"the step forward opened a second budget: {forward}"
    assert refused in forward["reason"]
    assert plant.gateway.stop() == 0

    # What reached the sensor (its own record) and what the ledger holds, by day.
    assert [w["values"] for w in plant.writes_of_x_zero()] == [
        list(cdab(v)) for v in (1.0, 2.0, 3.0, 4.0)
    ]
    ledger = sqlite3.connect(plant.tmp_path / "state" / "flash-writes.sqlite")
    try:
        rows = ledger.execute("SELECT day, count FROM flash_writes ORDER BY day").fetchall()
    finally:
        ledger.close()
    assert rows == [(str(day - timedelta(days=1)), 2), (str(day), 2)]


def cdab(value: float) -> tuple[int, int]:
    """A float32 as the tecLine sends it: low word first (``0x0000 0x4319`` = 153.0)."""
    high, low = struct.unpack(">HH", struct.pack(">f", value))
    return low, high
