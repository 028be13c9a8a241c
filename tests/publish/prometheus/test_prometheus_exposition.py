"""The scrape made in pieces and from lazy families: the same bytes as prometheus_client's."""

from __future__ import annotations

import time
from datetime import UTC, datetime
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from gateway.line.samples import Quality, Sample
from gateway.publish.prometheus.endpoint import PIECE_SAMPLES, exposition
from gateway.publish.prometheus.values import value_families
from gateway.shared.state import DeviceInfo, GatewayState
from gateway.wire.codec import BitfieldValue, EnumValue

if TYPE_CHECKING:
    from collections.abc import Iterable

    from gateway.wire.codec import Value

FLAGS = 16
DEVICES = PIECE_SAMPLES // FLAGS + 3  # the status bits' family spans two pieces


class Families(Collector):
    def __init__(self, families: Iterable[Metric]) -> None:
        self.families = list(families)

    def collect(self) -> Iterable[Metric]:
        return self.families


def registry_of(families: Iterable[Metric]) -> CollectorRegistry:
    registry = CollectorRegistry()
    registry.register(Families(families))
    return registry


def sample(device: str, point: str, value: Value, **fields: object) -> Sample:
    """A sample of ``device`` taken ``age_s`` ago (default good, without a unit)."""
    return Sample(
        bus="line1",
        device=device,
        profile="jumo-digiline-odo-s10",
        point=point,
        value=value,
        fault=fields.get("fault"),  # type: ignore[arg-type]
        unit=fields.get("unit"),  # type: ignore[arg-type]
        quality=fields.get("quality", Quality.GOOD),  # type: ignore[arg-type]
        monotonic=fields["at"],  # type: ignore[arg-type]
        time=datetime.now(tz=UTC),
        group="process",
    )


def plant_state(now: float) -> GatewayState:
    state = GatewayState()
    for d in range(DEVICES):
        device = f"dev{d}"
        intervals: dict[str, float | None] = dict.fromkeys(
            ("oxygen", "temperature", "status", "mode", "cap"), 1.0
        )
        intervals["serial"] = None
        state.add_device(
            DeviceInfo(
                bus="line1",
                name=device,
                profile="jumo-digiline-odo-s10",
                address=d + 1,
                intervals=intervals,
            )
        )

        flags = tuple((f"bit{i}", (i + d) % 3 == 0) for i in range(FLAGS))
        at = now - d / 1000  # a device's samples a millisecond older than the one before
        state.record(
            [
                sample(device, "oxygen", 8.25 + d, unit="ppm", at=at),
                sample(device, "temperature", 20.5, unit="°C", at=at),
                sample(device, "status", BitfieldValue(raw=d, flags=flags), at=at),
                sample(
                    device, "mode", EnumValue(code=d % 4, label='quoted "label" \\ here'), at=at
                ),
                sample(device, "serial", 4711 + d, at=at),
                sample(device, "cap", None, quality=Quality.FAULT, fault="overrange", at=at),
            ]
        )
    return state


def test_the_values_families_read_lazily_give_the_lines_they_stand_for() -> None:
    now = time.monotonic()
    families = {m.name: m for m in value_families(plant_state(now).snapshot(), now)}
    flags = list(families["gateway_status_flag"].samples)
    assert len(flags) == DEVICES * FLAGS
    assert flags[FLAGS + 2].labels == {
        "bus": "line1",
        "device": "dev1",
        "profile": "jumo-digiline-odo-s10",
        "point": "status",
        "flag": "bit2",
    }
    assert flags[FLAGS + 2].value == 1.0  # (2 + 1) % 3 == 0
    assert flags[FLAGS + 3].value == 0.0
    # Read twice, the same samples: a family is not used up by one exposition.
    assert list(families["gateway_status_flag"].samples) == flags
    faults = list(families["gateway_value_fault"].samples)
    assert [(s.labels["device"], s.labels["fault"]) for s in faults[:2]] == [
        ("dev0", "overrange"),
        ("dev1", "overrange"),
    ]
    ages = {s.labels["device"]: s.value for s in families["gateway_value_age_seconds"].samples}
    assert ages["dev10"] == now - (now - 10 / 1000)
    assert not any(
        s.labels["point"] == "serial" for s in families["gateway_value_age_seconds"].samples
    )


def test_the_exposition_in_pieces_is_generate_latests_text() -> None:
    now = time.monotonic()
    state = plant_state(now)

    def families() -> list[Metric]:
        counter = CounterMetricFamily("gateway_things", "Things counted", labels=["kind"])
        counter.add_metric(["a"], 3.0, created=1700000000.0)
        small = GaugeMetricFamily("gateway_small", "One\nsample", value=1.5)
        return [small, *value_families(state.snapshot(), now), counter]

    # prometheus_client's text of the same families, made from materialised samples.
    expected_families = []
    for metric in families():
        metric.samples = list(metric.samples)
        expected_families.append(metric)
    expected = generate_latest(registry_of(expected_families))
    pieces = exposition(registry_of(families()))
    assert b"".join(pieces) == expected
    status = [p for p in pieces if b"gateway_status_flag{" in p]
    assert len(status) == 2  # DEVICES * FLAGS lines, cut after PIECE_SAMPLES
    assert status[0].startswith(b"# HELP gateway_status_flag ")
    assert status[0].count(b"\n") == PIECE_SAMPLES + 2
    assert not status[1].startswith(b"#")
