"""Set payloads parsed, typed by their point, encoded, or rejected with a clear reason."""

from __future__ import annotations

import pytest

from gateway.control.commands import (
    SetCommand,
    function_for,
    parse_set_payload,
    validate_write,
    writable_point,
)
from gateway.errors import CommandRejectedError
from gateway.profiles import get_profile
from gateway.profiles.model import Profile
from gateway.wire.codec import WordOrder

CDAB = WordOrder.CDAB


@pytest.fixture(scope="module")
def s10() -> Profile:
    return get_profile("jumo-digiline-odo-s10")


@pytest.fixture(scope="module")
def h10() -> Profile:
    return get_profile("jumo-digiline-odo-h10")


@pytest.fixture(scope="module")
def tecline() -> Profile:
    return get_profile("jumo-tecline-cl2")


def rejected(profile: Profile, point: str, value: object) -> CommandRejectedError:
    with pytest.raises(CommandRejectedError) as info:
        validate_write(profile, writable_point(profile, point), value, float_order=CDAB)
    assert info.value.point == point
    return info.value


# --- parsing ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("payload", "expected"),
    [
        (b"20.5", SetCommand(value="20.5")),
        (b"wet\n", SetCommand(value="wet")),
        (b"true", SetCommand(value="true")),
        (b"Anlage Nord", SetCommand(value="Anlage Nord")),
        (b'{"value": 20.5}', SetCommand(value=20.5)),
        (b'{"value": "wet", "id": "abc"}', SetCommand(value="wet", id="abc")),
        (b'{"value": 1, "id": 42}', SetCommand(value=1, id="42")),
        (b'{"value": true, "id": null}', SetCommand(value=True)),
        (
            b'{"value": {"temperature_from_ram": true}, "id": 1.5}',
            SetCommand(value={"temperature_from_ram": True}, id="1.5"),
        ),
    ],
)
def test_payloads_plain_and_json(payload: bytes, expected: SetCommand) -> None:
    assert parse_set_payload(payload) == expected


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b'{"value": 20.5', "malformed JSON: "),
        (b"{value: 1}", "malformed JSON: "),
        (b'{"id": "x"}', 'needs a "value"'),
        (b'{"value": 1, "vaule": 2}', "unknown keys \\['vaule'\\]"),
        (b'{"value": 1, "id": [1]}', "the id must be"),
        (b"  \n", "empty"),
        (b"\xff\xfe", "not UTF-8"),
    ],
)
def test_bad_payloads_are_rejected(payload: bytes, reason: str) -> None:
    with pytest.raises(CommandRejectedError, match=reason):
        parse_set_payload(payload)


# --- rejections ------------------------------------------------------------------------


def test_unknown_point(s10: Profile) -> None:
    error = rejected(s10, "no_such_point", "1")
    assert error.reason == "no point 'no_such_point' in profile jumo-digiline-odo-s10"


def test_read_only_point(s10: Profile) -> None:
    assert "read-only" in rejected(s10, "oxygen", "8.0").reason


@pytest.mark.parametrize("value", ["warm", True, [20.5], {"value": 1}])
def test_wrong_type_for_a_float(s10: Profile, value: object) -> None:
    assert "float32 needs a number" in rejected(s10, "compensation_temperature", value).reason


@pytest.mark.parametrize("value", ["151", 150.5, -20.5])
def test_out_of_range_names_the_allowed_range(s10: Profile, value: object) -> None:
    reason = rejected(s10, "compensation_temperature", value).reason
    assert "allowed range -20 to 150" in reason


@pytest.mark.parametrize("value", ["nan", "inf", float("nan"), float("-inf")])
def test_non_finite_floats(s10: Profile, value: object) -> None:
    assert "not a finite number" in rejected(s10, "compensation_temperature", value).reason


def test_integers_refuse_fractions_and_text(s10: Profile) -> None:
    assert "needs an integer, got '3.5'" in rejected(s10, "min_response_time", "3.5").reason
    assert "needs an integer" in rejected(s10, "min_response_time", 3.5).reason
    assert "needs an integer" in rejected(s10, "min_response_time", "three").reason
    assert "allowed range 0 to 500" in rejected(s10, "min_response_time", "501").reason


def test_unknown_enum_label_lists_the_labels(h10: Profile) -> None:
    reason = rejected(h10, "calibration_mode", "moist").reason
    assert reason == "unknown label 'moist'; allowed: as_configured, wet, dry"
    assert "not one of the codes [0, 1, 2]" in rejected(h10, "calibration_mode", "7").reason


def test_string_too_long_names_the_capacity(s10: Profile) -> None:
    reason = rejected(s10, "description", "x" * 192).reason
    assert "exceed the 192 bytes" in reason


def test_bool_words(s10: Profile) -> None:
    point = "analog_output_warning_active"
    for word in ("true", "ON", "1", 1, True):
        assert validate_write(s10, writable_point(s10, point), word, float_order=CDAB) == (1,)
    for word in ("false", "Off", "0", 0, False):
        assert validate_write(s10, writable_point(s10, point), word, float_order=CDAB) == (0,)
    assert "bool needs true/false" in rejected(s10, point, "yes").reason
    assert "bool needs true/false" in rejected(s10, point, 2).reason


def test_bitfield_names_and_rejections(s10: Profile) -> None:
    point = "compensation_control"
    # Encoded alone, bits not named are 0; the write path keeps them as the device holds them.
    assert validate_write(
        s10,
        writable_point(s10, point),
        {"temperature_from_ram": True, "pressure_from_ram": True},
        float_order=CDAB,
    ) == (0b101,)
    assert validate_write(
        s10, writable_point(s10, point), {"salinity_from_ram": True}, float_order=CDAB
    ) == (0b010,)
    assert validate_write(s10, writable_point(s10, point), "3", float_order=CDAB) == (3,)
    assert "is not a bit of this field" in rejected(s10, point, {"ph_from_ram": True}).reason
    assert "needs true or false" in rejected(s10, point, {"salinity_from_ram": 1}).reason
    assert "JSON object of bit names" in rejected(s10, point, "temperature_from_ram").reason


def test_datetime_needs_an_offset(s10: Profile) -> None:
    assert "time-zone offset" in rejected(s10, "clock", "2025-02-10T14:30:05").reason
    assert "ISO 8601" in rejected(s10, "clock", "yesterday").reason


def test_calibration_stamp_rejections(tecline: Profile) -> None:
    assert (
        "minutes, not seconds"
        in rejected(tecline, "calibration_stamp", "2019-03-08T13:10:30").reason
    )
    assert "outside 2000-01-01" in rejected(tecline, "calibration_stamp", "2043-01-01T00:00").reason
    assert "ISO 8601" in rejected(tecline, "calibration_stamp", "soon").reason


# --- good values -----------------------------------------------------------------------


def test_float_from_text_and_json_in_the_device_order(s10: Profile) -> None:
    assert validate_write(
        s10, writable_point(s10, "compensation_temperature"), "20.25", float_order=CDAB
    ) == (
        0x0000,
        0x41A2,
    )
    assert validate_write(
        s10, writable_point(s10, "compensation_temperature"), 20.25, float_order=WordOrder.ABCD
    ) == (
        0x41A2,
        0x0000,
    )
    assert validate_write(
        s10, writable_point(s10, "compensation_temperature"), 20, float_order=CDAB
    ) == (
        0x0000,
        0x41A0,
    )


def test_enum_by_label_or_code(h10: Profile) -> None:
    assert validate_write(
        h10, writable_point(h10, "calibration_mode"), "wet", float_order=CDAB
    ) == (1,)
    assert validate_write(h10, writable_point(h10, "calibration_mode"), "2", float_order=CDAB) == (
        2,
    )
    assert validate_write(h10, writable_point(h10, "calibration_mode"), 0, float_order=CDAB) == (0,)


def test_string_from_the_s10_manual(s10: Profile) -> None:
    registers = validate_write(
        s10, writable_point(s10, "description"), "Anlage Nord", float_order=CDAB
    )
    assert registers == (0x416E, 0x6C61, 0x6765, 0x204E, 0x6F72, 0x6400)
    assert function_for(registers) == 16


def test_clock_with_offset(s10: Profile) -> None:
    registers = validate_write(
        s10, writable_point(s10, "clock"), "2025-02-10T14:30:05+01:00", float_order=CDAB
    )
    assert registers == (2025, 2, 10, 14, 30, 5, 60)


def test_calibration_stamp_naive_from_the_tecline_manual(tecline: Profile) -> None:
    assert validate_write(
        tecline, writable_point(tecline, "calibration_stamp"), "2019-03-08T13:10", float_order=CDAB
    ) == (
        0x716E,
        0xB75E,
    )


def test_integer_from_text(tecline: Profile) -> None:
    registers = validate_write(
        tecline, writable_point(tecline, "modbus_address"), "3", float_order=CDAB
    )
    assert registers == (3,)
    assert function_for(registers) == 6


def test_function_for_nothing_is_a_programming_error() -> None:
    with pytest.raises(ValueError, match="no registers"):
        function_for(())
