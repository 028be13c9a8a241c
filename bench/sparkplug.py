"""Sparkplug B against the plain topics: messages a second and bytes per value, at 16 x 16.

Synthetic poll cycles of 256 devices (16 buses x 16 S10s, 6 Float values each) go through
each sink to a local mosquitto, and a subscriber in this process counts what arrives:

- **plain**: the MQTT sink as configured by default (every poll: a retained topic per
  value and the state document), QoS 1;
- **sparkplug, every value changes**: the Sparkplug sink with every value moved past its
  deadband each round, so report by exception reports every value (its worst case): one
  DDATA per device cycle, QoS 0;
- **sparkplug, noise in the deadband**: values that move by a little noise around a level,
  with a deadband of 0.05 on every Float; only what moved past it is reported.

For each: values handed over, messages and bytes on the wire (topic and payload, as the
subscriber receives them), values and messages a second until the subscriber has them all
(including the births for Sparkplug), and bytes per value polled.

Printed, and written to bench/results/sparkplug.json.
Run from the repository root:
.venv/bin/python -m bench.sparkplug [--buses 16] [--devices 16] [--rounds 20]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import random
import tempfile
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import aiomqtt

from bench.publish import mosquitto
from gateway.config import MqttConfig, SparkplugConfig
from gateway.line.samples import Quality, Sample
from gateway.profiles import PollGroup, get_profile
from gateway.publish.mqtt import MqttSink
from gateway.publish.sparkplug import SparkplugSink
from gateway.shared.state import DeviceInfo, GatewayState, StateSink

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable

RESULTS = Path(__file__).parent / "results"
PROFILE = "jumo-digiline-odo-s10"
POINTS = (
    "oxygen",
    "temperature",
    "compensation_temperature",
    "compensation_salinity",
    "compensation_pressure",
    "temperature_highest",
)
NOISE = 0.01  # the noise of the steady scenario, well inside its deadband
DEADBAND = 0.05


@dataclass
class Counted:
    messages: int = 0
    bytes: int = 0


@contextlib.asynccontextmanager
async def subscriber(port: int, topic_filter: str) -> AsyncIterator[Counted]:
    counted = Counted()
    ready = asyncio.Event()

    async def listen() -> None:
        async with aiomqtt.Client("127.0.0.1", port, identifier=f"bench-{topic_filter}") as client:
            await client.subscribe(topic_filter, qos=1)
            ready.set()
            async for message in client.messages:
                payload = message.payload
                size = len(payload) if isinstance(payload, bytes) else len(str(payload))
                counted.messages += 1
                counted.bytes += size + len(message.topic.value)

    task = asyncio.create_task(listen())
    await asyncio.wait_for(ready.wait(), timeout=10)
    try:
        yield counted
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def devices(buses: int, per_bus: int) -> list[tuple[str, str]]:
    return [(f"bus{b}", f"dev{b}_{d}") for b in range(buses) for d in range(per_bus)]


def cycles(
    names: list[tuple[str, str]], rounds: int, value: Callable[[int, int], float]
) -> list[list[Sample]]:
    """Every device's cycle, ``rounds`` times; ``value(round, index)`` gives each value."""
    now, wall = time.monotonic(), datetime.now(tz=UTC)
    return [
        [
            Sample(
                bus=bus,
                device=device,
                profile=PROFILE,
                point=point,
                value=value(r, i),
                fault=None,
                unit="°C",
                quality=Quality.GOOD,
                monotonic=now,
                time=wall,
                group="process",
            )
            for i, point in enumerate(POINTS)
        ]
        for r in range(rounds)
        for bus, device in names
    ]


async def wait_for(counted: Counted, total: int, timeout_s: float = 300) -> None:
    deadline = time.monotonic() + timeout_s
    while counted.messages < total and time.monotonic() < deadline:  # noqa: ASYNC110
        await asyncio.sleep(0.005)


async def plain(
    port: int, directory: Path, names: list[tuple[str, str]], rounds: int
) -> dict[str, float]:
    state = GatewayState()
    for bus, device in names:
        state.add_device(
            DeviceInfo(
                bus=bus,
                name=device,
                profile=PROFILE,
                address=1,
                intervals=dict.fromkeys(POINTS, 1.0),
            )
        )
    settings = MqttConfig(host="127.0.0.1", port=port, base_topic="bench", queue_max=10_000_000)
    sink = MqttSink(settings, state, state_dir=directory / "plain")
    recorder = StateSink(state)
    work = cycles(names, rounds, lambda r, i: 20.0 + i + r * 0.1)
    async with subscriber(port, "bench/+/+") as counted:
        task = asyncio.create_task(sink.run())
        while not state.mqtt.connected:  # noqa: ASYNC110 - the sink's task sets it
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.5)
        base = counted.messages  # the retained status topic and such
        expected = 0
        start = time.perf_counter()
        for cycle in work:
            await recorder.publish(cycle)
            messages = sink.topics.cycle(cycle)
            expected += len(messages)
            sink.outbox.enqueue(messages)
        await wait_for(counted, base + expected)
        elapsed = time.perf_counter() - start
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    return figures(len(work) * len(POINTS), counted.messages - base, counted.bytes, elapsed)


async def sparkplug(
    port: int,
    directory: Path,
    names: list[tuple[str, str]],
    rounds: int,
    *,
    value: Callable[[int, int], float],
    deadband: float,
    label: str,
) -> dict[str, float]:
    profile = get_profile(PROFILE)
    # Every group: the six values include configuration (compensation) and diagnostics
    # points, which a host gets only when asked for (the default is process and status).
    settings = SparkplugConfig(
        enabled=True,
        group_id="bench",
        edge_node_id=label,
        deadband=deadband,
        groups=list(PollGroup),
    )
    broker = MqttConfig(host="127.0.0.1", port=port)
    sink = SparkplugSink(
        settings,
        broker,
        [(device, profile, POINTS) for _, device in names],
        state_dir=directory / label,
    )
    work = cycles(names, rounds, value)
    first, rest = work[: len(names)], work[len(names) :]
    async with subscriber(port, f"spBv1.0/bench/+/{label}/#") as counted:
        for cycle in first:  # born before the session: the births carry them
            sink.reporter.cycle(cycle, live=False, now_ms=0)
        task = asyncio.create_task(sink.run())
        start = time.perf_counter()
        expected = 1 + len(names)  # NBIRTH and a DBIRTH per device
        while not sink.session.live:  # noqa: ASYNC110 - the session's task sets it
            await asyncio.sleep(0.001)
        for cycle in rest:
            messages = sink.reporter.cycle(cycle, live=True, now_ms=1)
            expected += len(messages)
            sink.session.enqueue(messages)
        await wait_for(counted, expected)
        elapsed = time.perf_counter() - start
        births_bytes = sum(len(m.payload) + len(m.topic) for m in sink.births(0, 0))
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    result = figures(len(work) * len(POINTS), counted.messages, counted.bytes, elapsed)
    result["births_bytes"] = births_bytes
    result["data_bytes_per_value"] = (counted.bytes - births_bytes) / (len(rest) * len(POINTS))
    return result


def figures(values: int, messages: int, size: int, elapsed: float) -> dict[str, float]:
    return {
        "values": values,
        "messages": messages,
        "bytes": size,
        "seconds": elapsed,
        "values_per_s": values / elapsed,
        "messages_per_s": messages / elapsed,
        "bytes_per_value": size / values,
        "messages_per_value": messages / values,
    }


async def main_async(args: argparse.Namespace) -> dict[str, dict[str, float]]:
    names = devices(args.buses, args.devices)
    rng = random.Random(1)  # noqa: S311 - repeatable noise
    levels = [20.0 + i for i in range(len(POINTS))]
    with tempfile.TemporaryDirectory() as temp:
        directory = Path(temp)
        with mosquitto(directory) as port:
            result = {"plain": await plain(port, directory, names, args.rounds)}
            result["sparkplug_every_change"] = await sparkplug(
                port,
                directory,
                names,
                args.rounds,
                value=lambda r, i: levels[i] + r * 0.1,
                deadband=DEADBAND,
                label="every",
            )
            result["sparkplug_noise_in_deadband"] = await sparkplug(
                port,
                directory,
                names,
                args.rounds,
                value=lambda _r, i: levels[i] + rng.gauss(0, NOISE),
                deadband=DEADBAND,
                label="steady",
            )
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--buses", type=int, default=16)
    parser.add_argument("--devices", type=int, default=16)
    parser.add_argument("--rounds", type=int, default=20)
    args = parser.parse_args()
    result = asyncio.run(main_async(args))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "sparkplug.json").write_text(json.dumps(result, indent=2), encoding="utf-8")
    for section, values in result.items():
        print(section)
        for key, value in values.items():
            print(
                f"  {key:<24} {value:,.2f}" if isinstance(value, float) else f"  {key:<24} {value}"
            )


if __name__ == "__main__":
    main()
