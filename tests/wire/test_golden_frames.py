"""Golden frames: every frame example printed in the five manuals, both directions.

For each case in ``golden/frames.yaml`` the request we build equals the manual's bytes,
the slave-side helpers produce the manual's response bytes, and the response parses and
decodes, through the profile's point at that address, to the value the manual states.
"""

from __future__ import annotations

import dataclasses
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
import yaml

from gateway.errors import DeviceExceptionError
from gateway.profiles import Point, Profile, get_profile
from gateway.wire import codec, encoding, frames

CASES: list[dict[str, Any]] = yaml.safe_load(
    (Path(__file__).parent / "golden" / "frames.yaml").read_text(encoding="utf-8")
)


def hexbytes(text: str) -> bytes:
    return bytes.fromhex(text)


def point_at(profile: Profile, address: int, count: int) -> Point | None:
    """The profile's point that the manual's frame reads or writes.

    A frame may cover a point exactly, or the leading registers of a string (the S10
    manual reads 7 of the 96 registers of the measuring point description).
    """
    at = [point for point in profile.points if point.address == address]
    exact = [point for point in at if point.count == count]
    prefix = [p for p in at if p.dtype is codec.DataType.STRING and p.count > count]
    matches = exact or prefix
    return matches[0] if matches else None


def build_request(case: dict[str, Any]) -> frames.Request:
    kind, device, address = case["kind"], case["device"], case["address"]
    if kind == "read":
        return frames.read_request(device, address, case["count"], function=case["function"])
    if kind == "write_single":
        return frames.write_single_request(device, address, case["registers"][0])
    if kind == "write_multiple":
        return frames.write_multiple_request(device, address, case["registers"])
    request = frames.parse_request(hexbytes(case["request"]))  # exception cases: any request
    assert request.function == case["function"]
    return request


def test_the_golden_file_covers_every_family_and_kind() -> None:
    assert len(CASES) >= 26
    assert {c["profile"].split("-")[0] for c in CASES} == {"jumo", "reiss"}
    assert {c["kind"] for c in CASES} == {"read", "write_single", "write_multiple", "exception"}
    assert len({c["id"] for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c["id"] for c in CASES])
def test_manual_crcs_are_valid(case: dict[str, Any]) -> None:
    assert frames.crc_ok(hexbytes(case["request"]))
    assert frames.crc_ok(hexbytes(case["response"]))


@pytest.mark.parametrize("case", CASES, ids=[c["id"] for c in CASES])
def test_request_bytes_equal_the_manual(case: dict[str, Any]) -> None:
    request = build_request(case)
    assert request.frame == hexbytes(case["request"])
    assert frames.parse_request(request.frame) == request


@pytest.mark.parametrize(
    "case", [c for c in CASES if c["kind"] == "exception"], ids=lambda c: c["id"]
)
def test_exception_responses(case: dict[str, Any]) -> None:
    profile = get_profile(case["profile"])
    request = build_request(case)
    response = hexbytes(case["response"])
    assert (
        frames.exception_response(request.device, request.function, case["exception_code"])
        == response
    )
    with pytest.raises(DeviceExceptionError) as caught:
        frames.parse_response(request, response, exceptions=profile.exceptions)
    assert caught.value.code == case["exception_code"]
    assert caught.value.meaning == profile.exception_meaning(case["exception_code"])
    assert caught.value.meaning == "illegal_address"


READS = [c for c in CASES if c["kind"] == "read"]


@pytest.mark.parametrize("case", READS, ids=[c["id"] for c in READS])
def test_read_responses_decode_to_the_manual_value(case: dict[str, Any]) -> None:
    profile = get_profile(case["profile"])
    request = build_request(case)
    raw = hexbytes(case["response"])
    quirk = case.get("quirk") == frames.QUIRK_STRING_BYTE_COUNT
    assert quirk <= profile.quirks.string_byte_count_16bit  # only where the family documents it
    assert frames.response_length(request, raw[:3], byte_count_16bit=quirk) == len(raw)
    response = frames.parse_response(
        request, raw, exceptions=profile.exceptions, byte_count_16bit=quirk
    )
    assert (response.tolerated is not None) == quirk
    # The slave side reproduces the manual's bytes, quirk included.
    assert (
        frames.read_response(
            request.device, request.function, response.registers, byte_count_16bit=quirk
        )
        == raw
    )

    if "registers" in case:  # a block of several integers, e.g. the H10 calibration date
        assert list(response.registers) == case["registers"]
        return
    point = point_at(profile, request.address, request.count)
    fmt = (
        dataclasses.replace(point.format, count=request.count)
        if point
        else codec.Format(dtype=codec.DataType.UINT16, count=1)
    )
    if point is None:  # S10 2.6.1 reads only the year word of the 7-word start-up date
        assert case["id"] == "s10-read-initial-startup-year"
    decoded = codec.decode(fmt, response.registers, float_order=profile.float_order)
    expected = case["value"]
    if isinstance(expected, dict):
        assert isinstance(decoded, codec.Fault)
        assert decoded.name == expected["fault"]
    elif isinstance(decoded, codec.EnumValue):
        assert decoded.code == expected
        assert decoded.known
    elif isinstance(decoded, datetime):
        assert decoded == datetime.fromisoformat(case["datetime"])
    elif isinstance(expected, float):
        assert decoded == pytest.approx(expected, abs=5e-4)
    else:
        assert decoded == expected


WRITES = [c for c in CASES if c["kind"] in {"write_single", "write_multiple"}]


@pytest.mark.parametrize("case", WRITES, ids=[c["id"] for c in WRITES])
def test_writes_encode_the_manual_value_into_the_manual_bytes(case: dict[str, Any]) -> None:
    profile = get_profile(case["profile"])
    request = build_request(case)
    point = point_at(profile, request.address, request.count)
    assert point is not None, "every write example targets a point of the profile"
    assert point.writable
    encoded = encoding.encode(point.format, case["value"], float_order=profile.float_order)
    assert list(encoded) == case["registers"]
    assert frames.write_request(request.device, request.address, encoded).frame == hexbytes(
        case["request"]
    )
    response = hexbytes(case["response"])
    parsed = frames.parse_response(request, response, exceptions=profile.exceptions)
    assert (parsed.address, parsed.count) == (request.address, request.count)
    if request.function == frames.WRITE_SINGLE:
        assert (
            frames.write_single_response(request.device, request.address, request.values[0])
            == response
        )
    else:
        assert (
            frames.write_multiple_response(request.device, request.address, request.count)
            == response
        )
