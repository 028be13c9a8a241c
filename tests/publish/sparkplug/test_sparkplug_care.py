"""Sensor care in Sparkplug B: the ``care`` group's metrics, in births and by exception.

The care reports come from a real :class:`~gateway.care.CareBook` fed with hand-made poll
cycles of a tecLine's calibration records (on a clock the test moves), as the running
gateway feeds it; the births and data go through a real mosquitto and are read with the
hand-written decoder of ``tests/sparkplug_decoder.py``.
"""

from __future__ import annotations

import asyncio
import contextlib
import textwrap
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING

import pytest

from gateway.care import CareBook, CareReport, CareState, Finding, resolve
from gateway.config import ConfigProblems, parse_config
from gateway.profiles import PollGroup, get_profile
from gateway.publish.sparkplug import SparkplugSink
from gateway.publish.sparkplug.catalogue import Catalogue
from gateway.publish.sparkplug.payloads import QUALITY_GOOD, QUALITY_STALE, epoch_ms
from gateway.publish.sparkplug.reports import Reporter
from gateway.publish.sparkplug.topics import SparkplugTopics
from gateway.shared.state import GatewayState, StateSink
from gateway.wire.codec import EnumValue
from tests.mqtt_broker import Broker
from tests.publish.prometheus.test_prometheus import sample
from tests.publish.sparkplug.test_sparkplug import SpRecorder, sp_recording
from tests.sparkplug_decoder import DecodedMetric, DecodedPayload, decode

if TYPE_CHECKING:
    from collections.abc import AsyncIterator
    from pathlib import Path

    from gateway.line.samples import Sample
    from gateway.wire.codec import Value

TECLINE = "jumo-tecline-cl2"
H10 = "jumo-digiline-odo-h10"
S10 = "jumo-digiline-odo-s10"
NODE, EDGE = "spBv1.0/plant", "gw1"
NOW = datetime(2026, 3, 10, 12, 0, tzinfo=UTC)
NOMINAL_SLOPE = 22.0  # nA/ppm, the tecLine's 0x030A (annex 7.5.1)
SLOPE_044 = 0.44 * NOMINAL_SLOPE  # an active slope at 44 % of nominal
EVERY_CARE_METRIC = {
    "care/state": "String",
    "care/reasons": "String",
    "care/last_calibration": "DateTime",
    "care/due": "DateTime",
    "care/slope_ratio": "Double",
    "care/slope_limit_projected": "DateTime",
    "care/cap_usage": "Double",
}
COMMON = {"care/state", "care/reasons", "care/last_calibration", "care/due"}


class Clock:
    """The care book's time, moved by the test."""

    def __init__(self) -> None:
        self.now = NOW

    def __call__(self) -> datetime:
        return self.now


def care_records(calibrations: list[tuple[datetime, float]]) -> dict[str, Value]:
    """A tecLine's calibration records: ``(stamp, slope)`` newest first, the rest empty.

    The active calibration is history entry 0, as the sensor keeps it (annex 7.2); the
    stamps are zone-less, as the sensor holds them.
    """
    stamp, span = calibrations[0]
    values: dict[str, Value] = {
        "x_zero": 1.0,
        "x_span": span,
        "calibration_stamp": stamp.replace(tzinfo=None),
        "nominal_slope": NOMINAL_SLOPE,
        "unit": EnumValue(code=3, label="ppm"),
    }
    for index in range(5):
        when, slope = calibrations[index] if index < len(calibrations) else (None, 0.0)
        values[f"history_{index}_x_zero"] = 1.0 if when is not None else 0.0
        values[f"history_{index}_x_span"] = slope
        values[f"history_{index}_stamp"] = when.replace(tzinfo=None) if when else None
    return values


def poll_cycle(
    device: str, calibrations: list[tuple[datetime, float]], *, temperature: float = 20.0
) -> list[Sample]:
    """One poll cycle of a tecLine: its process values and its care records."""
    process: dict[str, Value] = {"concentration": 0.5, "cell_current": 12.0}
    samples = [sample(device, TECLINE, name, value) for name, value in process.items()]
    samples[0] = sample(device, TECLINE, "concentration", 0.5, unit="ppm")
    samples.append(sample(device, TECLINE, "temperature", temperature, unit="°C"))
    records = care_records(calibrations)
    return [*samples, *(sample(device, TECLINE, name, v) for name, v in records.items())]


def care_book(clock: Clock, *devices: str) -> CareBook:
    book = CareBook(clock=clock, zone=UTC)
    profile = get_profile(TECLINE)
    for device in devices:
        book.add_device(
            bus="line1",
            device=device,
            profile=profile,
            rules=resolve(profile, []),
            polled=[p.name for p in profile.points],
        )
    return book


def care_of(payload: DecodedPayload) -> dict[str, DecodedMetric]:
    return {name: m for name, m in payload.by_name().items() if name.startswith("care/")}


# --- the config ------------------------------------------------------------------------


def test_care_is_a_group_a_host_may_ask_for_and_anything_else_is_named_with_its_line() -> None:
    text = textwrap.dedent(
        """\
        buses: [{name: a, port: /dev/ttyUSB0}]
        devices: [{name: basin, bus: a, address: 1, profile: jumo-tecline-cl2}]
        sparkplug:
          groups: [process, care]
          device_groups: {basin: [status, care]}
        """
    )
    settings = parse_config(text, environ={}).sparkplug
    assert settings.groups == [PollGroup.PROCESS, "care"]
    assert settings.device_groups == {"basin": [PollGroup.STATUS, "care"]}
    bad = text.replace("[process, care]", "[process, cares]").replace("[status, care]", "[x]")
    with pytest.raises(ConfigProblems) as info:
        parse_config(bad, environ={})
    found = {(p.key, p.line): p.message for p in info.value.problems}
    assert set(found) == {("sparkplug.groups[1]", 4), ("sparkplug.device_groups.basin[0]", 5)}
    choices = ", ".join([*(g.value for g in PollGroup), "care"])
    assert found["sparkplug.groups[1]", 4] == f"'cares' is not a Sparkplug group: one of {choices}"
    assert found["sparkplug.device_groups.basin[0]", 5].startswith("'x' is not a Sparkplug group")


# --- the catalogue and the reporter, without a broker ---------------------------------


@pytest.mark.parametrize(
    ("profile_id", "figures"),
    [
        (TECLINE, {"care/slope_ratio", "care/slope_limit_projected"}),
        ("reiss-m0c", {"care/slope_ratio", "care/slope_limit_projected"}),
        (H10, {"care/cap_usage"}),
        (S10, set()),
    ],
)
def test_each_family_gets_the_care_metrics_it_has_figures_for(
    profile_id: str, figures: set[str]
) -> None:
    profile = get_profile(profile_id)
    polled = [p.name for p in profile.points if not p.view]
    plain = Catalogue.build([("d", profile, polled)]).devices["d"]
    assert not plain.care
    assert not [m for m in plain.metrics if m.name.startswith("care/")]
    groups = ["process", "status", "care"]
    metrics = Catalogue.build([("d", profile, polled)], groups=groups).devices["d"]
    care = {m.name: m for m in metrics.care}
    assert set(care) == COMMON | figures
    for name, spec in care.items():
        assert spec.datatype.name.lower() == EVERY_CARE_METRIC[name].lower()
        assert spec.point is None
        assert not spec.writable
        assert spec.description.startswith("sensor care: ")
        assert metrics.by_name[name] is spec
    # Added to the metrics of the poll groups, before Write/Result; aliases stay unique.
    assert [m.name for m in metrics.metrics if m.care is None] == [m.name for m in plain.metrics]
    assert [m.name for m in metrics.metrics[-len(care) - 1 :]] == [*care, "Write/Result"]
    aliases = [m.alias for m in metrics.metrics]
    assert len(set(aliases)) == len(aliases)


class FakeCare:
    """A care source of hand-made reports (the :class:`CareSource` a book is)."""

    def __init__(self, tracked: set[str]) -> None:
        self.reports: dict[str, CareReport] = {}
        self.versions: dict[str, int] = {}
        self.followed = tracked

    def put(self, report: CareReport) -> None:
        self.reports[report.device] = report
        self.versions[report.device] = self.versions.get(report.device, 0) + 1

    def report(self, device: str) -> CareReport | None:
        return self.reports.get(device)

    def version(self, device: str) -> int:
        return self.versions.get(device, 0)

    def tracked(self, device: str) -> bool:
        return device in self.followed


def h10_report(**figures: object) -> CareReport:
    fields: dict[str, object] = {
        "device": "tank",
        "bus": "line1",
        "profile": H10,
        "kind": "optical_hygienic",
        "state": CareState.MAINTENANCE,
        "findings": (
            Finding(state=CareState.OK, text="calibrate by Tue 17 Mar 2026"),
            Finding(state=CareState.MAINTENANCE, text="the cap is worn out: replace it"),
        ),
        "assessed_at": NOW,
        "interval_days": 30.0,
        "interval_source": "gateway default",
        "cap_usage": 1.0,
    }
    return CareReport(**(fields | figures))  # type: ignore[arg-type]


def test_births_carry_nulls_before_the_first_report_and_none_for_a_device_care_skips() -> None:
    profile = get_profile(H10)
    polled = [p.name for p in profile.points if not p.view]
    catalogue = Catalogue.build(
        [("tank", profile, polled), ("other", profile, polled)], groups=["process", "care"]
    )
    care = FakeCare(tracked={"tank"})  # care switched off for "other" in the config
    report = Reporter(catalogue, SparkplugTopics("plant", EDGE), birth_wait_s=0.0, care=care)

    def h10(device: str) -> list[Sample]:
        return [sample(device, H10, "temperature", 20.0, unit="°C")]

    birth = decode(report.cycle(h10("tank"), live=True, now_ms=5)[0].payload)
    before = care_of(birth)
    assert set(before) == COMMON | {"care/cap_usage"}
    for metric in before.values():
        assert metric.is_null
        assert metric.properties["Quality"] == QUALITY_STALE  # not assessed yet
        assert metric.properties["readOnly"] is True
    other = decode(report.cycle(h10("other"), live=True, now_ms=5)[0].payload)
    assert not care_of(other)
    # The first report: every care metric good, in the next DDATA with the values.
    care.put(h10_report())
    data = decode(report.cycle(h10("tank"), live=True, now_ms=6)[0].payload).by_alias()
    alias = {name: m.alias or 0 for name, m in before.items()}
    assert set(data) == set(alias.values())
    assert data[alias["care/state"]].value == "maintenance"
    assert data[alias["care/reasons"]].value == (
        "the cap is worn out: replace it; calibrate by Tue 17 Mar 2026"
    )
    assert data[alias["care/cap_usage"]].value == 1.0
    assert data[alias["care/due"]].is_null  # good, and none: no logbook date to count from
    assert data[alias["care/due"]].properties["Quality"] == QUALITY_GOOD
    assert data[alias["care/state"]].timestamp == epoch_ms(NOW)
    # A new report whose cap figure only changed: that metric alone.
    care.put(h10_report(cap_usage=0.5))
    data = decode(report.cycle(h10("tank"), live=True, now_ms=7)[0].payload).by_alias()
    assert {a: m.value for a, m in data.items()} == {alias["care/cap_usage"]: 0.5}
    # Dead and born again: the birth carries the care as it stands.
    report.ddeath("tank", 8)
    report.alive("tank")
    again = care_of(decode(report.cycle(h10("tank"), live=True, now_ms=9)[0].payload))
    assert again["care/cap_usage"].value == 0.5
    assert again["care/state"].value == "maintenance"
    assert again["care/state"].properties["Quality"] == QUALITY_GOOD


# --- through a real broker ---------------------------------------------------------------


@contextlib.asynccontextmanager
async def edge_node(
    tmp_path: Path, port: int, state: GatewayState, seen: SpRecorder
) -> AsyncIterator[SparkplugSink]:
    """The Sparkplug sink of two tecLines, ``basin`` with care and ``pool`` without, live."""
    text = textwrap.dedent(
        f"""\
        buses: [{{name: line1, port: /dev/ttyUSB0}}]
        devices:
          - {{name: basin, bus: line1, address: 1, profile: {TECLINE}}}
          - {{name: pool, bus: line1, address: 2, profile: {TECLINE}}}
        mqtt: {{host: 127.0.0.1, port: {port}, reconnect_max_s: 1}}
        sparkplug:
          enabled: true
          group_id: plant
          edge_node_id: {EDGE}
          birth_wait_s: 0
          device_groups: {{basin: [process, status, care]}}
        """
    )
    config = parse_config(text, environ={})
    profile = get_profile(TECLINE)
    polled = [p.name for p in profile.points if not p.view]
    sink = SparkplugSink(
        config.sparkplug,
        config.mqtt,
        [("basin", profile, polled), ("pool", profile, polled)],
        state_dir=tmp_path,
        state=state,
    )
    task = asyncio.create_task(sink.run(), name="test[sparkplug]")
    try:
        await seen.wait_for(f"{NODE}/NBIRTH/{EDGE}")  # the session is live
        yield sink
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


@dataclass
class Run:
    """What the host saw of a run, and the care book at its end."""

    seen: SpRecorder
    state: GatewayState

    def births(self, device: str) -> list[DecodedPayload]:
        return self.seen.on(f"{NODE}/DBIRTH/{EDGE}/{device}")

    def data(self, device: str) -> list[DecodedPayload]:
        return self.seen.on(f"{NODE}/DDATA/{EDGE}/{device}")


async def care_run(tmp_path: Path, port: int) -> Run:
    """Births; an unchanged report, then a process value; a calibration; a projection."""
    clock = Clock()
    state = GatewayState(care=care_book(clock, "basin", "pool"))
    first = [(NOW - timedelta(days=10), SLOPE_044)]  # a week's interval: overdue 3 days
    async with (
        sp_recording(port) as seen,
        edge_node(tmp_path, port, state, seen) as sink,
    ):

        async def poll(cycle: list[Sample]) -> None:
            # As the bus task hands a cycle to the sinks: the state's (and its care book)
            # first, then Sparkplug's.
            await StateSink(state).publish(cycle)
            await sink.publish(cycle)

        await poll(poll_cycle("pool", first))
        await poll(poll_cycle("basin", first))
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/basin")
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/pool")
        # Unchanged: time alone (an hour) changes no care figure; nor does the same cycle.
        clock.now += timedelta(hours=1)
        await poll(poll_cycle("basin", first))
        # Then only a process value changes: the first DDATA carries it and nothing else.
        await poll(poll_cycle("basin", first, temperature=21.0))
        await seen.wait_for(f"{NODE}/DDATA/{EDGE}/basin")
        # A new calibration, its slope the same: what depends on the date changes.
        clock.now += timedelta(minutes=30)
        second = [(clock.now - timedelta(minutes=10), SLOPE_044), *first]
        await poll(poll_cycle("basin", second, temperature=21.0))
        await seen.wait_for(f"{NODE}/DDATA/{EDGE}/basin", count=2)
        # A falling slope over four weekly calibrations: now there is a projection.
        falling = [
            (clock.now - timedelta(days=7 * weeks), SLOPE_044 * (1 + 0.125 * weeks))
            for weeks in range(4)
        ]
        falling[0] = (clock.now - timedelta(minutes=5), SLOPE_044)
        await poll(poll_cycle("basin", falling, temperature=21.0))
        await seen.wait_for(f"{NODE}/DDATA/{EDGE}/basin", count=3)
    return Run(seen, state)


@pytest.mark.broker
async def test_a_dbirth_carries_the_care_report_typed_only_with_the_care_group(
    tmp_path: Path, broker: Broker
) -> None:
    run = await care_run(tmp_path, broker.port)
    # Without `care` in its groups, a device has no care metric, though care follows it.
    assert run.state.care.report("pool") is not None
    assert not care_of(run.births("pool")[0])
    # With it, its birth carries the report as it was, typed.
    birth = care_of(run.births("basin")[0])
    assert {name: m.datatype for name, m in birth.items()} == {
        name: kind for name, kind in EVERY_CARE_METRIC.items() if name != "care/cap_usage"
    }
    calibrated = NOW - timedelta(days=10)
    assert birth["care/state"].value == "due"
    reasons = str(birth["care/reasons"].value)
    assert reasons.startswith("check the calibration: overdue for 3 days, due Sat 7 Mar 2026")
    assert reasons.endswith("; slope 44% of nominal")
    assert birth["care/last_calibration"].value == epoch_ms(calibrated)
    assert birth["care/due"].value == epoch_ms(calibrated + timedelta(days=7))
    assert birth["care/slope_ratio"].value == 0.44
    assert birth["care/slope_limit_projected"].is_null  # one calibration: no trend
    assert birth["care/slope_limit_projected"].value is None
    for metric in birth.values():
        assert metric.properties["Quality"] == QUALITY_GOOD
        assert metric.properties["readOnly"] is True
        assert str(metric.properties["description"]).startswith("sensor care: ")
        assert metric.timestamp == epoch_ms(NOW)  # when it was assessed


@pytest.mark.broker
async def test_a_ddata_carries_only_the_care_metrics_that_changed(
    tmp_path: Path, broker: Broker
) -> None:
    run = await care_run(tmp_path, broker.port)
    birth = run.births("basin")[0].by_name()
    name_of = {m.alias: name for name, m in birth.items()}
    unchanged, calibration, projected = run.data("basin")
    # The same report (an hour later) sent nothing; a new temperature only itself.
    assert [m.alias for m in unchanged.metrics] == [birth["temperature"].alias]
    # A calibration today: state, reasons and dates; the slope and its projection are as
    # they were, so not in it.
    changed = {name_of[m.alias or 0]: m for m in calibration.metrics}
    assert set(changed) == {"care/state", "care/reasons", "care/last_calibration", "care/due"}
    assert changed["care/state"].value == "ok"
    when = NOW + timedelta(hours=1, minutes=20)
    assert changed["care/last_calibration"].value == epoch_ms(when)
    assert changed["care/due"].value == epoch_ms(when + timedelta(days=7))
    assert "Quality" not in changed["care/state"].properties  # good, and good before
    assert all(m.name is None and m.datatype is None for m in calibration.metrics)
    # The projection appears; the state (ok) and the slope (44 %) stay out.
    latest = run.state.care.report("basin")
    assert latest is not None
    assert latest.projection is not None
    changed = {name_of[m.alias or 0]: m for m in projected.metrics}
    assert set(changed) == {
        "care/reasons",
        "care/last_calibration",
        "care/due",
        "care/slope_limit_projected",
    }
    assert changed["care/slope_limit_projected"].value == epoch_ms(latest.projection.at)
    assert changed["care/reasons"].value == "; ".join(latest.reasons)
