"""Grab-sample verification without I/O: the acceptance rule at its boundaries, the window.

EPA Method 334.0: the online value within ±0.1 mg/L or ±15 % of the grab sample's,
whichever is larger: at a 0.50 mg/L reference ±0.10, at 2.00 ±0.30, and a deviation
exactly on the limit passes. The sensor's value is a float32 as it sends it.
"""

from __future__ import annotations

import struct
from datetime import UTC, datetime, timedelta
from decimal import Decimal

import pytest

from gateway.config.verification import AcceptanceRuleConfig, VerificationConfig
from gateway.control.verification import VerificationRequest, verifiable_point
from gateway.errors import CommandRejectedError
from gateway.line.samples import Quality, Sample
from gateway.profiles import get_profile
from gateway.records.recent import RecentValues
from gateway.records.verification import EPA_334, OXYGEN_DEFAULT, judge, rule_for, same_unit

NOW = datetime(2026, 12, 2, 9, 0, tzinfo=UTC)


def f32(value: float) -> float:
    """``value`` as the sensor sends it: the nearest float32."""
    return float(struct.unpack(">f", struct.pack(">f", value))[0])


@pytest.mark.parametrize(
    ("reference", "sensor", "limit", "passed"),
    [
        (0.50, 0.60, "0.1", True),  # +0.10: on the limit passes
        (0.50, 0.40, "0.1", True),  # -0.10
        (0.50, 0.61, "0.1", False),
        (0.50, 0.39, "0.1", False),
        (2.00, 2.30, "0.30", True),  # 15 % of 2.00 is larger than 0.1
        (2.00, 1.70, "0.30", True),  # 2.00 - 1.70 is 0.30, not 0.30000000000000004
        (2.00, 2.31, "0.30", False),
        (2.00, 1.69, "0.30", False),
        (0.666, 0.766, "0.1", True),  # 15 % is 0.0999: the 0.1 holds
        (1.0, 1.15, "0.15", True),  # 15 % of 1.0 is 0.15, larger than 0.1
    ],
)
def test_epa_334_at_its_boundaries(
    reference: float, sensor: float, limit: str, *, passed: bool
) -> None:
    judged = judge(EPA_334, reference=reference, sensor=f32(sensor))
    assert judged.limit == Decimal(limit)
    assert judged.passed is passed
    assert judged.deviation == Decimal(repr(sensor)) - Decimal(repr(reference))


def test_the_rule_in_the_record_has_its_name_and_parameters() -> None:
    assert EPA_334.as_dict() == {
        "name": "EPA 334.0",
        "absolute": 0.1,
        "relative": 0.15,
        "unit": "mg/l",
        "source": EPA_334.source,
    }
    assert "334.0" in EPA_334.source


def test_a_rule_by_device_then_profile_then_family_then_built_in() -> None:
    tecline = get_profile("jumo-tecline-clo2")
    rule = AcceptanceRuleConfig(name="SOP 12", absolute=0.05, relative=0.1, unit="mg/l")
    other = AcceptanceRuleConfig(name="SOP 13", absolute=0.2, relative=0.0)
    config = VerificationConfig(rules={"jumo-tecline-clo2": rule, "basin_2": other})
    assert rule_for(config, device="basin_2", profile=tecline).name == "SOP 13"  # type: ignore[union-attr]
    assert rule_for(config, device="basin_1", profile=tecline).name == "SOP 12"  # type: ignore[union-attr]
    by_family = VerificationConfig(rules={"jumo-tecline": other})
    assert rule_for(by_family, device="x", profile=tecline).name == "SOP 13"  # type: ignore[union-attr]
    assert rule_for(VerificationConfig(), device="x", profile=tecline) == EPA_334
    s10 = get_profile("jumo-digiline-odo-s10")
    assert rule_for(VerificationConfig(), device="x", profile=s10) == OXYGEN_DEFAULT


def test_units_compare_as_water_chemists_write_them() -> None:
    assert same_unit("mg/L", "mg/l")
    assert same_unit("ppm", "mg/l")
    assert not same_unit("%sat", "mg/l")
    assert same_unit(None, "mg/l")


def test_a_request_is_checked_where_it_comes_in() -> None:
    request = VerificationRequest.from_arguments(
        {"reference": 0.5, "method": "DPD", "sampled_at": "2026-12-02T08:40:00"}
    )
    assert request.sampled_at == datetime(2026, 12, 2, 8, 40, tzinfo=UTC)  # UTC if no zone
    cases: list[tuple[dict[str, object], str]] = [
        ({"method": "DPD"}, "reference must be a number"),
        ({"reference": "0.5", "method": "DPD"}, "reference must be a number"),
        ({"reference": -1, "method": "DPD"}, "0 or more"),
        ({"reference": 0.5}, "method is needed"),
        ({"reference": 0.5, "method": "DPD", "colour": "pink"}, "unknown keys"),
        ({"reference": 0.5, "method": "DPD", "sampled_at": "yesterday"}, "not an ISO 8601"),
    ]
    for wrong, said in cases:
        with pytest.raises(CommandRejectedError, match=said):
            VerificationRequest.from_arguments(wrong)


def test_the_process_value_is_what_is_verified() -> None:
    assert verifiable_point(get_profile("reiss-m0c")).name == "concentration"
    assert verifiable_point(get_profile("jumo-digiline-odo-h10")).name == "oxygen"
    with pytest.raises(CommandRejectedError, match="not a measured value"):
        verifiable_point(get_profile("reiss-m0c"), "serial_number")


def sample(at: datetime, value: float, *, quality: Quality = Quality.GOOD) -> Sample:
    return Sample(
        bus="line1",
        device="basin",
        profile="reiss-m0c",
        point="concentration",
        value=value,
        fault=None,
        unit="mg/l",
        quality=quality,
        monotonic=0.0,
        time=at,
        group="process",
    )


async def test_a_sample_entered_20_minutes_late_is_compared_with_the_value_then() -> None:
    recent = RecentValues({"basin": "concentration"}, window_s=3600, resolution_s=10)
    start = NOW - timedelta(minutes=30)
    for second in range(0, 30 * 60, 1):  # a poll a second for half an hour, falling
        await recent.publish([sample(start + timedelta(seconds=second), 1.0 - second / 3600)])
    then = NOW - timedelta(minutes=20)
    found = recent.value_at("basin", "concentration", then, now=NOW)
    assert found.at == then
    assert found.value == pytest.approx(1.0 - 600 / 3600)  # 10 min into the half hour
    assert found.unit == "mg/l"
    latest = recent.value_at("basin", "concentration", NOW - timedelta(seconds=5), now=NOW)
    assert latest.value < found.value


async def test_the_window_is_bounded_and_says_why_it_refuses() -> None:
    recent = RecentValues({"basin": "concentration"}, window_s=600, resolution_s=10)
    assert recent.capacity == 61  # values per device: 600 s at 10 s, and one more
    for minute in range(20):
        await recent.publish([sample(NOW - timedelta(minutes=20 - minute), 0.5)])
    with pytest.raises(CommandRejectedError, match="more than the 10 min of values"):
        recent.value_at("basin", "concentration", NOW - timedelta(minutes=11), now=NOW)
    with pytest.raises(CommandRejectedError, match="in the future"):
        recent.value_at("basin", "concentration", NOW + timedelta(minutes=1), now=NOW)
    await recent.publish([sample(NOW - timedelta(seconds=2), 0.5, quality=Quality.FAULT)])
    with pytest.raises(CommandRejectedError, match="no good concentration value within 20 s"):
        recent.value_at("basin", "concentration", NOW - timedelta(seconds=2), now=NOW)
