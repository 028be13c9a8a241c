"""Sparkplug B without a broker: payloads, report by exception, seq, and the config section.

Payloads are read back with the hand-written decoder of ``tests/sparkplug_decoder.py``.
Test names that carry a Sparkplug 3.0 statement id (``tck_id_…``) are the proof of that
statement in docs/sparkplug-conformance.md.
"""

from __future__ import annotations

import json
import textwrap
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import pytest

from gateway.config import ConfigProblems, parse_config
from gateway.errors import CommandRejectedError
from gateway.line.samples import Quality
from gateway.profiles import get_profile
from gateway.profiles.model import PollGroup
from gateway.publish.sparkplug import payloads
from gateway.publish.sparkplug.catalogue import DEFAULT_GROUPS, Catalogue
from gateway.publish.sparkplug.reports import Reporter
from gateway.publish.sparkplug.session import HostOfflineError, SparkplugSession
from gateway.publish.sparkplug.topics import SparkplugTopics
from gateway.publish.store import MessageStore
from gateway.wire.codec import EnumValue
from tests.publish.prometheus.test_prometheus import sample
from tests.sparkplug_decoder import command, decode

if TYPE_CHECKING:
    from collections.abc import Collection
    from pathlib import Path

    from gateway.line.samples import Sample
    from gateway.publish.message import Message

S10 = "jumo-digiline-odo-s10"
TOPICS = SparkplugTopics("plant", "gw1")


ALL_GROUPS = [g.value for g in PollGroup]


class FakeClock:
    """Monotonic seconds that move only when a test says so."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def reporter(
    *,
    groups: Collection[str] = DEFAULT_GROUPS,
    clock: FakeClock | None = None,
    wait_s: float = 10.0,
    **deadbands: float,
) -> Reporter:
    profile = get_profile(S10)
    polled = [p.name for p in profile.points if not p.view]
    catalogue = Catalogue.build(
        [("tank", profile, polled)], deadband=0.0, deadbands={"tank": deadbands}, groups=groups
    )
    return Reporter(catalogue, TOPICS, birth_wait_s=wait_s, clock=clock or FakeClock())


def cycle(report: Reporter, *samples: Sample, live: bool = True) -> list[Message]:
    return report.cycle(samples, live=live, now_ms=1)


def s10(point: str, value: Any = None, **options: Any) -> Sample:
    return sample("tank", S10, point, value, **options)


def test_first_cycle_births_then_only_changes_past_the_deadband() -> None:
    report = reporter(temperature=0.5, groups=ALL_GROUPS, wait_s=0.0)
    birth = cycle(report, s10("temperature", 20.0, unit="°C"), s10("oxygen", 8.0, unit="mg/l"))
    assert [m.topic for m in birth] == ["spBv1.0/plant/DBIRTH/gw1/tank"]
    metrics = decode(birth[0].payload).by_name()
    alias = {name: m.alias for name, m in metrics.items()}
    assert metrics["temperature"].value == 20.0
    assert metrics["temperature"].properties["engUnit"] == "°C"
    assert metrics["serial_number"].is_null  # not read yet
    assert metrics["serial_number"].properties["Quality"] == payloads.QUALITY_STALE
    # 20.4 is within 0.5 of 20.0: not news; oxygen changed by 0.01: news (no deadband).
    data = cycle(report, s10("temperature", 20.4), s10("oxygen", 8.01))
    reported = {m.alias: m for m in decode(data[0].payload).metrics}
    assert set(reported) == {alias["oxygen"]}
    assert abs(float(reported[alias["oxygen"]].value) - 8.01) < 1e-6  # type: ignore[arg-type]
    assert "Quality" not in reported[alias["oxygen"]].properties  # good, and good before
    # Drift is measured from the value last reported (20.0), not the last seen (20.4).
    data = cycle(report, s10("temperature", 20.5), s10("oxygen", 8.01))
    assert {m.alias for m in decode(data[0].payload).metrics} == {alias["temperature"]}
    assert cycle(report, s10("temperature", 20.5), s10("oxygen", 8.01)) == []


def test_a_fault_is_null_with_a_bad_quality_and_its_end_is_reported() -> None:
    report = reporter(wait_s=0.0)
    cycle(report, s10("oxygen", 8.0))
    alias = decode(report.dbirth("tank", 1).payload).by_name()["oxygen"].alias
    faulted = cycle(report, s10("oxygen", 2.0e37, fault="overrange", quality=Quality.FAULT))
    metric = decode(faulted[0].payload).by_alias()[alias or 0]
    assert metric.is_null
    assert metric.value is None  # never the fault float
    assert metric.properties == {"Quality": payloads.QUALITY_BAD, "fault": "overrange"}
    assert 2.0e37 not in [m.value for m in decode(faulted[0].payload).metrics]
    # The same fault again is no news; its end is, with the quality good again.
    assert cycle(report, s10("oxygen", 2.0e37, fault="overrange", quality=Quality.FAULT)) == []
    back = cycle(report, s10("oxygen", 8.0))
    metric = decode(back[0].payload).by_alias()[alias or 0]
    assert metric.value == 8.0
    assert metric.properties == {"Quality": payloads.QUALITY_GOOD}


def test_types_on_the_wire_signed_enums_and_dates() -> None:
    report = reporter(groups=ALL_GROUPS, wait_s=0.0)
    stamp = datetime(2026, 5, 4, 3, 2, 1, tzinfo=UTC)
    enum = EnumValue(code=3, label="x")
    cycle(report, s10("commissioning_date", stamp), s10("baud_rate", enum))
    metrics = decode(report.dbirth("tank", 1).payload).by_name()
    assert metrics["commissioning_date"].datatype == "DateTime"
    assert metrics["commissioning_date"].value == int(stamp.timestamp() * 1000)
    assert metrics["baud_rate"].datatype == "UInt16"
    assert metrics["baud_rate"].value == 3
    metric = payloads.new_payload(1).metrics.add()
    payloads.set_value(metric, payloads.SpType.INT16, -5)
    assert metric.int_value == 0xFFFFFFFB  # two's complement in the uint32 field, as Tahu


def test_offline_is_a_ddeath_and_not_live_cycles_are_historical() -> None:
    report = reporter(wait_s=0.0)
    cycle(report, s10("oxygen", 8.0))
    death = report.ddeath("tank", 5)
    assert death is not None
    assert death.topic == "spBv1.0/plant/DDEATH/gw1/tank"
    assert report.ddeath("tank", 6) is None  # dead once
    report.alive("tank")
    # Back while the host is away: born for the next births, nothing to send now ...
    assert cycle(report, s10("oxygen", 8.0), live=False) == []
    assert "tank" in report.born
    # ... and what changes meanwhile is history.
    data = cycle(report, s10("oxygen", 9.0), live=False)
    assert all(m.is_historical for m in decode(data[0].payload).metrics)


class FakeClient:
    """Takes publishes as a broker would, keeping them."""

    def __init__(self) -> None:
        self.published: list[tuple[str, bytes, int, bool]] = []

    async def publish(self, topic: str, payload: bytes, *, qos: int, retain: bool) -> None:
        self.published.append((topic, payload, qos, retain))


async def test_seq_wraps_from_255_to_0_on_every_message(tmp_path: Path) -> None:
    config = parse_config(
        "buses: [{name: a, port: /dev/ttyUSB0}]\nsparkplug: {enabled: true}\n", environ={}
    )
    report = reporter(wait_s=0.0)
    cycle(report, s10("oxygen", 8.0))
    session = SparkplugSession(
        config.mqtt,
        config.sparkplug,
        TOPICS,
        MessageStore(tmp_path / "q.sqlite", max_messages=1000),
        births=report,  # type: ignore[arg-type]
        client_id="test",
        bd_seq_path=tmp_path / "bdseq",
    )
    client = FakeClient()
    await session._birth(client, 7)  # type: ignore[arg-type]
    for value in range(300):
        for message in cycle(report, s10("oxygen", float(value))):
            await session._publish(client, message)  # type: ignore[arg-type]
    seqs = [decode(payload).seq for _, payload, _, _ in client.published]
    assert seqs == [n % 256 for n in range(len(seqs))]
    assert len(seqs) > 256
    assert {qos for _, _, qos, _ in client.published} == {0}
    assert not any(retain for *_, retain in client.published)
    nbirth = decode(client.published[0][1]).by_name()
    assert nbirth["bdSeq"].value == 7
    session.store.close()


def test_bd_seq_goes_on_from_the_last_start(tmp_path: Path) -> None:
    config = parse_config("buses: [{name: a, port: /dev/ttyUSB0}]\n", environ={})

    def session() -> SparkplugSession:
        store = MessageStore(tmp_path / "q.sqlite", max_messages=1000)
        store.close()
        return SparkplugSession(
            config.mqtt,
            config.sparkplug,
            TOPICS,
            store,
            births=reporter(),  # type: ignore[arg-type]
            client_id="t",
            bd_seq_path=tmp_path / "bdseq",
        )

    first = session()
    assert [first._next_bd_seq() for _ in range(3)] == [0, 1, 2]
    assert session()._next_bd_seq() == 3


def test_commands_are_read_strictly() -> None:
    (metric,) = payloads.decode_command(command(("x", "Float", 1.5)))
    assert payloads.command_value(metric, payloads.SpType.FLOAT) == 1.5
    (double,) = payloads.decode_command(command(("x", "Double", 1.5)))
    with pytest.raises(CommandRejectedError, match="is a Float, the command says Double"):
        payloads.command_value(double, payloads.SpType.FLOAT)
    (int16,) = payloads.decode_command(command(("x", "Int16", -2)))
    assert payloads.command_value(int16, payloads.SpType.INT16) == -2
    (untyped,) = payloads.decode_command(command(("x", "Boolean", True), datatype_given=False))
    with pytest.raises(CommandRejectedError, match=r"Float \(float_value\).*boolean_value"):
        payloads.command_value(untyped, payloads.SpType.FLOAT)
    with pytest.raises(CommandRejectedError, match="not a Sparkplug B payload"):
        payloads.decode_command(b"\x0a\xff")
    with pytest.raises(CommandRejectedError, match="no metric"):
        payloads.decode_command(b"")


def test_the_sparkplug_section_is_off_by_default_and_checked() -> None:
    base = "buses: [{name: a, port: /dev/ttyUSB0}]\n"
    assert parse_config(base, environ={}).sparkplug.enabled is False
    text = textwrap.dedent(
        """\
        buses: [{name: a, port: /dev/ttyUSB0}]
        devices: [{name: tank, bus: a, address: 1, profile: jumo-digiline-odo-s10}]
        sparkplug:
          enabled: true
          group_id: "a/b"
          deadband: -1
          deadbands: {tank: {temperatur: 0.1}, nope: {x: 1}}
          surprise: 1
        """
    )
    with pytest.raises(ConfigProblems) as info:
        parse_config(text, environ={})
    found = {(p.key, p.line) for p in info.value.problems}
    assert ("sparkplug.group_id", 5) in found
    assert ("sparkplug.deadband", 6) in found
    assert ("sparkplug.deadbands.tank.temperatur", 7) in found
    assert ("sparkplug.deadbands.nope", 7) in found
    assert ("sparkplug.surprise", 8) in found
    messages = " ".join(p.message for p in info.value.problems)
    assert "did you mean 'temperature'" in messages


def test_a_birth_waits_for_the_unit_register_and_comes_once() -> None:
    clock = FakeClock()
    report = reporter(clock=clock)
    # The first answer without the unit of the oxygen (its unit register not read yet):
    # no birth, and nothing else either.
    assert cycle(report, s10("oxygen", 8.0), s10("temperature", 20.0, unit="°C")) == []
    clock.now += 1.0
    births = cycle(report, s10("oxygen", 8.1, unit="mg/l"), s10("temperature", 20.0))
    assert [m.topic for m in births] == ["spBv1.0/plant/DBIRTH/gw1/tank"]
    metrics = decode(births[0].payload).by_name()
    assert metrics["oxygen"].properties["engUnit"] == "mg/l"
    assert metrics["oxygen"].value == pytest.approx(8.1)
    assert metrics["temperature"].value == 20.0  # kept from the cycle before the birth
    # The same unit again is no news: one DBIRTH, then data.
    data = cycle(report, s10("oxygen", 8.2, unit="mg/l"))
    assert [m.topic for m in data] == ["spBv1.0/plant/DDATA/gw1/tank"]


def test_a_unit_that_never_comes_births_after_the_wait_and_a_later_one_rebirths() -> None:
    clock = FakeClock()
    report = reporter(clock=clock, wait_s=10.0)
    assert cycle(report, s10("oxygen", 8.0)) == []
    clock.now += 9.9
    assert cycle(report, s10("oxygen", 8.0)) == []
    clock.now += 0.1
    first = cycle(report, s10("oxygen", 8.0))
    assert [m.topic for m in first] == ["spBv1.0/plant/DBIRTH/gw1/tank"]
    assert "engUnit" not in decode(first[0].payload).by_name()["oxygen"].properties
    again = cycle(report, s10("oxygen", 8.0, unit="mg/l"))
    assert [m.topic for m in again] == ["spBv1.0/plant/DBIRTH/gw1/tank"]
    assert decode(again[0].payload).by_name()["oxygen"].properties["engUnit"] == "mg/l"
    assert cycle(report, s10("oxygen", 8.0, unit="mg/l")) == []
    changed = cycle(report, s10("oxygen", 8.0, unit="%"))
    assert decode(changed[0].payload).by_name()["oxygen"].properties["engUnit"] == "%"


def test_tck_id_operational_behavior_device_ddeath_a_dead_device_stays_dead() -> None:
    """DDEATH, then nothing of the device until it answers again, then one DBIRTH."""
    report = reporter(wait_s=0.0)
    cycle(report, s10("oxygen", 8.0, unit="mg/l"))
    assert "tank" in report.born
    death = report.ddeath("tank", 5)
    assert death is not None
    # The failed cycle reaches the reporter after the DDEATH: dropped, no DBIRTH of nulls.
    failed = s10("oxygen", None, fault="timeout", quality=Quality.COMMS_ERROR)
    assert cycle(report, failed) == []
    # Even a cycle with an answer in it, while the device is announced offline.
    assert cycle(report, s10("oxygen", 8.0, unit="mg/l"), failed) == []
    assert "tank" not in report.born
    report.alive("tank")
    # Online again, but a cycle without any answer is no birth either.
    assert cycle(report, failed) == []
    back = cycle(report, s10("oxygen", 8.3, unit="mg/l"))
    assert [m.topic for m in back] == ["spBv1.0/plant/DBIRTH/gw1/tank"]
    assert decode(back[0].payload).by_name()["oxygen"].value == pytest.approx(8.3)


def test_quality_has_one_meaning_per_code() -> None:
    report = reporter(groups=ALL_GROUPS, wait_s=0.0)
    births = cycle(
        report,
        s10("oxygen", 2.0e37, unit="mg/l", fault="overrange", quality=Quality.FAULT),
        s10("temperature", None, fault="timeout after 3 tries", quality=Quality.COMMS_ERROR),
        s10("commissioning_date", None),  # registers all zero: a date never set
        s10("temperature_highest", 31.5, unit="°C"),
    )
    metrics = decode(births[0].payload).by_name()
    # Good: the value the sensor holds; null for none, and no fault.
    assert metrics["commissioning_date"].is_null
    assert metrics["commissioning_date"].properties["Quality"] == payloads.QUALITY_GOOD
    assert "fault" not in metrics["commissioning_date"].properties
    assert metrics["temperature_highest"].properties["Quality"] == payloads.QUALITY_GOOD
    # Bad: the sensor sent a fault, named.
    assert metrics["oxygen"].properties["Quality"] == payloads.QUALITY_BAD
    assert metrics["oxygen"].properties["fault"] == "overrange"
    # Stale: no current reading (the read failed), null, no fault.
    assert metrics["temperature"].is_null
    assert metrics["temperature"].properties["Quality"] == payloads.QUALITY_STALE
    assert "fault" not in metrics["temperature"].properties
    # The property's codes are the three Sparkplug 3.0 allows, always an Int32.
    for metric in decode(births[0].payload).metrics:
        assert metric.properties["Quality"] in {0, 192, 500}


def test_an_enum_carries_its_label_in_a_string_metric_beside_its_code() -> None:
    report = reporter(groups=ALL_GROUPS, wait_s=0.0)
    births = cycle(report, s10("analog_output_function", EnumValue(code=2, label="standard")))
    metrics = decode(births[0].payload).by_name()
    code, label = metrics["analog_output_function"], metrics["analog_output_function/label"]
    assert (code.datatype, code.value) == ("UInt16", 2)
    assert (label.datatype, label.value) == ("String", "standard")
    assert label.properties["readOnly"] is True
    assert code.properties["readOnly"] is False
    # A new code: both change, in one DDATA.
    data = cycle(report, s10("analog_output_function", EnumValue(code=1, label="fixed_value")))
    changed = {m.alias: m.value for m in decode(data[0].payload).metrics}
    assert changed == {code.alias: 1, label.alias: "fixed_value"}


def test_a_host_gets_process_and_status_by_default_and_the_groups_it_asks_for() -> None:
    profile = get_profile(S10)
    polled = [p.name for p in profile.points if not p.view]
    default = Catalogue.build([("tank", profile, polled)]).devices["tank"]
    groups = {m.point.group for m in default.metrics if m.point is not None}
    assert groups == {PollGroup.PROCESS, PollGroup.STATUS}
    assert "Write/Result" in default.by_name
    every = Catalogue.build([("tank", profile, polled)], groups=ALL_GROUPS).devices["tank"]
    assert len(every.metrics) > 3 * len(default.metrics)
    own = Catalogue.build(
        [("tank", profile, polled), ("other", profile, polled)],
        device_groups={"tank": ["diagnostics"]},
    ).devices
    assert {m.point.group for m in own["tank"].metrics if m.point} == {PollGroup.DIAGNOSTICS}
    assert {m.point.group for m in own["other"].metrics if m.point} == groups
    text = (
        "buses: [{name: a, port: /dev/ttyUSB0}]\n"
        "devices: [{name: tank, bus: a, address: 1, profile: jumo-digiline-odo-s10}]\n"
        "sparkplug: {groups: [process, diagnostics], device_groups: {tank: [status]}}\n"
    )
    config = parse_config(text, environ={}).sparkplug
    assert config.groups == [PollGroup.PROCESS, PollGroup.DIAGNOSTICS]
    assert config.device_groups == {"tank": [PollGroup.STATUS]}
    bad = text.replace("[process, diagnostics]", "[process, logbook]").replace("{tank:", "{tnk:")
    with pytest.raises(ConfigProblems) as info:
        parse_config(bad, environ={})
    found = {p.key for p in info.value.problems}
    assert found == {"sparkplug.groups[1]", "sparkplug.device_groups.tnk"}


def test_tck_id_operational_behavior_data_commands_rebirth_name_aliases() -> None:
    """NBIRTH's ``Node Control/Rebirth``: Boolean, false, and without an alias."""
    nbirth = decode(reporter().nbirth(3, 1).payload).by_name()
    rebirth = nbirth["Node Control/Rebirth"]
    assert rebirth.alias is None
    assert (rebirth.datatype, rebirth.value) == ("Boolean", False)
    assert nbirth["bdSeq"].alias is None


def state_session(tmp_path: Path) -> SparkplugSession:
    config = parse_config(
        "buses: [{name: a, port: /dev/ttyUSB0}]\n"
        "sparkplug: {enabled: true, primary_host_id: scada}\n",
        environ={},
    )
    store = MessageStore(tmp_path / "q.sqlite", max_messages=1000)
    store.close()
    return SparkplugSession(
        config.mqtt,
        config.sparkplug,
        SparkplugTopics("plant", "gw1", "scada"),
        store,
        births=reporter(),  # type: ignore[arg-type]
        client_id="t",
        bd_seq_path=tmp_path / "bdseq",
    )


def state(*, online: bool, timestamp: int) -> bytes:
    return json.dumps({"online": online, "timestamp": timestamp}).encode()


def test_tck_id_operational_behavior_edge_node_termination_host_offline_timestamp(
    tmp_path: Path,
) -> None:
    """An offline STATE older than the online one acted on is ignored; a newer one ends it."""
    session = state_session(tmp_path)
    session._host_state(state(online=True, timestamp=2000))
    assert session.host_online
    session._host_state(state(online=False, timestamp=1999))  # a stale will: ignored
    assert session.host_online
    session._host_state(state(online=True, timestamp=1000))  # older, though online: ignored
    assert session.host_timestamp == 2000
    # The will of the session the host is in carries its birth's timestamp: acted on.
    with pytest.raises(HostOfflineError):
        session._host_state(state(online=False, timestamp=2000))
    assert not session.host_online
    session._host_state(state(online=True, timestamp=3000))
    assert session.host_online
    with pytest.raises(HostOfflineError):
        session._host_state(b"OFFLINE")  # Sparkplug 2.2: no timestamp to compare


def test_an_ncmd_names_the_rebirth_metric_by_name_only() -> None:
    from gateway.publish.sparkplug.session import _node_command_metrics  # noqa: PLC0415

    assert _node_command_metrics(command(("Node Control/Rebirth", "Boolean", True))) == [True]
    with pytest.raises(CommandRejectedError, match="no metric alias 1"):
        _node_command_metrics(command((1, "Boolean", True)))
