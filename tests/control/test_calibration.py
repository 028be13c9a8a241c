"""Guided calibrations: the arithmetic alone, then each flow against the simulator on a pty.

Expected registers come from the manuals' own examples: X_Span 153 nA/ppm is
``00 00 43 19`` (tecLine 2.4.3), the stamp 1903081310 is ``71 6E B7 5E`` (tecLine 2.6.2),
0.168 is ``08 31 3E 2C`` and 20.25 is ``00 00 41 A2`` (CDAB examples), calibration mode
"wet" is ``06 30 09 00 01`` (H10/H20 2.4.2) and the date 2025-02-10 starts ``07 E9 00 02
00 0A`` (H10/H20 2.4.1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from typing import TYPE_CHECKING, Any

import pytest

from gateway.config import FlashPolicy
from gateway.control.calibration import (
    HistoryEffect,
    HistoryEntry,
    Status,
    Step,
    StepKind,
    calibrate_oxygen_end_value,
    calibrate_oxygen_zero,
    calibrate_slope,
    calibrate_zero_point,
    calibration_stamp,
    check_slope,
    expected_history,
    history_effect,
    judge_slope,
    logbook_date,
    nominal_in_unit,
    restore_nominal_slope,
    slope_from,
    stamp_number,
)
from gateway.control.flash import FlashLedger, utc_today
from gateway.control.writes import SafeWriter
from gateway.errors import CalibrationInterruptedError, CommandRejectedError
from gateway.profiles import Slope, get_profile
from gateway.simulator.device import SlaveExceptionError
from tests.rigs import LinkRig, link_rig, link_target

if TYPE_CHECKING:
    from collections.abc import AsyncIterator
    from pathlib import Path

    from gateway.profiles import Point
    from gateway.simulator.device import Behaviour, SimulatedDevice


# --- the pure part ---------------------------------------------------------------------------


def test_slope_is_cell_current_less_zero_over_reference() -> None:
    assert slope_from(10.45, 0.5) == pytest.approx(20.9)  # simulator: 0.5 ppm x 22 x 0.95
    assert slope_from(76.668, 0.5, zero_na=0.168) == pytest.approx(153.0)  # annex 7.3.1 note


@pytest.mark.parametrize(
    ("current", "reference", "zero", "reason"),
    [
        (10.0, 0.0, 0.0, "reference concentration must be above 0"),
        (10.0, -0.5, 0.0, "reference concentration must be above 0"),
        (10.0, math.nan, 0.0, "reference concentration must be above 0"),
        (0.168, 0.5, 0.168, "not above the zero point"),
        (0.1, 0.5, 0.168, "not above the zero point"),
    ],
)
def test_a_slope_that_cannot_be_is_refused(
    current: float, reference: float, zero: float, reason: str
) -> None:
    with pytest.raises(CommandRejectedError, match=reason):
        slope_from(current, reference, zero_na=zero)


def _cell_slope() -> Slope:
    """The tecLine's slope limit and units, from its profile's data."""
    facts = get_profile("jumo-tecline-cl2").slope
    assert facts is not None
    return facts


CELL = _cell_slope()


def test_below_30_percent_of_nominal_is_low_and_30_percent_is_not() -> None:
    at_limit = judge_slope(6.0, 20.0, "ppm", CELL)
    assert at_limit.fraction == pytest.approx(0.30)
    assert not at_limit.low  # annex 7.3.4: "lower than 30 %"
    assert judge_slope(5.99, 20.0, "ppm", CELL).low
    assert judge_slope(20.9, 22.0, "ppm", CELL).fraction == pytest.approx(0.95)


def test_the_nominal_slope_per_ppm_is_converted_to_the_sensor_unit() -> None:
    assert nominal_in_unit(22.0, "ppm", CELL) == 22.0
    assert nominal_in_unit(7.5, "mg_per_l", CELL) == 7.5
    assert nominal_in_unit(22.0, "ppb", CELL) == pytest.approx(0.022)
    assert nominal_in_unit(22.0, "ug_per_l", CELL) == pytest.approx(0.022)  # Reiss unit 6
    assert nominal_in_unit(22.0, "g_per_l", CELL) == pytest.approx(22_000.0)
    judged = judge_slope(0.0066, 22.0, "ppb", CELL)  # 6.6 nA/ppm in nA/ppb
    assert judged.nominal == pytest.approx(0.022)
    assert judged.fraction == pytest.approx(0.30)
    with pytest.raises(CommandRejectedError, match="no known relation to ppm"):
        nominal_in_unit(22.0, "unknown_9", CELL)
    with pytest.raises(CommandRejectedError, match="nominal slope 0 nA/ppm"):
        judge_slope(6.0, 0.0, "ppm", CELL)


def test_stamp_is_yymmddhhmm_of_the_wall_clock_to_the_minute() -> None:
    assert stamp_number(datetime(2019, 3, 8, 13, 10)) == 1903081310  # tecLine 2.6.2
    assert divmod(1903081310, 0x10000) == (0x716E, 0xB75E)
    assert stamp_number(datetime(2019, 4, 10, 14, 30, 59, 999)) == 1904101430  # annex 7.3.2
    aware = datetime(2019, 4, 10, 14, 30, tzinfo=timezone(timedelta(hours=-5)))
    assert stamp_number(aware) == 1904101430  # no zone in the stamp: wall-clock time kept
    assert calibration_stamp(aware) == datetime(2019, 4, 10, 14, 30)
    assert stamp_number(datetime(2042, 12, 31, 23, 59)) == 4212312359  # annex 7.1, the last
    with pytest.raises(CommandRejectedError, match="2000-2042"):
        stamp_number(datetime(2043, 1, 1, 0, 0))


def test_history_effect_later_pushes_equal_or_earlier_overwrites() -> None:
    last = datetime(2019, 3, 8, 13, 10)
    assert history_effect(datetime(2019, 3, 8, 13, 11), last) is HistoryEffect.PUSH
    assert history_effect(datetime(2019, 3, 8, 13, 10, 59), last) is HistoryEffect.OVERWRITE
    assert history_effect(datetime(2019, 3, 8, 13, 9), last) is HistoryEffect.OVERWRITE
    assert history_effect(datetime(2019, 3, 8, 13, 9), None) is HistoryEffect.PUSH  # never set


def test_expected_history_follows_annex_7_2() -> None:
    old = tuple(HistoryEntry(0.1 * i, 20.0 - i, datetime(2018, 5 - i, 1, 12, 0)) for i in range(5))
    new = HistoryEntry(0.0, 21.0, datetime(2019, 1, 1, 8, 0))
    assert expected_history(old, new, HistoryEffect.PUSH) == (new, *old[:4])
    assert expected_history(old, new, HistoryEffect.OVERWRITE) == (new, *old[1:])


def test_logbook_date_keeps_the_second_and_an_offset() -> None:
    zone = timezone(timedelta(hours=1))
    assert logbook_date(datetime(2025, 2, 10, 8, 30, 15, 123, tzinfo=zone)) == datetime(
        2025, 2, 10, 8, 30, 15, tzinfo=zone
    )
    naive = logbook_date(datetime(2025, 2, 10, 8, 30, 15))
    assert naive.utcoffset() is not None
    assert naive.replace(tzinfo=None) == datetime(2025, 2, 10, 8, 30, 15)


# --- fakes and rigs --------------------------------------------------------------------------


@dataclass
class FakeOperator:
    """Records every step; answers each confirmation with ``answer``."""

    answer: bool = True
    steps: list[Step] = field(default_factory=list)
    questions: list[str] = field(default_factory=list)

    def show(self, step: Step) -> None:
        self.steps.append(step)

    def confirm(self, question: str) -> bool:
        self.questions.append(question)
        return self.answer

    def texts(self, kind: StepKind) -> list[str]:
        return [s.text for s in self.steps if s.kind is kind]


@dataclass
class Misbehaving:
    """A simulated sensor that refuses, or stores but ignores, writes to some points."""

    inner: Behaviour
    refuse: frozenset[str] = frozenset()
    ignore: frozenset[str] = frozenset()

    def start(self, device: SimulatedDevice, now: float) -> None:
        self.inner.start(device, now)

    def tick(self, device: SimulatedDevice, now: float) -> None:
        self.inner.tick(device, now)

    def filter_write(self, device: SimulatedDevice, points: list[Point]) -> list[Point]:
        refused = [p.name for p in points if p.name in self.refuse]
        if refused:
            raise SlaveExceptionError(3, f"{refused} refused by the test")
        return self.inner.filter_write(device, points)

    def on_write(self, device: SimulatedDevice, points: list[Point], now: float) -> None:
        self.inner.on_write(device, [p for p in points if p.name not in self.ignore], now)


CELLS = [
    {"profile": "jumo-tecline-cl2", "address": 20, "animate": False},
    {"profile": "reiss-m0c", "address": 10, "animate": False},
]
CELL_TARGETS = [
    link_target("cl2", "jumo-tecline-cl2", 20),
    link_target("m0c", "reiss-m0c", 10),
]
CELL_ADDRESS = {"cl2": 20, "m0c": 10}
OXYGEN = [
    {"profile": "jumo-digiline-odo-h10", "address": 2, "animate": False},
    {"profile": "jumo-digiline-odo-h20", "address": 3, "animate": False},
]
OXYGEN_TARGETS = [
    link_target("h10", "jumo-digiline-odo-h10", 2),
    link_target("h20", "jumo-digiline-odo-h20", 3),
]
OXYGEN_ADDRESS = {"h10": 2, "h20": 3}

# Five calibrations, entry 0 newest (tecLine annex 7.2).
SEEDED = tuple(
    HistoryEntry(x_zero=0.0, x_span=21.0 - i, stamp=datetime(2018, 12 - i, 1, 10, 0))
    for i in range(5)
)
STAMP = datetime(2019, 3, 8, 13, 10)  # 1903081310 = 0x716E 0xB75E, tecLine 2.6.2
STAMP_REGISTERS = (0x716E, 0xB75E)


@pytest.fixture
async def cells(tmp_path: Path) -> AsyncIterator[LinkRig]:
    async with link_rig(tmp_path, CELLS, CELL_TARGETS) as r:
        yield r


@pytest.fixture
async def oxygen(tmp_path: Path) -> AsyncIterator[LinkRig]:
    async with link_rig(tmp_path, OXYGEN, OXYGEN_TARGETS) as r:
        yield r


@pytest.fixture
def ledger(tmp_path: Path) -> FlashLedger:
    return FlashLedger(tmp_path / "flash.sqlite")


def writer_for(r: LinkRig, name: str, ledger: FlashLedger, *, budget: int = 4) -> SafeWriter:
    # No allow-list: a calibration's explicit writes need none, only the budget.
    policy = FlashPolicy(allowed=frozenset(), daily_budget=budget)
    return SafeWriter(r.links[name], policy=policy, ledger=ledger)


def seed(device: SimulatedDevice, entries: tuple[HistoryEntry, ...]) -> None:
    """History entries as given, and the current calibration equal to entry 0."""
    for i, entry in enumerate(entries):
        device.put(f"history_{i}_x_zero", entry.x_zero)
        device.put(f"history_{i}_x_span", entry.x_span)
        device.put(f"history_{i}_stamp", entry.stamp)
    device.put("x_zero", entries[0].x_zero)
    device.put("x_span", entries[0].x_span)
    device.put("calibration_stamp", entries[0].stamp)


def history(device: SimulatedDevice) -> list[HistoryEntry]:
    entries = []
    for i in range(5):
        zero, span, stamp = (device.get(f"history_{i}_{p}") for p in ("x_zero", "x_span", "stamp"))
        assert isinstance(zero, float)
        assert isinstance(span, float)
        assert stamp is None or isinstance(stamp, datetime)
        entries.append(HistoryEntry(zero, span, stamp))
    return entries


def same(a: list[HistoryEntry], b: list[HistoryEntry] | tuple[HistoryEntry, ...]) -> bool:
    return len(a) == len(b) and all(x.matches(y) for x, y in zip(a, b, strict=True))


def written(r: LinkRig, address: int) -> list[tuple[int, int, tuple[int, ...]]]:
    """The write log as (function, address, registers); every write accepted."""
    log = r.writes(address)
    assert all(w.exception is None for w in log), log
    return [(w.function, w.address, w.values) for w in log]


def wait_on_the_wire(r: LinkRig, device: int, function: int, address: int) -> float:
    """Silence from the answer to a write until the next request to the same device."""
    records = r.rig.frames()
    index = next(
        i
        for i, rec in enumerate(records)
        if (rec.device, rec.function, rec.address) == (device, function, address)
    )
    answered = records[index].answer_at
    assert answered is not None
    following = next(rec for rec in records[index + 1 :] if rec.device == device)
    gap: float = following.start - answered
    return gap


# --- tecLine / Reiss slope -------------------------------------------------------------------


@pytest.mark.parametrize("name", ["cl2", "m0c"])
@pytest.mark.line
async def test_slope_calibration_writes_the_annex_registers_and_pushes_the_history(
    cells: LinkRig, ledger: FlashLedger, name: str
) -> None:
    device = cells.device(CELL_ADDRESS[name])
    seed(device, SEEDED)
    device.hold("cell_current", 76.5)  # with 0.5 ppm: 153 nA/ppm, the tecLine 2.4.3 example
    operator = FakeOperator()
    outcome = await calibrate_slope(
        writer_for(cells, name, ledger), operator, reference=0.5, when=STAMP
    )
    assert outcome.status is Status.CALIBRATED, outcome.failed_checks
    # Annex 7.3.2: X_Zero, then X_Span, then the date stamp, each with function 16.
    assert written(cells, CELL_ADDRESS[name]) == [
        (16, 0x0206, (0x0000, 0x0000)),  # X_Zero 0 nA (the sensor held 0)
        (16, 0x0208, (0x0000, 0x4319)),  # X_Span 153.0, CDAB as in tecLine 2.4.3
        (16, 0x020A, STAMP_REGISTERS),  # 1903081310, high word first
    ]
    # Annex 7.2, later stamp: new entry 0, the others one down, the oldest dropped.
    new = HistoryEntry(0.0, 153.0, STAMP)
    assert same(history(device), (new, *SEEDED[:4]))
    assert device.get("concentration") == pytest.approx(0.5)  # (76.5 - 0) / 153
    assert [c.ok for c in outcome.checks] == [True] * 6
    assert outcome.values["history_effect"] is HistoryEffect.PUSH
    assert outcome.values["concentration_after"] == pytest.approx(0.5)
    assert len(operator.questions) == 1
    assert "3 register block(s)" in operator.questions[0]
    assert cells.violations() == []
    today = utc_today()
    for point in ("x_zero", "x_span", "calibration_stamp"):
        assert ledger.count_today(name, point, today) == 1  # every flash write counted


@pytest.mark.line
async def test_equal_stamp_overwrites_entry_0_and_keeps_entries_1_to_4(
    cells: LinkRig, ledger: FlashLedger
) -> None:
    device = cells.device(20)
    seeded = (HistoryEntry(0.0, 21.0, STAMP), *SEEDED[1:])
    seed(device, seeded)
    device.hold("cell_current", 76.5)
    outcome = await calibrate_slope(
        writer_for(cells, "cl2", ledger), FakeOperator(), reference=0.5, when=STAMP
    )
    assert outcome.status is Status.CALIBRATED, outcome.failed_checks
    assert outcome.values["history_effect"] is HistoryEffect.OVERWRITE
    assert written(cells, 20)[-1] == (16, 0x020A, STAMP_REGISTERS)  # the same stamp again
    after = history(device)
    assert after[0].matches(HistoryEntry(0.0, 153.0, STAMP))
    assert same(after[1:], seeded[1:])  # annex 7.2: positions 1-4 unaffected
    assert not any(e.matches(seeded[0]) for e in after)  # the old entry 0 is gone


@pytest.mark.line
async def test_earlier_stamp_warns_and_overwrites_entry_0(
    cells: LinkRig, ledger: FlashLedger
) -> None:
    device = cells.device(20)
    seed(device, SEEDED)
    device.hold("cell_current", 76.5)
    operator = FakeOperator()
    outcome = await calibrate_slope(
        writer_for(cells, "cl2", ledger),
        operator,
        reference=0.5,
        when=datetime(2018, 6, 1, 9, 0),  # before entry 0 (2018-12-01)
    )
    assert outcome.status is Status.CALIBRATED
    assert any("earlier than history entry 0" in w for w in outcome.warnings)
    assert same(history(device)[1:], SEEDED[1:])


@pytest.mark.line
async def test_slope_below_30_percent_of_nominal_warns(cells: LinkRig, ledger: FlashLedger) -> None:
    device = cells.device(20)
    seed(device, SEEDED)
    device.hold("cell_current", 3.0)  # 3.0 nA / 0.5 ppm = 6 nA/ppm; nominal 22: 27 %
    operator = FakeOperator()
    outcome = await calibrate_slope(
        writer_for(cells, "cl2", ledger), operator, reference=0.5, when=STAMP
    )
    assert outcome.status is Status.CALIBRATED  # a warning, as the annex advises, not a refusal
    assert outcome.values["slope_fraction_of_nominal"] == pytest.approx(6.0 / 22.0)
    [warning] = outcome.warnings
    assert "27% of the nominal 22 nA/ppm" in warning
    assert "below 30%" in warning
    assert "maintenance" in warning
    assert warning in operator.texts(StepKind.WARNING)
    assert written(cells, 20)[1] == (16, 0x0208, (0x0000, 0x40C0))  # 6.0 in CDAB


@pytest.mark.line
async def test_healthy_slope_gives_no_warning(cells: LinkRig, ledger: FlashLedger) -> None:
    seed(cells.device(20), SEEDED)
    # Static simulator: cell current 0.5 ppm x 22 nA/ppm x 0.95 = 10.45 nA.
    outcome = await calibrate_slope(
        writer_for(cells, "cl2", ledger), FakeOperator(), reference=0.5, when=STAMP
    )
    assert outcome.values["x_span"] == pytest.approx(20.9)
    assert outcome.values["slope_fraction_of_nominal"] == pytest.approx(0.95)
    assert outcome.warnings == ()


@pytest.mark.line
async def test_noted_cell_current_is_used_instead_of_a_reading(
    cells: LinkRig, ledger: FlashLedger
) -> None:
    seed(cells.device(20), SEEDED)
    outcome = await calibrate_slope(
        writer_for(cells, "cl2", ledger),
        FakeOperator(),
        reference=0.5,
        cell_current_na=76.5,
        when=STAMP,
    )
    assert written(cells, 20)[1] == (16, 0x0208, (0x0000, 0x4319))
    # The sensor reads 10.45 nA now, so (10.45 - 0) / 153 is far from 0.5: annex 7.3.3 check.
    assert any("not broadly identical" in w for w in outcome.warnings)


@pytest.mark.line
async def test_declining_writes_nothing(cells: LinkRig, ledger: FlashLedger) -> None:
    device = cells.device(20)
    seed(device, SEEDED)
    operator = FakeOperator(answer=False)
    outcome = await calibrate_slope(
        writer_for(cells, "cl2", ledger), operator, reference=0.5, when=STAMP
    )
    assert outcome.status is Status.DECLINED
    assert outcome.writes == ()
    assert cells.writes(20) == []
    assert len(operator.texts(StepKind.PLAN)) == 3  # shown before asking
    assert same(history(device), SEEDED)
    assert ledger.count_today("cl2", "x_span", utc_today()) == 0


@pytest.mark.line
async def test_flash_budget_0_refuses_before_anything_is_written(
    cells: LinkRig, ledger: FlashLedger
) -> None:
    seed(cells.device(20), SEEDED)
    operator = FakeOperator()
    with pytest.raises(CommandRejectedError, match="budget of 0 writes per day"):
        await calibrate_slope(
            writer_for(cells, "cl2", ledger, budget=0), operator, reference=0.5, when=STAMP
        )
    assert cells.writes(20) == []
    assert operator.questions == []  # refused before asking


@pytest.mark.line
async def test_a_spent_budget_on_the_last_point_stops_the_whole_calibration(
    cells: LinkRig, ledger: FlashLedger
) -> None:
    seed(cells.device(20), SEEDED)
    for _ in range(2):
        ledger.record("cl2", "calibration_stamp", utc_today())
    with pytest.raises(CommandRejectedError, match="calibration_stamp: budget of 2"):
        await calibrate_slope(
            writer_for(cells, "cl2", ledger, budget=2),
            FakeOperator(),
            reference=0.5,
            when=STAMP,
        )
    # X_Zero and X_Span had budget left, but without the stamp they would hang unactivated.
    assert cells.writes(20) == []


@pytest.mark.line
async def test_a_refused_stamp_says_what_was_written_and_that_it_is_not_active(
    cells: LinkRig, ledger: FlashLedger
) -> None:
    device = cells.device(20)
    seed(device, SEEDED)
    device.behaviour = Misbehaving(device.behaviour, refuse=frozenset({"calibration_stamp"}))
    with pytest.raises(CalibrationInterruptedError) as caught:
        await calibrate_slope(
            writer_for(cells, "cl2", ledger), FakeOperator(), reference=0.5, when=STAMP
        )
    assert caught.value.written == ("x_zero", "x_span")
    assert caught.value.failed == "calibration_stamp"
    assert "exception 03" in str(caught.value)
    assert "date stamp activates" in str(caught.value)
    assert same(history(device), SEEDED)


@pytest.mark.line
async def test_a_history_that_did_not_move_fails_verification(
    cells: LinkRig, ledger: FlashLedger
) -> None:
    device = cells.device(20)
    seed(device, SEEDED)
    device.behaviour = Misbehaving(device.behaviour, ignore=frozenset({"calibration_stamp"}))
    outcome = await calibrate_slope(
        writer_for(cells, "cl2", ledger), FakeOperator(), reference=0.5, when=STAMP
    )
    assert outcome.status is Status.VERIFICATION_FAILED
    failed = [c.name for c in outcome.failed_checks]
    assert failed[0] == "history entry 0 (X_Zero 0x0210, X_Span 0x0212)"
    assert all(name.startswith("history entry") for name in failed)
    assert outcome.checks[0].ok  # 0x0206-0x020A hold what was written


# --- tecLine / Reiss zero point and nominal slope --------------------------------------------


@pytest.mark.line
async def test_zero_point_then_slope_subtracts_the_new_zero(
    cells: LinkRig, ledger: FlashLedger
) -> None:
    device = cells.device(20)
    seed(device, SEEDED)
    writer = writer_for(cells, "cl2", ledger)
    span_before = tuple(device.registers[a] for a in (0x0208, 0x0209))
    device.hold("cell_current", 0.168)  # disinfectant-free medium
    zero = await calibrate_zero_point(writer, FakeOperator(), when=STAMP)
    assert zero.status is Status.CALIBRATED, zero.failed_checks
    assert written(cells, 20) == [
        (16, 0x0206, (0x0831, 0x3E2C)),  # X_Zero 0.168 nA
        (16, 0x0208, span_before),  # X_Span as the sensor held it
        (16, 0x020A, STAMP_REGISTERS),
    ]
    assert history(device)[0].matches(HistoryEntry(0.168, SEEDED[0].x_span, STAMP))

    device.hold("cell_current", 76.668)  # disinfectant back: (76.668 - 0.168) / 0.5 = 153
    later = STAMP + timedelta(minutes=1)  # annex 7.2 note: at least a minute apart
    slope = await calibrate_slope(writer, FakeOperator(), reference=0.5, when=later)
    assert slope.status is Status.CALIBRATED, slope.failed_checks
    assert written(cells, 20)[3:] == [
        (16, 0x0206, (0x0831, 0x3E2C)),  # the zero point kept (annex 7.3.2 step 1)
        (16, 0x0208, (0x0000, 0x4319)),
        (16, 0x020A, divmod(1903081311, 0x10000)),
    ]
    assert same(
        history(device),
        (
            HistoryEntry(0.168, 153.0, later),
            HistoryEntry(0.168, SEEDED[0].x_span, STAMP),
            *SEEDED[:3],
        ),
    )


@pytest.mark.parametrize(
    ("name", "nominal_registers"),
    [("cl2", (0x0000, 0x41B0)), ("m0c", (0x0000, 0x4120))],  # 22.0 and 10.0 in CDAB
)
@pytest.mark.line
async def test_restoring_the_nominal_slope_in_the_annex_order(
    cells: LinkRig, ledger: FlashLedger, name: str, nominal_registers: tuple[int, int]
) -> None:
    device = cells.device(CELL_ADDRESS[name])
    seeded = (HistoryEntry(0.168, 15.0, datetime(2018, 12, 1, 10, 0)), *SEEDED[1:])
    seed(device, seeded)
    nominal = device.get("nominal_slope")
    assert isinstance(nominal, float)
    outcome = await restore_nominal_slope(
        writer_for(cells, name, ledger), FakeOperator(), when=STAMP
    )
    assert outcome.status is Status.CALIBRATED, outcome.failed_checks
    # Annex 7.5.1 / Reiss 5.3.1: X_Span first (step 2), then X_Zero 0 (step 3), then the stamp.
    assert written(cells, CELL_ADDRESS[name]) == [
        (16, 0x0208, nominal_registers),
        (16, 0x0206, (0x0000, 0x0000)),
        (16, 0x020A, STAMP_REGISTERS),
    ]
    # 7.5.2: 0x0210 holds 0 and 0x0212 the nominal slope; the last calibration moved to 1.
    assert same(history(device), (HistoryEntry(0.0, nominal, STAMP), *seeded[:4]))


@pytest.mark.line
async def test_check_writes_nothing_and_warns_below_30_percent(
    cells: LinkRig, ledger: FlashLedger
) -> None:
    device = cells.device(10)
    seed(device, SEEDED)
    device.hold("cell_current", 1.2)  # 1.2 / 0.5 = 2.4 nA/ppm; Reiss nominal 10: 24 %
    outcome = await check_slope(writer_for(cells, "m0c", ledger), FakeOperator(), reference=0.5)
    assert outcome.status is Status.CHECKED
    assert outcome.values["slope_now"] == pytest.approx(2.4)
    assert any("24% of the nominal 10 nA/ppm" in w for w in outcome.warnings)
    assert cells.writes(10) == []


@pytest.mark.line
async def test_a_profile_without_the_registers_is_refused(
    oxygen: LinkRig, ledger: FlashLedger
) -> None:
    with pytest.raises(CommandRejectedError, match="has no slope calibration"):
        await calibrate_slope(
            writer_for(oxygen, "h10", ledger), FakeOperator(), reference=0.5, when=STAMP
        )
    assert oxygen.rig.frames() == []  # refused before any I/O


# --- H10 / H20 -------------------------------------------------------------------------------

ZONE = timezone(timedelta(hours=1))
WHEN = datetime(2025, 2, 10, 8, 30, 15, tzinfo=ZONE)  # 2025-02-10 as in H10/H20 2.4.1
DATE_REGISTERS = (0x07E9, 0x0002, 0x000A, 8, 30, 15, 60)  # offset +60 min


def logbook_1(device: SimulatedDevice) -> dict[str, Any]:
    names = [p.name for p in device.profile.points if p.name.startswith("logbook_1_")]
    return {n.removeprefix("logbook_1_"): device.get(n) for n in names}


@pytest.mark.parametrize("name", ["h10", "h20"])
@pytest.mark.line
async def test_oxygen_zero_point_sets_mode_and_date_triggers_and_logs(
    oxygen: LinkRig, ledger: FlashLedger, name: str
) -> None:
    address = OXYGEN_ADDRESS[name]
    device = oxygen.device(address)
    device.hold("phase_shift", 41.25)
    device.hold("temperature", 21.5)
    operator = FakeOperator()
    outcome = await calibrate_oxygen_zero(
        writer_for(oxygen, name, ledger), operator, when=WHEN, mode="wet"
    )
    assert outcome.status is Status.CALIBRATED, outcome.failed_checks
    assert written(oxygen, address) == [
        (6, 0x3009, (0x0001,)),  # calibration mode "wet", H10/H20 2.4.2
        (16, 0x300A, DATE_REGISTERS),
        (16, 0x3003, (0x0000, 0x0000)),  # any value starts it; 0.0 is written
    ]
    # 6.2.4: 0x203F/0x2041 take the last measured values; 0x3009 is back to 0.
    assert device.get("zero_point_phase") == 41.25
    assert device.get("zero_point_temperature") == 21.5
    assert str(device.get("calibration_mode")) == "as_configured"
    entry = logbook_1(device)
    assert str(entry["entry_type"]) == "zero_point"  # type 20
    assert entry["date"] == WHEN
    assert entry["phase"] == 41.25
    assert outcome.record["date"] == WHEN  # read back over the bus and shown
    assert str(outcome.record["entry_type"]) == "zero_point"
    assert any(
        "logbook entry 1 (newest) after: zero_point" in t for t in operator.texts(StepKind.READ)
    )
    # The waits on the wire: 250 ms after every write, 650 ms after 0x3003 (6.1.5).
    assert wait_on_the_wire(oxygen, address, 6, 0x3009) >= 0.25
    assert wait_on_the_wire(oxygen, address, 16, 0x300A) >= 0.25
    assert wait_on_the_wire(oxygen, address, 16, 0x3003) >= 0.65
    assert oxygen.violations() == []
    assert ledger.count_today(name, "zero_point_calibration_trigger", utc_today()) == 1
    assert ledger.count_today(name, "calibration_date", utc_today()) == 0  # volatile


@pytest.mark.parametrize("name", ["h10", "h20"])
@pytest.mark.line
async def test_oxygen_end_value_writes_reference_and_trigger_and_logs(
    oxygen: LinkRig, ledger: FlashLedger, name: str
) -> None:
    address = OXYGEN_ADDRESS[name]
    device = oxygen.device(address)
    device.hold("phase_shift", 20.5)
    outcome = await calibrate_oxygen_end_value(
        writer_for(oxygen, name, ledger),
        FakeOperator(),
        reference=20.25,
        unit="percent_volume",
        when=WHEN,
    )
    assert outcome.status is Status.CALIBRATED, outcome.failed_checks
    assert written(oxygen, address) == [
        (16, 0x204B, (0x0000, 0x0010)),  # unit % Vol. (code 0x10), 0x204B held no unit
        (16, 0x2043, (0x0000, 0x41A2)),  # 20.25, CDAB
        (6, 0x3009, (0x0000,)),  # mode as configured at 0x2021
        (16, 0x300A, DATE_REGISTERS),
        (16, 0x3005, (0x0000, 0x41A2)),  # the trigger, with the reference
    ]
    entry = logbook_1(device)
    assert str(entry["entry_type"]) == "end_value"  # type 21
    assert entry["date"] == WHEN
    assert entry["oxygen"] == 20.25
    assert entry["oxygen_unit"] == "%vol"
    assert entry["phase"] == 20.5
    assert device.get("end_value_phase") == 20.5
    assert outcome.record["oxygen"] == 20.25
    for write_address in (0x204B, 0x2043, 0x3005):  # "0x2031 ff." and 0x3005: 650 ms
        assert wait_on_the_wire(oxygen, address, 16, write_address) >= 0.65
    assert wait_on_the_wire(oxygen, address, 6, 0x3009) >= 0.25
    assert oxygen.violations() == []


@pytest.mark.line
async def test_end_value_keeps_a_unit_the_sensor_already_has(
    oxygen: LinkRig, ledger: FlashLedger
) -> None:
    device = oxygen.device(2)
    device.put("end_value_oxygen_unit", "percent_saturation")
    outcome = await calibrate_oxygen_end_value(
        writer_for(oxygen, "h10", ledger), FakeOperator(), reference=95.5, when=WHEN
    )
    assert outcome.status is Status.CALIBRATED, outcome.failed_checks
    assert [a for _, a, _ in written(oxygen, 2)] == [0x2043, 0x3009, 0x300A, 0x3005]
    assert logbook_1(device)["oxygen_unit"] == "%sat"


@pytest.mark.line
async def test_end_value_without_a_known_unit_is_refused(
    oxygen: LinkRig, ledger: FlashLedger
) -> None:
    with pytest.raises(CommandRejectedError, match="not a known unit"):
        await calibrate_oxygen_end_value(
            writer_for(oxygen, "h10", ledger), FakeOperator(), reference=20.25, when=WHEN
        )
    assert oxygen.writes(2) == []


@pytest.mark.line
async def test_oxygen_budget_0_writes_not_even_the_volatile_registers(
    oxygen: LinkRig, ledger: FlashLedger
) -> None:
    with pytest.raises(CommandRejectedError, match="zero_point_calibration_trigger: budget of 0"):
        await calibrate_oxygen_zero(
            writer_for(oxygen, "h10", ledger, budget=0), FakeOperator(), when=WHEN
        )
    assert oxygen.writes(2) == []


@pytest.mark.line
async def test_oxygen_declined_writes_nothing(oxygen: LinkRig, ledger: FlashLedger) -> None:
    before = logbook_1(oxygen.device(2))
    outcome = await calibrate_oxygen_zero(
        writer_for(oxygen, "h10", ledger), FakeOperator(answer=False), when=WHEN
    )
    assert outcome.status is Status.DECLINED
    assert oxygen.writes(2) == []
    assert logbook_1(oxygen.device(2)) == before


@pytest.mark.line
async def test_a_trigger_that_logs_nothing_fails_verification(
    oxygen: LinkRig, ledger: FlashLedger
) -> None:
    device = oxygen.device(2)
    device.behaviour = Misbehaving(
        device.behaviour, ignore=frozenset({"zero_point_calibration_trigger"})
    )
    outcome = await calibrate_oxygen_zero(
        writer_for(oxygen, "h10", ledger), FakeOperator(), when=WHEN
    )
    assert outcome.status is Status.VERIFICATION_FAILED
    failed = {c.name for c in outcome.failed_checks}
    assert {"new logbook entry type", "new logbook entry date (0x300A-0x3010)"} <= failed
