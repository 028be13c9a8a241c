"""Sparkplug B without a broker: payloads, report by exception, seq, and the config section.

Payloads are read back with the hand-written decoder of ``tests/sparkplug_decoder.py``.
"""

from __future__ import annotations

import textwrap
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import pytest

from gateway.config import ConfigProblems, parse_config
from gateway.errors import CommandRejectedError
from gateway.line.samples import Quality
from gateway.profiles import get_profile
from gateway.publish.sparkplug import payloads
from gateway.publish.sparkplug.catalogue import Catalogue
from gateway.publish.sparkplug.reports import Reporter
from gateway.publish.sparkplug.session import SparkplugSession
from gateway.publish.sparkplug.topics import SparkplugTopics
from gateway.publish.store import MessageStore
from gateway.wire.codec import EnumValue
from tests.sinks.test_prometheus import sample
from tests.sparkplug_decoder import command, decode

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.line.samples import Sample
    from gateway.publish.message import Message

S10 = "jumo-digiline-odo-s10"
TOPICS = SparkplugTopics("plant", "gw1")


def reporter(**deadbands: float) -> Reporter:
    profile = get_profile(S10)
    polled = [p.name for p in profile.points if not p.view]
    catalogue = Catalogue.build(
        [("tank", profile, polled)], deadband=0.0, deadbands={"tank": deadbands}
    )
    return Reporter(catalogue, TOPICS)


def cycle(report: Reporter, *samples: Sample, live: bool = True) -> list[Message]:
    return report.cycle(samples, live=live, now_ms=1)


def s10(point: str, value: Any = None, **options: Any) -> Sample:
    return sample("tank", S10, point, value, **options)


def test_first_cycle_births_then_only_changes_past_the_deadband() -> None:
    report = reporter(temperature=0.5)
    birth = cycle(report, s10("temperature", 20.0, unit="°C"), s10("oxygen", 8.0))
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
    report = reporter()
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
    report = reporter()
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
    report = reporter()
    cycle(report, s10("oxygen", 8.0))
    death = report.ddeath("tank", 5)
    assert death is not None
    assert death.topic == "spBv1.0/plant/DDEATH/gw1/tank"
    assert report.ddeath("tank", 6) is None  # dead once
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
    report = reporter()
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


def test_a_unit_read_after_the_birth_is_told_by_a_new_dbirth() -> None:
    report = reporter()
    first = cycle(report, s10("oxygen", 8.0))  # the unit register not read yet
    assert "engUnit" not in decode(first[0].payload).by_name()["oxygen"].properties
    again = cycle(report, s10("oxygen", 8.0, unit="mg/l"))
    assert [m.topic for m in again] == ["spBv1.0/plant/DBIRTH/gw1/tank"]
    assert decode(again[0].payload).by_name()["oxygen"].properties["engUnit"] == "mg/l"
    assert cycle(report, s10("oxygen", 8.0, unit="mg/l")) == []
    changed = cycle(report, s10("oxygen", 8.0, unit="%"))
    assert decode(changed[0].payload).by_name()["oxygen"].properties["engUnit"] == "%"
