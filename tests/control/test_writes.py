"""The safe write path against the simulator: bytes on the wire, flash rules, rejections.

Every assertion on what was written reads the simulator's own write log; every assertion
on timing, its referee.
"""

from __future__ import annotations

import struct
import sys
from datetime import date
from typing import TYPE_CHECKING

import pytest

from gateway.config import FlashPolicy
from gateway.control.flash import FlashLedger
from gateway.control.writes import SafeWriter, WriteOutcome
from gateway.errors import CommandRejectedError, ConfigError, DeviceExceptionError
from gateway.profiles.model import Point, Profile
from tests.rigs import PLANT, link_rig, link_target

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.line.engine.devices import DeviceTarget
    from tests.rigs import LinkRig

pytestmark = [pytest.mark.line]

DAY = date(2026, 11, 22)
NOTHING = FlashPolicy(allowed=frozenset(), daily_budget=4)


def cdab(value: float) -> tuple[int, int]:
    """A float32 as the manuals send it: low word first (``0x0000 0x41A2`` = 20.25)."""
    high, low = struct.unpack(">HH", struct.pack(">f", value))
    return low, high


def targets() -> list[DeviceTarget]:
    return [
        link_target("s10", "jumo-digiline-odo-s10", 1),
        link_target("h10", "jumo-digiline-odo-h10", 2),
        link_target("cl2", "jumo-tecline-cl2", 20),
    ]


def writer(
    rig: LinkRig, device: str, ledger: FlashLedger, policy: FlashPolicy = NOTHING
) -> SafeWriter:
    return SafeWriter(rig.links[device], policy=policy, ledger=ledger, today=lambda: DAY)


async def set_named(writer: SafeWriter, name: str, value: object, **options: bool) -> WriteOutcome:
    """A write as a command enters it: the point looked up by name once, then written."""
    return await writer.set(writer.point(name), value, **options)


@pytest.fixture
def ledger(tmp_path: Path) -> FlashLedger:
    return FlashLedger(tmp_path / "state" / "flash-writes.sqlite")


@pytest.mark.parametrize("poll", [False, True], ids=["inline", "while-polling"])
async def test_ram_write_goes_out_as_function_16_in_cdab_and_is_read_back(
    tmp_path: Path, ledger: FlashLedger, *, poll: bool
) -> None:
    async with link_rig(tmp_path, PLANT, targets(), poll=poll) as rig:
        done = await set_named(writer(rig, "s10", ledger), "compensation_temperature", "21.5")
        assert done.written
        assert done.value == 21.5
        assert not done.flash
        [record] = rig.writes(1)
        assert (record.function, record.address) == (16, 0x25B0)
        assert record.values == cdab(21.5) == (0x0000, 0x41AC)
        assert rig.device(1).get("compensation_temperature") == 21.5
        assert rig.violations() == []
    assert ledger.totals() == {}  # RAM is free: nothing counted


async def test_float_word_order_follows_the_devices_format_register(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    devices = [{"profile": "jumo-digiline-odo-s10", "address": 1, "values": {"float_format": 2}}]
    async with link_rig(tmp_path, devices, targets()[:1]) as rig:
        await set_named(writer(rig, "s10", ledger), "compensation_temperature", 20.25)
        [record] = rig.writes(1)
        assert record.values == (0x41A2, 0x0000)  # ABCD, as 0x0307 = 2 selects
        assert rig.device(1).get("compensation_temperature") == 20.25


async def test_single_register_goes_out_as_function_06(tmp_path: Path, ledger: FlashLedger) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        done = await set_named(
            writer(rig, "s10", ledger),
            "compensation_control",
            {"temperature_from_ram": True, "pressure_from_ram": True},
        )
        [record] = rig.writes(1)
        assert (record.function, record.address, record.values) == (6, 0x25AF, (0b101,))
        assert done.value is not None
        assert dict(done.value.flags) == {  # type: ignore[union-attr]
            "temperature_from_ram": True,
            "salinity_from_ram": False,
            "pressure_from_ram": True,
        }


async def test_named_bits_change_only_themselves_the_rest_of_the_word_is_kept(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        # Bits 0 and 2 named and set; bit 4 is one the S10 profile does not name.
        rig.device(1).put("compensation_control", 0b1_0101)
        done = await set_named(
            writer(rig, "s10", ledger),
            "compensation_control",
            {"salinity_from_ram": True, "pressure_from_ram": False},
        )
        [record] = rig.writes(1)
        assert (record.function, record.address, record.values) == (6, 0x25AF, (0b1_0011,))
        assert done.registers == (0b1_0011,)
        assert rig.device(1).get("compensation_control").raw == 0b1_0011  # type: ignore[union-attr]
        raw = await set_named(writer(rig, "s10", ledger), "compensation_control", 0b010)
        assert raw.registers == (0b010,)  # a raw number is the whole word
        assert [r.values for r in rig.writes(1)] == [(0b1_0011,), (0b010,)]


async def test_a_bit_that_is_not_in_the_field_reads_nothing_and_writes_nothing(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        frames_before = len(rig.rig.frames())
        with pytest.raises(CommandRejectedError, match="is not a bit of this field"):
            await set_named(
                writer(rig, "s10", ledger), "compensation_control", {"ph_from_ram": True}
            )
        assert rig.writes(1) == []
        assert len(rig.rig.frames()) == frames_before


async def test_h10_volatile_write_keeps_the_250_ms_wait_on_the_wire(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        await set_named(writer(rig, "h10", ledger), "compensation_pressure", 1000)
        frames = [f for f in rig.rig.frames() if f.device == 2]
        write_at = next(i for i, f in enumerate(frames) if f.function == 16)
        write, read_back = frames[write_at], frames[write_at + 1]
        assert write.answer_at is not None
        assert read_back.start - write.answer_at >= 0.250
        [record] = rig.writes(2)
        assert (record.address, record.values) == (0x2017, cdab(1000.0))
        assert rig.violations() == []


# --- flash ----------------------------------------------------------------------------------


async def test_flash_point_without_permission_is_refused_and_nothing_is_sent(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        requests_before = len(rig.rig.frames())
        with pytest.raises(CommandRejectedError, match="flash-backed point not allowed"):
            await set_named(writer(rig, "cl2", ledger), "x_span", 55.0)
        assert rig.writes(20) == []
        assert len(rig.rig.frames()) == requests_before  # not even a read
    assert ledger.totals() == {}


async def test_allowed_flash_write_is_counted_skipped_when_unchanged_and_budgeted(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    policy = FlashPolicy(allowed=frozenset({"x_span"}), daily_budget=2)
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        cl2 = writer(rig, "cl2", ledger, policy)
        first = await set_named(cl2, "x_span", 55.0)
        assert first.written
        assert first.flash
        assert first.value == 55.0
        unchanged = await set_named(cl2, "x_span", 55.0)
        assert not unchanged.written
        assert unchanged.note == "unchanged, not written"
        assert unchanged.value == 55.0
        second = await set_named(cl2, "x_span", 56.0)
        assert second.written
        with pytest.raises(CommandRejectedError, match="budget of 2 writes per day"):
            await set_named(cl2, "x_span", 57.0)
        written = [(r.function, r.address, r.values) for r in rig.writes(20)]
        assert written == [(16, 0x0208, cdab(55.0)), (16, 0x0208, cdab(56.0))]
        assert rig.device(20).get("x_span") == 56.0
    assert ledger.count_today("cl2", "x_span", DAY) == 2


async def test_flash_counts_survive_a_restart(tmp_path: Path) -> None:
    path = tmp_path / "state" / "flash-writes.sqlite"
    policy = FlashPolicy(allowed=frozenset({"x_span"}), daily_budget=1)
    first = FlashLedger(path)
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        await set_named(writer(rig, "cl2", first, policy), "x_span", 55.0)
    first.close()
    again = FlashLedger(path)  # the gateway started again
    assert again.totals() == {("cl2", "x_span"): 1}
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        with pytest.raises(CommandRejectedError, match="budget of 1 writes per day"):
            await set_named(writer(rig, "cl2", again, policy), "x_span", 56.0)
        assert rig.writes(20) == []


async def test_explicit_operator_write_needs_no_allow_list_but_keeps_the_budget(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    policy = FlashPolicy(allowed=frozenset(), daily_budget=1)
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        cl2 = writer(rig, "cl2", ledger, policy)
        done = await set_named(cl2, "x_zero", 0.0, explicit=True)
        assert done.written  # written although unchanged: an operator's deliberate step
        with pytest.raises(CommandRejectedError, match="budget"):
            await set_named(cl2, "x_zero", 0.0, explicit=True)
        assert len(rig.writes(20)) == 1


# --- rejections: nothing reaches the bus ----------------------------------------------------


@pytest.mark.parametrize(
    ("device", "point", "value", "reason"),
    [
        ("s10", "no_such_point", 1, "no point 'no_such_point'"),
        ("s10", "oxygen", 1.0, "read-only"),
        ("s10", "compensation_temperature", "warm", "float32 needs a number"),
        ("h10", "compensation_pressure", 0.5, "allowed range 1 to 9999"),
        ("s10", "oxygen_unit", "furlongs", "unknown label 'furlongs'"),
        ("s10", "description", "x" * 200, "exceed the 192 bytes"),
    ],
    ids=["unknown-point", "read-only", "wrong-type", "out-of-range", "bad-label", "long-string"],
)
async def test_invalid_values_are_refused_before_the_bus(
    tmp_path: Path, ledger: FlashLedger, *, device: str, point: str, value: object, reason: str
) -> None:
    policy = FlashPolicy(allowed=frozenset({"description"}), daily_budget=4)
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        before = len(rig.rig.frames())
        with pytest.raises(CommandRejectedError, match=reason):
            await set_named(writer(rig, device, ledger, policy), point, value)
        assert len(rig.rig.frames()) == before
        assert rig.writes(1) == rig.writes(2) == []


async def test_a_value_the_device_refuses_is_its_exception(tmp_path: Path) -> None:
    # The H10 range of 0x2013 is 0 to 99.99; the profile agrees, so go around the check
    # and send 120 °C as registers to see the device's own refusal come back.
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        link = rig.links["h10"]
        with pytest.raises(DeviceExceptionError, match="exception 03"):
            await link.write_registers(link.profile.point("compensation_temperature"), cdab(120.0))
        [record] = rig.writes(2)
        assert record.exception == 3


@pytest.mark.parametrize(
    ("device", "point", "value"),
    [
        ("s10", "compensation_temperature", 21.5),  # float32, function 16
        (
            "s10",
            "compensation_control",
            {"salinity_from_ram": True},
        ),  # bits: the word is read first
        ("cl2", "x_span", 55.0),  # flash-backed, explicit: the flash guard is asked
    ],
)
async def test_a_write_looks_its_point_up_by_name_once(
    tmp_path: Path,
    ledger: FlashLedger,
    monkeypatch: pytest.MonkeyPatch,
    *,
    device: str,
    point: str,
    value: object,
) -> None:
    # The name becomes a Point where it comes in, and the encoding, the flash guard, the
    # link, the job queue and the reads (the bits to keep, the read-back) are handed the
    # Point: nothing below looks the name up again.
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        w = writer(rig, device, ledger)
        await w.link.float_order()  # the format register is read once per device, by name
        looked_up = spy_on_lookups(monkeypatch)
        done = await w.set(w.point(point), value, explicit=True)
    assert done.written
    assert done.value is not None  # read back
    assert looked_up == [point]


@pytest.mark.parametrize(
    ("device", "units", "names"),
    [
        ("s10", ("oxygen_unit",), ("oxygen",)),  # a float whose unit a register selects
        # several points in one block, a bit field among them, and a unit register itself
        ("s10", (), ("oxygen_unit", "oxygen", "temperature", "compensation_control")),
        ("s10", (), ("clock", "clock_year")),  # a view that shares its register's read
        ("cl2", ("unit",), ("concentration", "x_span")),  # a process value, a flash-backed one
        ("h10", ("oxygen_unit",), ("oxygen", "oxygen", "temperature")),  # a name twice
    ],
)
async def test_a_read_looks_each_point_up_by_name_once(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    *,
    device: str,
    units: tuple[str, ...],
    names: tuple[str, ...],
) -> None:
    # The names become Points where they come in (the link); the job queue, the
    # transactions, the planner (whose plans are not cached yet: it checks the points it
    # is handed, it does not look them up) and the decoder (the unit registers read
    # before, so a value's unit is found from its register) are handed the Points.
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        link = rig.links[device]
        if units:
            await link.read(*units)
        looked_up = spy_on_lookups(monkeypatch)
        values = await link.read(*names)
    assert set(values) == set(names)
    assert looked_up == list(names)


def spy_on_lookups(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The names the gateway looks up in a profile from now on, in order.

    The simulated devices, in the same process, look their points up too: theirs are not
    counted.
    """
    looked_up: list[str] = []
    lookup = Profile.point

    def counting(profile: Profile, name: str) -> Point:
        caller = sys._getframe(1).f_globals["__name__"]
        if not caller.startswith("gateway.simulator"):
            looked_up.append(name)
        return lookup(profile, name)

    monkeypatch.setattr(Profile, "point", counting)
    return looked_up


@pytest.mark.parametrize("poll", [False, True], ids=["inline", "while-polling"])
async def test_a_point_of_another_profile_is_refused_before_it_is_queued(
    tmp_path: Path, *, poll: bool
) -> None:
    # Handed a Point, the line checks it is the device's own at the door: in the bus task,
    # the planner's refusal would end the line's polling.
    async with link_rig(tmp_path, PLANT, targets(), poll=poll) as rig:
        foreign = rig.links["cl2"].profile.point("concentration")
        with pytest.raises(ConfigError, match="no point 'concentration'"):
            await rig.links["s10"].read_points(foreign)
        with pytest.raises(ConfigError, match="not the one of profile"):
            await rig.links["s10"].read_points(rig.links["cl2"].profile.point("temperature"))
        assert await rig.links["s10"].read_value("temperature") is not None  # still served
        assert rig.polling is None or not rig.polling.done()
