"""Codec: every data type of the manuals, decoded and encoded without I/O."""

from __future__ import annotations

import math
import struct
from datetime import datetime, timedelta, timezone

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.errors import DecodeError, EncodeError
from gateway.wire.codec import (
    BitfieldValue,
    DataType,
    EnumValue,
    Fault,
    Format,
    WordOrder,
    decode,
    float_to_registers,
)
from gateway.wire.encoding import encode

FLOAT = Format(dtype=DataType.FLOAT32, count=2)
FLOAT_WITH_FAULTS = Format(dtype=DataType.FLOAT32, count=2, float_faults=True)


def f32(value: float) -> float:
    """The float32 nearest to ``value``, as the sensor would hold it."""
    result: float = struct.unpack(">f", struct.pack(">f", value))[0]
    return result


# --- floats ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("registers", "expected"),
    [
        ((0x0000, 0x41A2), 20.25),  # S10 manual 2.6.2, H10/H20 manual 2.6.2
        ((0xBA2F, 0x41C0), 24.09091),  # tecLine manual 2.4.1 prints it rounded: 24.091
        ((0x0831, 0x3E2C), 0.168),  # tecLine 2.6.3, Reiss 3.3
        ((0x0000, 0x4319), 153.0),  # tecLine 2.4.3
    ],
)
def test_manual_floats_decode_word_swapped(registers: tuple[int, int], expected: float) -> None:
    # The shortest decimal of the float32: exactly what the manual prints.
    assert decode(FLOAT, registers) == expected


@pytest.mark.parametrize(
    ("order", "registers"),
    [
        (WordOrder.ABCD, (0x41A2, 0x0000)),
        (WordOrder.CDAB, (0x0000, 0x41A2)),
        (WordOrder.BADC, (0xA241, 0x0000)),
        (WordOrder.DCBA, (0x0000, 0xA241)),
    ],
)
def test_each_word_order_reads_20_25(order: WordOrder, registers: tuple[int, int]) -> None:
    assert decode(FLOAT, registers, float_order=order) == 20.25
    assert float_to_registers(20.25, order) == registers


@pytest.mark.parametrize(
    ("multiple", "name"),
    [
        (1, "underrange"),
        (2, "overrange"),
        (3, "no_valid_input"),
        (4, "division_by_zero"),
        (5, "math_error"),
        (6, "invalid_compensation_temperature"),
        (7, "probe_short_circuit"),
        (8, "probe_break"),
        (9, "timeout"),
    ],
)
@pytest.mark.parametrize("order", list(WordOrder))
def test_fault_floats_are_faults_never_numbers(multiple: int, name: str, order: WordOrder) -> None:
    registers = float_to_registers(multiple * 1.0e37, order)
    decoded = decode(FLOAT_WITH_FAULTS, registers, float_order=order)
    assert isinstance(decoded, Fault)
    assert decoded.name == name


def test_overrange_registers_from_the_manual() -> None:
    # S10 manual 2.8.2: response bytes BD C2 7D 70 are 2.0e37, "over-range".
    assert decode(FLOAT_WITH_FAULTS, (0xBDC2, 0x7D70)) == Fault(name="overrange", raw=f32(2e37))


def test_fault_values_are_numbers_where_the_family_has_none() -> None:
    assert decode(FLOAT, (0xBDC2, 0x7D70)) == 2e37


def test_a_value_near_a_fault_value_is_a_value() -> None:
    near = float_to_registers(f32(2e37) * (1 + 1e-6), WordOrder.CDAB)
    assert isinstance(decode(FLOAT_WITH_FAULTS, near), float)


# --- integers --------------------------------------------------------------------------


def test_uint32_is_high_word_first() -> None:
    fmt = Format(dtype=DataType.UINT32, count=2)
    assert decode(fmt, (0x716E, 0xB75E)) == 1903081310  # tecLine 2.6.2
    assert decode(fmt, (0x0000, 0x0019)) == 25  # H10/H20 2.6.1


def test_signed_types() -> None:
    assert decode(Format(dtype=DataType.INT16, count=1), (0xFFC4,)) == -60
    assert decode(Format(dtype=DataType.INT32, count=2), (0xFFFF, 0xFFFE)) == -2


def test_byte_types_use_the_low_byte_only() -> None:
    # digiLine "char": low byte of a word, the high byte is not used.
    assert decode(Format(dtype=DataType.UINT8, count=1), (0xAB07,)) == 7
    assert decode(Format(dtype=DataType.INT8, count=1), (0x12FF,)) == -1
    assert decode(Format(dtype=DataType.BOOL, count=1), (0x0001,)) is True
    assert decode(Format(dtype=DataType.BOOL, count=1), (0xFF00,)) is False


@pytest.mark.parametrize(
    ("dtype", "value"),
    [
        (DataType.UINT8, 256),
        (DataType.INT8, -129),
        (DataType.UINT16, -1),
        (DataType.INT16, 32768),
        (DataType.UINT32, 2**32),
        (DataType.INT32, -(2**31) - 1),
    ],
)
def test_integers_out_of_their_type_are_refused(dtype: DataType, value: int) -> None:
    fmt = Format(dtype=dtype, count=2 if dtype in {DataType.UINT32, DataType.INT32} else 1)
    with pytest.raises(EncodeError, match="does not fit"):
        encode(fmt, value)


def test_range_is_checked_before_encoding() -> None:
    fmt = Format(dtype=DataType.FLOAT32, count=2, minimum=0.0, maximum=99.99)
    assert encode(fmt, 20.25) == (0x0000, 0x41A2)
    with pytest.raises(EncodeError, match="above the maximum"):
        encode(fmt, 100.0)
    with pytest.raises(EncodeError, match="below the minimum"):
        encode(fmt, -0.5)


@pytest.mark.parametrize("bad", [math.nan, math.inf, "20.25", True, None, 1e39])
def test_floats_refuse_what_is_not_a_finite_float32(bad: object) -> None:
    with pytest.raises(EncodeError):
        encode(FLOAT, bad)


def test_integers_refuse_fractions_and_bools() -> None:
    fmt = Format(dtype=DataType.UINT16, count=1, minimum=0, maximum=500)
    assert encode(fmt, 250.0) == (250,)
    with pytest.raises(EncodeError):
        encode(fmt, 2.5)
    with pytest.raises(EncodeError):
        encode(fmt, True)  # noqa: FBT003 - the point of the test


# --- enums and bit fields --------------------------------------------------------------

UNIT = Format(dtype=DataType.ENUM, count=1, enum={0: "percent", 3: "ppm", 4: "mg_per_l"})
UNIT32 = Format(dtype=DataType.ENUM32, count=2, enum={0x10: "percent_volume", 0x2000_0000: "hpa"})


def test_enum_decodes_to_code_and_label() -> None:
    assert decode(UNIT, (3,)) == EnumValue(code=3, label="ppm")  # tecLine 2.7: 3 = ppm
    assert decode(UNIT32, (0x2000, 0x0000)) == EnumValue(code=0x2000_0000, label="hpa")


def test_unknown_enum_code_is_reported_not_guessed() -> None:
    value = decode(UNIT, (9,))
    assert value == EnumValue(code=9, label="unknown_9", known=False)


def test_enum_encodes_label_or_code_and_refuses_others() -> None:
    assert encode(UNIT, "mg_per_l") == (4,)
    assert encode(UNIT, 3) == (3,)
    assert encode(UNIT32, "hpa") == (0x2000, 0x0000)
    with pytest.raises(EncodeError, match="not one of"):
        encode(UNIT, "furlong")
    with pytest.raises(EncodeError, match="not one of"):
        encode(UNIT, 5)


STATUS = Format(
    dtype=DataType.BITFIELD,
    count=1,
    bits={0: "oxygen_invalid", 2: "cap_missing", 10: "cap_replacement_recommended"},
)


def test_bitfield_names_every_bit() -> None:
    value = decode(STATUS, (0x0404,))
    assert isinstance(value, BitfieldValue)
    assert value.raw == 0x0404
    assert value.flags == (
        ("oxygen_invalid", False),
        ("cap_missing", True),
        ("cap_replacement_recommended", True),
    )
    assert value.active == ("cap_missing", "cap_replacement_recommended")


def test_bitfield_encodes_from_names() -> None:
    assert encode(STATUS, {"oxygen_invalid": True, "cap_missing": True}) == (0x0005,)
    with pytest.raises(EncodeError, match="not a bit"):
        encode(STATUS, {"reserve": True})


def test_bitfield32_keeps_high_bits() -> None:
    fmt = Format(dtype=DataType.BITFIELD32, count=2, bits={0: "error", 16: "warning"})
    value = decode(fmt, (0x0001, 0x0001))
    assert isinstance(value, BitfieldValue)
    assert value.active == ("error", "warning")
    assert encode(fmt, {"error": True, "warning": True}) == (0x0001, 0x0001)


# --- strings ---------------------------------------------------------------------------


def test_string_stops_at_the_first_nul() -> None:
    name = Format(dtype=DataType.STRING, count=5)
    assert decode(name, (0x646C, 0x2043, 0x5200, 0x0000, 0x0000)) == "dl CR"  # S10 2.4.1
    part = Format(dtype=DataType.STRING, count=6)
    # H10/H20 2.6.3: "00 FF FF FF" after the NUL is garbage and ignored.
    assert decode(part, (0x3030, 0x3132, 0x3334, 0x3536, 0x00FF, 0xFFFF)) == "00123456"


def test_utf8_and_latin1_strings() -> None:
    utf8 = Format(dtype=DataType.STRING, count=4, encoding="utf-8")
    latin1 = Format(dtype=DataType.STRING, count=4, encoding="iso-8859-1")
    assert decode(utf8, encode(utf8, "µS/cm")) == "µS/cm"
    assert encode(latin1, "µS") == (0xB553, 0x0000)


def test_string_with_invalid_bytes_is_a_decode_error() -> None:
    with pytest.raises(DecodeError, match="not valid ascii"):
        decode(Format(dtype=DataType.STRING, count=1), (0xC3A4,))


def test_string_write_is_nul_terminated_and_padded_to_whole_registers() -> None:
    description = Format(dtype=DataType.STRING, count=96, encoding="utf-8")
    # S10 2.4.3: 11 characters + NUL = 12 bytes = 6 registers, nothing more.
    assert encode(description, "Anlage Nord") == (0x416E, 0x6C61, 0x6765, 0x204E, 0x6F72, 0x6400)
    assert encode(description, "abc") == (0x6162, 0x6300)  # 3 + NUL: even already
    assert encode(description, "ab") == (0x6162, 0x0000)  # 2 + NUL + pad


def test_string_too_long_for_its_field_is_refused() -> None:
    name = Format(dtype=DataType.STRING, count=5)  # string[10]: 9 characters + NUL
    assert len(encode(name, "x" * 9)) == 5
    with pytest.raises(EncodeError, match="exceed the 10 bytes"):
        encode(name, "x" * 10)
    utf8 = Format(dtype=DataType.STRING, count=2, encoding="utf-8")
    with pytest.raises(EncodeError, match="exceed"):
        encode(utf8, "µµ")  # 4 bytes + NUL > 4


def test_string_refuses_nul_and_unencodable_text() -> None:
    with pytest.raises(EncodeError, match="NUL"):
        encode(Format(dtype=DataType.STRING, count=5), "a\x00b")
    with pytest.raises(EncodeError, match="cannot be written as ascii"):
        encode(Format(dtype=DataType.STRING, count=5), "µ")


# --- dates -----------------------------------------------------------------------------

STAMP = Format(dtype=DataType.YYMMDDHHMM, count=2)
CLOCK = Format(dtype=DataType.DATETIME, count=7)


def test_yymmddhhmm_from_the_tecline_manual() -> None:
    # tecLine 2.6.2: 0x716E 0xB75E = 1903081310 = 2019-03-08 13:10
    assert decode(STAMP, (0x716E, 0xB75E)) == datetime(2019, 3, 8, 13, 10)
    assert encode(STAMP, datetime(2019, 3, 8, 13, 10)) == (0x716E, 0xB75E)
    assert encode(STAMP, datetime(2019, 4, 10, 14, 30)) == divmod(1904101430, 0x10000)


def test_yymmddhhmm_initial_value_means_never() -> None:
    assert decode(STAMP, (0, 0)) is None


def test_yymmddhhmm_invalid_and_out_of_range() -> None:
    with pytest.raises(DecodeError, match="not a YYMMDDHHMM"):
        decode(STAMP, divmod(1913081310, 0x10000))  # month 13
    with pytest.raises(EncodeError, match="outside"):
        encode(STAMP, datetime(2043, 1, 1))


def test_digiline_date_block_is_timezone_aware() -> None:
    registers = (2025, 2, 10, 14, 30, 5, 60)
    value = decode(CLOCK, registers)
    assert value == datetime(2025, 2, 10, 14, 30, 5, tzinfo=timezone(timedelta(minutes=60)))
    assert encode(CLOCK, value) == registers


def test_negative_offsets_in_words_and_chars() -> None:
    west = datetime(2021, 6, 1, 8, 0, 0, tzinfo=timezone(timedelta(minutes=-120)))
    assert encode(CLOCK, west)[6] == 0xFF88
    assert decode(CLOCK, encode(CLOCK, west)) == west
    char_tz = Format(dtype=DataType.DATETIME, count=7, tz_signed_byte=True)
    assert encode(char_tz, west)[6] == 0x0088
    assert decode(char_tz, (2021, 6, 1, 8, 0, 0, 0x0088)) == west
    with pytest.raises(EncodeError, match="does not fit"):
        encode(char_tz, datetime(2021, 6, 1, tzinfo=timezone(timedelta(hours=3))))


def test_date_block_needs_a_zone_and_valid_fields() -> None:
    with pytest.raises(EncodeError, match="time zone"):
        encode(CLOCK, datetime(2021, 6, 1))
    with pytest.raises(DecodeError):
        decode(CLOCK, (2021, 2, 30, 0, 0, 0, 0))
    assert decode(CLOCK, (0, 0, 0, 0, 0, 0, 0)) is None


def test_wrong_register_count_is_a_decode_error() -> None:
    with pytest.raises(DecodeError, match="needs 2 registers"):
        decode(FLOAT, (0x41A2,))


# --- round trips -----------------------------------------------------------------------

float32s = st.floats(width=32, allow_nan=False, allow_infinity=False)


@given(value=float32s, order=st.sampled_from(list(WordOrder)))
def test_float_round_trip_in_every_order(value: float, order: WordOrder) -> None:
    registers = encode(FLOAT, value, float_order=order)
    decoded = decode(FLOAT, registers, float_order=order)
    assert isinstance(decoded, float)
    assert f32(decoded) == value  # the same float32 ...
    assert len(repr(decoded)) <= len(repr(value))  # ... in its shortest decimal form


INT_FORMATS = {
    DataType.UINT8: (0, 255),
    DataType.INT8: (-128, 127),
    DataType.UINT16: (0, 65535),
    DataType.INT16: (-32768, 32767),
    DataType.UINT32: (0, 2**32 - 1),
    DataType.INT32: (-(2**31), 2**31 - 1),
}


@given(data=st.data(), dtype=st.sampled_from(sorted(INT_FORMATS)))
def test_integer_round_trip(data: st.DataObject, dtype: DataType) -> None:
    low, high = INT_FORMATS[dtype]
    value = data.draw(st.integers(low, high))
    fmt = Format(dtype=dtype, count=2 if dtype in {DataType.UINT32, DataType.INT32} else 1)
    assert decode(fmt, encode(fmt, value)) == value


@given(value=st.booleans())
def test_bool_round_trip(value: bool) -> None:  # noqa: FBT001
    fmt = Format(dtype=DataType.BOOL, count=1)
    assert decode(fmt, encode(fmt, value)) is value


@given(
    text=st.text(alphabet=st.characters(codec="utf-8", exclude_characters="\x00"), max_size=40),
    encoding=st.sampled_from(["ascii", "utf-8", "iso-8859-1"]),
)
def test_string_round_trip(text: str, encoding: str) -> None:
    fmt = Format(dtype=DataType.STRING, count=30, encoding=encoding)
    try:
        raw = text.encode(encoding)
    except UnicodeEncodeError:
        with pytest.raises(EncodeError, match="cannot be written"):
            encode(fmt, text)
        return
    if len(raw) + 1 > fmt.byte_capacity:
        with pytest.raises(EncodeError, match="exceed"):
            encode(fmt, text)
        return
    registers = encode(fmt, text)
    assert len(registers) == (len(raw) + 2) // 2
    garbage = (0xFFFF,) * (fmt.count - len(registers))
    assert decode(fmt, (*registers, *garbage)) == text


@given(
    moment=st.datetimes(
        min_value=datetime(2000, 1, 1),
        max_value=datetime(2042, 12, 31, 23, 59),
    )
)
def test_yymmddhhmm_round_trip(moment: datetime) -> None:
    minute = moment.replace(second=0, microsecond=0)
    assert decode(STAMP, encode(STAMP, minute)) == minute


@given(
    moment=st.datetimes(min_value=datetime(1, 1, 1, 0, 0, 1), max_value=datetime(9999, 12, 31)),
    offset=st.integers(-720, 840),
)
def test_date_block_round_trip(moment: datetime, offset: int) -> None:
    aware = moment.replace(microsecond=0, tzinfo=timezone(timedelta(minutes=offset)))
    assert decode(CLOCK, encode(CLOCK, aware)) == aware


@given(raw=st.integers(0, 0xFFFF))
def test_bitfield_round_trip(raw: int) -> None:
    value = decode(STATUS, (raw,))
    assert isinstance(value, BitfieldValue)
    assert encode(STATUS, value) == (raw,)
    named = dict(value.flags)
    mask = 0x0405
    assert encode(STATUS, named) == (raw & mask,)
