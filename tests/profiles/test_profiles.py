"""Profiles: the shipped register maps are complete and consistent, broken ones fail loudly."""

from __future__ import annotations

import itertools
import math
import re
import shutil
import struct
from datetime import UTC, datetime
from typing import TYPE_CHECKING

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.errors import ConfigError, ProfileError
from gateway.profiles import (
    Access,
    Point,
    PollGroup,
    Profile,
    Storage,
    builtin_profiles,
    get_profile,
    load_profiles,
    loader,
)
from gateway.profiles.loader import DATA_DIR
from gateway.wire import codec, encoding
from gateway.wire.codec import DataType, EnumValue

if TYPE_CHECKING:
    from pathlib import Path

PROFILE_IDS = {
    "jumo-digiline-odo-s10",
    "jumo-digiline-odo-h10",
    "jumo-digiline-odo-h20",
    "jumo-tecline-cl2",
    "jumo-tecline-tc",
    "jumo-tecline-clo2",
    "jumo-tecline-o3",
    "jumo-tecline-h2o2",
    "jumo-tecline-paa",
    "jumo-tecline-br",
    "jumo-tecline-cl2-om",
    "reiss-m0c",
    "reiss-m3c",
}
PROFILES = builtin_profiles()
ALL_POINTS = [(p, point) for p in PROFILES.values() for point in p.points]


def test_every_sensor_in_the_specs_has_a_profile() -> None:
    assert set(PROFILES) == PROFILE_IDS


# --- internal consistency, for every point of every profile ----------------------------


@pytest.mark.parametrize("profile", PROFILES.values(), ids=lambda p: p.id)
def test_profile_is_internally_consistent(profile: Profile) -> None:
    names = [point.name for point in profile.points]
    assert len(names) == len(set(names))
    solid = sorted((p for p in profile.points if not p.view), key=lambda p: p.address)
    for a, b in itertools.pairwise(solid):
        assert b.address > a.last, f"{a.name} overlaps {b.name}"
    for point in profile.points:
        assert re.fullmatch(r"[a-z][a-z0-9_]*", point.name)
        assert point.description
        if point.dtype in codec.REGISTER_COUNT:
            assert point.count == codec.REGISTER_COUNT[point.dtype], point.name
        run = profile.readable_run(point.address)
        assert run is not None, f"{point.name} is outside every readable run"
        assert point.last <= run[1], f"{point.name} runs past its readable run"
        assert point.count <= profile.limits.max_read


@pytest.mark.parametrize("profile", PROFILES.values(), ids=lambda p: p.id)
def test_readable_runs_only_cover_documented_registers(profile: Profile) -> None:
    covered = {a for p in profile.points for a in range(p.address, p.last + 1)}
    for first, last in profile.readable:
        gaps = [a for a in range(first, last + 1) if a not in covered]
        assert not gaps, f"run {first:#06x}..{last:#06x} crosses undocumented {gaps[0]:#06x}"


@pytest.mark.parametrize(
    ("profile", "point"), ALL_POINTS, ids=lambda x: getattr(x, "name", None) or x.id
)
def test_every_point_is_complete(profile: Profile, point: Point) -> None:
    fmt = point.format
    if point.dtype in codec.NUMERIC_TYPES:
        assert point.unit is not None or point.unit_from is not None
    if point.unit_from is not None:
        assert profile.point(point.unit_from).enum_units
    if point.dtype in codec.ENUM_TYPES:
        assert fmt.enum
    if point.dtype in codec.BITFIELD_TYPES:
        assert fmt.bits
    if point.writable:
        assert point.storage is not None
        if point.dtype in codec.NUMERIC_TYPES:
            assert fmt.minimum is not None
            assert fmt.maximum is not None
    else:
        assert point.storage is None
    assert point.post_write_wait_s >= 0
    assert fmt.float_faults == (profile.float_faults and point.dtype is DataType.FLOAT32)


def _f32_inward(bound: float, *, up: bool) -> float:
    """The float32 nearest to ``bound`` on the inside of the range."""
    value: float = struct.unpack(">f", struct.pack(">f", bound))[0]
    if (value < bound and up) or (value > bound and not up):
        step = 1 if (value >= 0) == up else -1
        bits = struct.unpack(">i", struct.pack(">f", value))[0] + step
        value = struct.unpack(">f", struct.pack(">i", bits))[0]
    return value


def _value_for(point: Point, data: st.DataObject) -> object:  # noqa: PLR0911 - one per type
    fmt = point.format
    dtype = point.dtype
    if dtype in codec.ENUM_TYPES:
        return data.draw(st.sampled_from(sorted(fmt.enum.values())))
    if dtype in codec.BITFIELD_TYPES:
        names = list(fmt.bits.values())
        return data.draw(st.fixed_dictionaries({n: st.booleans() for n in names}))
    if dtype is DataType.BOOL:
        return data.draw(st.booleans())
    if dtype is DataType.STRING:
        alphabet = st.characters(codec="ascii", min_codepoint=32, max_codepoint=126)
        return data.draw(st.text(alphabet, max_size=fmt.byte_capacity - 1))
    if dtype is DataType.YYMMDDHHMM:
        moment = data.draw(st.datetimes(datetime(2000, 1, 1), datetime(2042, 12, 31)))
        return moment.replace(second=0, microsecond=0)
    if dtype is DataType.DATETIME:
        moment = data.draw(st.datetimes(datetime(2000, 1, 1), datetime(2099, 12, 31)))
        return moment.replace(microsecond=0, tzinfo=UTC)
    low, high = fmt.minimum, fmt.maximum
    assert low is not None
    assert high is not None
    if dtype is DataType.FLOAT32:
        inside = (_f32_inward(low, up=True), _f32_inward(high, up=False))
        return data.draw(st.floats(*inside, width=32))
    return data.draw(st.integers(math.ceil(low), math.floor(high)))


WRITABLE = [(p.id, point.name) for p, point in ALL_POINTS if point.writable]


@pytest.mark.parametrize(("profile_id", "name"), WRITABLE, ids=[f"{p}-{n}" for p, n in WRITABLE])
@settings(max_examples=25)
@given(data=st.data())
def test_every_writable_point_round_trips_its_valid_values(
    profile_id: str, name: str, data: st.DataObject
) -> None:
    point = get_profile(profile_id).point(name)
    value = _value_for(point, data)
    for order in codec.WordOrder:
        registers = encoding.encode(point.format, value, float_order=order)
        assert len(registers) <= point.count
        padded = (*registers, *([0] * (point.count - len(registers))))
        decoded = codec.decode(point.format, padded, float_order=order)
        if isinstance(decoded, EnumValue):
            assert decoded.label == value
        elif isinstance(decoded, codec.BitfieldValue):
            assert dict(decoded.flags) == value
        elif isinstance(decoded, float):
            assert struct.pack(">f", decoded) == struct.pack(">f", value), (profile_id, name)
        else:
            assert decoded == value, (profile_id, name)


# --- what the manuals say, checked on the data ------------------------------------------


def test_h10_logbook_is_ten_entries_at_the_documented_stride() -> None:
    h10 = get_profile("jumo-digiline-odo-h10")
    entries = [p for p in h10.points if p.repeat == "logbook" and p.name.endswith("_entry_type")]
    assert [p.index for p in entries] == list(range(1, 11))
    for n, point in enumerate(entries, start=1):
        assert point.address == 0x0600 + (n - 1) * 0x31  # H10/H20 manual 6.1.6
    # Entry 7's table prints wrong hex addresses; the formula puts it at 0x0726.
    assert h10.point("logbook_7_entry_type").address == 0x0726
    assert h10.point("logbook_10_date").address == 0x07BE
    assert h10.point("logbook_10_date").dtype is DataType.DATETIME


def test_tecline_history_follows_the_structure_not_the_misprint() -> None:
    tecline = get_profile("jumo-tecline-cl2")
    history = [p for p in tecline.points if p.repeat == "history"]
    assert len(history) == 15
    entry3 = sorted((p for p in history if p.index == 3), key=lambda p: p.address)
    assert [p.address for p in entry3] == [0x0222, 0x0224, 0x0226]
    assert [p.dtype for p in entry3] == [DataType.FLOAT32, DataType.FLOAT32, DataType.YYMMDDHHMM]


def test_the_rings_are_read_whole_from_the_repeats() -> None:
    """The history and the logbook as care and the calibrations take them, from the data."""
    history = get_profile("reiss-m3c").ring("history")  # inherited from the tecLine file
    assert history is not None
    assert history.numbers == (0, 1, 2, 3, 4)  # tecLine annex 7.2 / Reiss 5.1, 0 newest
    assert history.fields == ("x_zero", "x_span", "stamp")
    assert history.points("stamp") == tuple(f"history_{n}_stamp" for n in range(5))
    logbook = get_profile("jumo-digiline-odo-h20").ring("logbook")
    assert logbook is not None
    assert logbook.numbers == tuple(range(1, 11))  # 6.1.6, 1 newest
    assert logbook.point(10, "date") == "logbook_10_date"
    assert {"entry_type", "rating", "date", "phase"} <= set(logbook.fields)
    s10 = get_profile("jumo-digiline-odo-s10")
    assert (s10.ring("history"), s10.ring("logbook")) == (None, None)
    cares = {pid: profile.care for pid, profile in builtin_profiles().items()}
    assert set(cares.values()) == {"amperometric", "optical_hygienic", "optical"}
    assert cares["reiss-m0c"] == cares["jumo-tecline-cl2"] == "amperometric"


@pytest.mark.parametrize(
    ("profile_id", "address", "wait_s"),
    [
        ("jumo-digiline-odo-h10", 0x0402, 0.65),
        ("jumo-digiline-odo-h10", 0x2031, 0.65),
        ("jumo-digiline-odo-h10", 0x204B, 0.65),
        ("jumo-digiline-odo-h10", 0x3003, 0.65),
        ("jumo-digiline-odo-h20", 0x3005, 0.65),
        ("jumo-digiline-odo-h10", 0x3009, 0.25),
        ("jumo-digiline-odo-h10", 0x2013, 0.25),
        ("jumo-digiline-odo-h10", 0x0300, 0.25),
        ("jumo-digiline-odo-s10", 0x25B0, 0.0),
        ("jumo-tecline-cl2", 0x0208, 0.0),
    ],
)
def test_post_write_waits(profile_id: str, address: int, wait_s: float) -> None:
    profile = get_profile(profile_id)
    point = next(p for p in profile.points if p.address == address and p.writable)
    assert point.post_write_wait_s == wait_s
    assert profile.post_write_wait(address, point.count) == wait_s


def test_flash_wear_storage_classes() -> None:
    h10 = get_profile("jumo-digiline-odo-h10")
    volatile = {p.address for p in h10.points if p.storage is Storage.VOLATILE}
    assert {0x2013, 0x2017, 0x201F, 0x3009, 0x300A} <= volatile  # "not written to flash"
    assert h10.point("oxygen_unit").storage is Storage.FLASH
    s10 = get_profile("jumo-digiline-odo-s10")
    ram = sorted(p.address for p in s10.points if p.storage is Storage.RAM)
    assert ram == [0x25AF, 0x25B0, 0x25B2, 0x25B4]  # S10 6.8.1 RAM block
    fixed = [p for p in s10.points if p.address in {0x2580, 0x2582}]
    assert all(p.storage is Storage.FLASH for p in fixed)


def test_units_come_from_the_unit_registers() -> None:
    s10 = get_profile("jumo-digiline-odo-s10")
    oxygen = next(p for p in s10.points if p.address == 0x2600)
    assert s10.point(oxygen.unit_from or "").address == 0x2530
    assert next(p for p in s10.points if p.address == 0x2620).unit == "°C"
    h10 = get_profile("jumo-digiline-odo-h10")
    assert (
        h10.point(next(p for p in h10.points if p.address == 0x2001).unit_from or "").address
        == 0x2011
    )
    tecline = get_profile("jumo-tecline-cl2")
    concentration = next(p for p in tecline.points if p.address == 0x0000)
    unit = tecline.point(concentration.unit_from or "")
    assert unit.address == 0x0200
    assert unit.enum_units[3] == "ppm"
    assert 6 not in unit.enum_units
    reiss = get_profile("reiss-m0c")
    assert reiss.point(unit.name).enum_units[6] == "µg/l"  # Reiss adds unit 6


def test_h20_adds_ppm_gas() -> None:
    h10_units = set(get_profile("jumo-digiline-odo-h10").point("oxygen_unit").format.enum.values())
    h20_units = set(get_profile("jumo-digiline-odo-h20").point("oxygen_unit").format.enum.values())
    assert h20_units - h10_units == {"ppm_gas"}
    h20 = get_profile("jumo-digiline-odo-h20")
    assert "ppm_gas" in h20.unit_availability["dry"]
    assert "ppm_gas" not in get_profile("jumo-digiline-odo-h10").unit_availability["dry"]


def test_reiss_has_the_sensor_type_string() -> None:
    reiss = get_profile("reiss-m3c")
    sensor_type = next(p for p in reiss.points if p.address == 0x0300)
    assert sensor_type.dtype is DataType.STRING
    assert sensor_type.count == 8
    assert not any(p.address == 0x0300 for p in get_profile("jumo-tecline-br").points)


@pytest.mark.parametrize(
    ("profile_id", "address", "baudrate", "parity", "stopbits"),
    [
        ("reiss-m0c", 10, 19200, "E", 1),
        ("reiss-m3c", 20, 9600, "N", 2),
    ],
)
def test_reiss_factory_serial_settings(
    profile_id: str, address: int, baudrate: int, parity: str, stopbits: int
) -> None:
    serial = get_profile(profile_id).serial
    assert serial is not None
    assert (serial.address, serial.baudrate, serial.parity, serial.stopbits) == (
        address,
        baudrate,
        parity,
        stopbits,
    )


@pytest.mark.parametrize(
    ("variant", "address"),
    [
        ("cl2", 20),
        ("tc", 30),
        ("o3", 50),
        ("clo2", 80),
        ("h2o2", 60),
        ("paa", 70),
        ("br", 90),
        ("cl2-om", 100),
    ],
)
def test_tecline_factory_addresses(variant: str, address: int) -> None:
    serial = get_profile(f"jumo-tecline-{variant}").serial
    assert serial is not None
    assert serial.address == address


@pytest.mark.parametrize(
    ("profile_id", "sensor_type", "sub_type"),
    [
        ("jumo-digiline-odo-s10", 4, 0),
        ("jumo-digiline-odo-h10", 3, 0),
        ("jumo-digiline-odo-h20", 3, 1),
    ],
)
def test_digiline_identification(profile_id: str, sensor_type: int, sub_type: int) -> None:
    profile = get_profile(profile_id)
    assert dict(profile.identify) == {"sensor_type": sensor_type, "oxygen_sub_type": sub_type}
    assert profile.point("sensor_type").address == 0x010A
    assert profile.point("oxygen_sub_type").address == 0x010B


def test_digiline_float_format_register_and_quirks() -> None:
    for profile_id in ("jumo-digiline-odo-s10", "jumo-digiline-odo-h10"):
        profile = get_profile(profile_id)
        assert profile.float_order is codec.WordOrder.CDAB
        register = profile.float_order_register
        assert register is not None
        assert profile.point(register.point).address == 0x0307
        assert dict(register.orders) == {0: "CDAB", 1: "DCBA", 2: "ABCD"}
        assert profile.float_faults
        assert profile.quirks.string_byte_count_16bit
        assert profile.timing.min_gap_s == 0.002
        assert profile.point(profile.timing.min_response_time_point or "").address == 0x0305
    for profile_id in ("jumo-tecline-cl2", "reiss-m0c"):
        profile = get_profile(profile_id)
        assert profile.float_order is codec.WordOrder.CDAB
        assert profile.float_order_register is None
        assert not profile.float_faults
        assert not profile.quirks.string_byte_count_16bit


def test_process_and_identity_groups() -> None:
    s10 = get_profile("jumo-digiline-odo-s10")
    process = {p.address for p in s10.points_in(PollGroup.PROCESS)}
    assert {0x2600, 0x2620} <= process
    status = next(p for p in s10.points if p.address == 0x2640)
    assert status.group is PollGroup.STATUS
    assert set(status.format.bits) == {0, 1, 2, 8, 9, 10}
    assert s10.point("serial_number").group is PollGroup.IDENTITY


def test_unknown_profile_and_point_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="unknown profile 'jumo-x'; known: jumo-digiline"):
        get_profile("jumo-x")
    with pytest.raises(ConfigError, match="has no point 'oxygenn'"):
        get_profile("jumo-digiline-odo-s10").point("oxygenn")


def test_json_contract_of_a_point() -> None:
    h10 = get_profile("jumo-digiline-odo-h10")
    data = h10.point("oxygen_unit").as_dict()
    assert {"name", "address", "type", "count", "access", "unit"} <= set(data)
    assert data["access"] in {"r", "rw"}
    assert data["type"] == "enum32"


# --- broken profile files ---------------------------------------------------------------


@pytest.fixture
def data_copy(tmp_path: Path) -> Path:
    for path in DATA_DIR.glob("*.yaml"):
        shutil.copy(path, tmp_path / path.name)
    return tmp_path


def _edit_point(directory: Path, file: str, name: str, changes: dict[str, object]) -> None:
    path = directory / file
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    for point in data["points"]:
        if point["name"] == name:
            point.update(changes)
            for key, value in list(point.items()):
                if value is None:
                    del point[key]
            break
    else:
        pytest.fail(f"{name} not in {file}")
    path.write_text(yaml.safe_dump(data, allow_unicode=True), encoding="utf-8")


def test_copied_data_loads(data_copy: Path) -> None:
    assert set(load_profiles(data_copy)) == PROFILE_IDS


def test_the_profiles_read_the_same_with_pyyamls_own_parser(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """libyaml's parser reads the profiles where PyYAML has it; where it has not (built
    without it), its pure-Python parser must read the same profiles."""
    assert loader._SAFE_LOADER is yaml.CSafeLoader
    with_libyaml = load_profiles(DATA_DIR)
    monkeypatch.setattr(loader, "_SAFE_LOADER", yaml.SafeLoader)
    assert load_profiles(DATA_DIR) == with_libyaml


@pytest.mark.parametrize(
    ("name", "changes", "problem"),
    [
        ("temperature_lowest", {"type": "floatt"}, r"unknown type 'floatt'"),
        ("temperature_lowest", {"address": 0x0508}, r"overlaps 'commissioning_operating_seconds'"),
        ("temperature_lowest", {"unit": None}, r"missing unit"),
        ("temperature_lowest", {"count": 3}, r"float32 takes 2 registers, not 3"),
        ("min_response_time", {"storage": None}, r"a writable point needs 'storage'"),
        ("min_response_time", {"range": None}, r"a writable number needs a 'range'"),
        ("baud_rate", {"enum": "baud_rates"}, r"unknown enum 'baud_rates'"),
        ("device_name", {"address": 0x001A}, r"outside every readable run"),
        ("device_name", {"encoding": None}, r"a string needs 'encoding'"),
        ("device_name", {"group": "sometimes"}, r"group"),
        ("device_name", {"name": "Device-Name"}, r"snake_case"),
        ("serial_number", {"colour": "red"}, r"colour"),
    ],
)
def test_a_broken_profile_names_file_point_and_problem(
    data_copy: Path, name: str, changes: dict[str, object], problem: str
) -> None:
    _edit_point(data_copy, "jumo-digiline-common.yaml", name, changes)
    point_name = changes.get("name", name)
    with pytest.raises(ProfileError, match=problem) as caught:
        load_profiles(data_copy)
    message = str(caught.value)
    assert message.startswith(f"jumo-digiline-common.yaml: point '{point_name}': ")
    assert caught.value.source == "jumo-digiline-common.yaml"


def test_a_point_defined_twice_is_refused(data_copy: Path) -> None:
    path = data_copy / "jumo-digiline-odo-s10.yaml"
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    data["points"].append(
        {
            "name": "device_name",
            "address": 0x0000,
            "type": "string",
            "count": 5,
            "access": "r",
            "encoding": "ascii",
            "group": "identity",
            "description": "again",
        }
    )
    path.write_text(yaml.safe_dump(data, allow_unicode=True), encoding="utf-8")
    with pytest.raises(
        ProfileError, match=r"jumo-digiline-odo-s10.yaml: point 'device_name': defined twice"
    ):
        load_profiles(data_copy)


def test_invalid_yaml_names_the_file(data_copy: Path) -> None:
    (data_copy / "jumo-tecline.yaml").write_text(
        "family: jumo-tecline\npoints: [\n", encoding="utf-8"
    )
    with pytest.raises(ProfileError, match=r"^jumo-tecline.yaml: not valid YAML"):
        load_profiles(data_copy)


def test_rw_points_are_the_only_ones_with_storage() -> None:
    for profile, point in ALL_POINTS:
        assert (point.access is Access.READ_WRITE) == (point.storage is not None), (
            profile.id,
            point.name,
        )


def test_an_unknown_care_kind_is_refused_with_the_key(data_copy: Path) -> None:
    path = data_copy / "jumo-tecline.yaml"
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    data["care"] = "chlorine"
    path.write_text(yaml.safe_dump(data, allow_unicode=True), encoding="utf-8")
    with pytest.raises(ProfileError, match=r"care: Input should be 'amperometric'"):
        load_profiles(data_copy)


def test_an_amperometric_profile_without_its_slope_facts_is_refused(data_copy: Path) -> None:
    path = data_copy / "jumo-tecline.yaml"
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    del data["slope"]
    path.write_text(yaml.safe_dump(data, allow_unicode=True), encoding="utf-8")
    with pytest.raises(ProfileError, match=r"care 'amperometric' needs 'slope'"):
        load_profiles(data_copy)
