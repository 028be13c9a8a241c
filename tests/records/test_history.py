"""The history the sensors forget: every entry of their rings copied into the records, once.

A tecLine keeps 5 calibrations (annex 7.2 of jumo-tecline.modbus.en.txt: entry 0 newest, a
later stamp pushes the others down and drops the oldest), an H10/H20 10 logbook entries
(6.1.6). Six weekly calibrations falling 6 % of the nominal 22 nA/ppm (annex 7.5.1) a
week, from 80 % to 50 %: the sensor holds the last five, the records all six, and care
fits its trend over the six. The simulated tecLine is the real simulator: its frames
encoded and answered in-process (a clocked master) where no line is needed, and on a
pseudo-terminal with the bus worker polling it for the path the running gateway takes.
"""

from __future__ import annotations

import asyncio
import contextlib
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Any

import pytest

from gateway.care import (
    Calibration,
    CareBook,
    CareKind,
    LogbookEntry,
    Records,
    assess,
    care_points,
    resolve,
    ring_entries,
)
from gateway.control.link import DeviceLink
from gateway.line.engine.devices import DeviceTarget
from gateway.line.samples import Quality, Sample
from gateway.profiles import PollGroup, get_profile
from gateway.records import DeviceRef, Kind, Query, RecordStore
from gateway.records.history import HistoryKeeper, device_refs
from gateway.shared.state import DeviceInfo, GatewayState, StateSink
from gateway.simulator import build_bus, parse_settings
from gateway.wire import codec, encoding, frames
from tests.rigs import rig
from tests.simulator.helpers import ClockedMaster
from tests.waiting import eventually

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator, Sequence
    from pathlib import Path

    from gateway.care import CareReport, SensorEntry

TECLINE = get_profile("jumo-tecline-cl2")
H10 = get_profile("jumo-digiline-odo-h10")
ADDRESS = 20
NOMINAL = 22.0  # nA/ppm, tecLine annex 7.5.1; the simulator's Cl2 cell
RATIOS = [0.80, 0.74, 0.68, 0.62, 0.56, 0.50]  # of nominal, oldest first, a week apart
FIRST = datetime(2026, 10, 1, 9, 0)  # zone-less, as the sensor keeps its stamps
STAMPS = [FIRST + timedelta(weeks=k) for k in range(len(RATIOS))]
NOW = STAMPS[-1].replace(tzinfo=UTC) + timedelta(days=2)
POOL = DeviceRef(name="pool", profile=TECLINE.id, bus="line1", address=ADDRESS, serial="S1")


def store_at(tmp_path: Path) -> RecordStore:
    return RecordStore(tmp_path / "records.sqlite", clock_synchronised=lambda: True)


def ring_after(calibrations: int) -> tuple[Calibration, ...]:
    """The history as the sensor shows it after that many calibrations: 5 newest, newest first."""
    done = [
        Calibration(x_zero=0.0, x_span=ratio * NOMINAL, stamp=stamp)
        for ratio, stamp in zip(RATIOS[:calibrations], STAMPS[:calibrations], strict=True)
    ]
    newest_first = list(reversed(done))[:5]
    return tuple(
        Calibration(x_zero=e.x_zero, x_span=e.x_span, stamp=e.stamp, number=n)
        for n, e in enumerate(newest_first)
    )


def history_records(store: RecordStore) -> list[dict[str, Any]]:
    """The ``data`` of every history record, in the order they were appended."""
    found = []
    for record in store.records(Query(kinds=(Kind.HISTORY,))):
        data = record.body["data"]
        assert isinstance(data, dict)
        found.append(data)
    return found


def holds(store: RecordStore, count: int) -> Callable[[], bool]:
    """Whether the store holds ``count`` history records (to wait for)."""
    return lambda: len(history_records(store)) == count


def stamps_of(entries: Sequence[SensorEntry]) -> list[datetime]:
    return [e.stamp for e in entries if isinstance(e, Calibration)]


# --- pure: six successive ring states --------------------------------------------------------


def test_six_ring_states_leave_six_records_though_the_ring_keeps_five(tmp_path: Path) -> None:
    store = store_at(tmp_path)
    keeper = HistoryKeeper(store)
    made_per_calibration = [len(keeper.copy(POOL, ring_after(k))) for k in range(1, 7)]
    assert made_per_calibration == [1, 1, 1, 1, 1, 1]  # the rotated entries recognised
    assert len(ring_after(6)) == 5
    copied = history_records(store)
    assert [d["entry"]["stamp"] for d in copied] == [s.isoformat() for s in STAMPS]
    assert [d["position"] for d in copied] == [0] * 6  # each copied as the new entry 0
    assert {d["sensor"] for d in copied} == {"serial:S1"}
    assert stamps_of(keeper.history(POOL)) == STAMPS  # oldest first
    record = next(store.records(Query(kinds=(Kind.HISTORY,))))
    assert record.body["result"] == "noted"
    assert record.body["device"] == POOL.as_dict()
    assert "2026-10-01 09:00" in str(record.body["note"])
    assert store.verify().intact


def test_an_entry_seen_again_is_not_copied_twice_nor_after_a_restart(tmp_path: Path) -> None:
    store = store_at(tmp_path)
    keeper = HistoryKeeper(store)
    for _ in range(3):
        keeper.copy(POOL, ring_after(6))
    assert len(history_records(store)) == 5
    store.close()

    reopened = store_at(tmp_path)
    again = HistoryKeeper(reopened)  # learns what was copied from the store
    assert again.copy(POOL, ring_after(6)) == []
    assert all(again.copied(POOL, entry) for entry in ring_after(6))
    assert stamps_of(again.history(POOL)) == STAMPS[1:]
    # The same sensor under another name in the config: its serial's history, not copied again.
    renamed = DeviceRef(name="basin", profile=TECLINE.id, serial="S1")
    assert again.copy(renamed, ring_after(6)) == []
    # Another sensor with the same entries (a spare calibrated alike): its own history.
    spare = DeviceRef(name="pool", profile=TECLINE.id, serial="S2")
    assert len(again.copy(spare, ring_after(6))) == 5
    assert len(history_records(reopened)) == 10
    assert reopened.verify().intact


def test_a_profile_without_a_serial_number_is_keyed_on_the_device_name(tmp_path: Path) -> None:
    keeper = HistoryKeeper(store_at(tmp_path))
    unnamed = DeviceRef(name="pool", profile=TECLINE.id)
    keeper.copy(unnamed, ring_after(2))
    assert [d["sensor"] for d in history_records(keeper.store)] == ["device:pool"] * 2
    assert keeper.copy(unnamed, ring_after(2)) == []
    assert keeper.history(POOL) == ()  # a serial's history is another


def test_a_store_that_cannot_be_written_gives_the_ring_back_and_copies_later(
    tmp_path: Path,
) -> None:
    store = store_at(tmp_path)
    HistoryKeeper(store).copy(POOL, ring_after(1))
    store.close()
    read_only = RecordStore(tmp_path / "records.sqlite", read_only=True)
    keeper = HistoryKeeper(read_only)
    whole = keeper.keep(POOL, ring_after(2))  # RecordError inside: logged, not raised
    assert stamps_of(whole) == STAMPS[:2]
    assert len(history_records(read_only)) == 1
    read_only.close()
    writable = store_at(tmp_path)
    assert len(HistoryKeeper(writable).copy(POOL, ring_after(2))) == 1  # copied at last


def test_care_fits_its_trend_over_the_whole_copied_history(tmp_path: Path) -> None:
    keeper = HistoryKeeper(store_at(tmp_path))
    for k in range(1, 7):
        keeper.copy(POOL, ring_after(k))
    values = history_values(ring_after(6))
    alone = tecline(values)
    whole = tecline(values, past=keeper.history(POOL))
    assert alone.slope_trend is not None
    assert alone.slope_trend.points == 5
    assert whole.slope_trend is not None
    assert whole.slope_trend.points == 6
    assert whole.slope_trend.per_week == pytest.approx(-0.06)
    assert whole.slope_trend.since == STAMPS[0].replace(tzinfo=UTC)
    # What the sensor holds is still what the care document shows.
    assert len(whole.records["history"]) == 5
    assert whole.slope_ratio == pytest.approx(0.50)


def test_the_trend_over_the_copy_starts_at_the_last_membrane_cap(tmp_path: Path) -> None:
    """A rise of the slope by more than 10 % of nominal is a new membrane cap and
    electrolyte (care's SERVICE_RISE): what came before it is another cap's, not fitted."""
    ratios = [0.40, 0.34, 0.90, 0.84, 0.78, 0.72, 0.66, 0.60]  # serviced at the third
    stamps = [FIRST + timedelta(weeks=k) for k in range(len(ratios))]
    done = [
        Calibration(x_zero=0.0, x_span=r * NOMINAL, stamp=s)
        for r, s in zip(ratios, stamps, strict=True)
    ]
    keeper = HistoryKeeper(store_at(tmp_path))
    for k in range(1, len(done) + 1):
        ring = [
            Calibration(x_zero=e.x_zero, x_span=e.x_span, stamp=e.stamp, number=n)
            for n, e in enumerate(reversed(done[:k]))
        ][:5]
        keeper.copy(POOL, ring)
    assert len(history_records(keeper.store)) == 8
    report = tecline(
        history_values(ring), now=stamps[-1].replace(tzinfo=UTC), past=keeper.history(POOL)
    )
    assert report.slope_trend is not None
    assert report.slope_trend.points == 6  # 0.90 to 0.60: this cap's six, not the eight
    assert report.slope_trend.since == stamps[2].replace(tzinfo=UTC)


def test_the_book_hands_each_ring_to_the_keeper_and_fits_over_what_it_gives_back(
    tmp_path: Path,
) -> None:
    """The running gateway's path: samples → CareBook → the keeper's seam → the records."""
    store = store_at(tmp_path)
    keeper = HistoryKeeper(store)
    serial: list[str | None] = [None]

    def identify(device: str) -> DeviceRef | None:
        return (
            None
            if serial[0] is None
            else DeviceRef(name=device, profile=TECLINE.id, serial=serial[0])
        )

    book = CareBook(clock=lambda: NOW, zone=UTC)
    book.keep_history(keeper.for_care(identify))
    points = care_points(TECLINE, CareKind.AMPEROMETRIC)
    book.add_device(
        bus="line1", device="pool", profile=TECLINE, rules=resolve(TECLINE, []), polled=points
    )
    book.observe(samples(history_values(ring_after(1)), at=0.0))
    assert history_records(store) == []  # the serial not read yet: nothing copied
    serial[0] = "S1"
    for k in range(2, 7):
        book.observe(samples(history_values(ring_after(k)), at=float(k)))
    report = book.report("pool")
    assert report is not None
    assert report.slope_trend is not None
    # The first ring was not copied, but its entry was still in the second ring.
    assert len(history_records(store)) == 6
    assert report.slope_trend.points == 6
    assert store.verify().intact


def test_the_running_gateway_names_a_device_with_the_serial_its_sensor_sent() -> None:
    state = GatewayState()
    state.add_device(
        DeviceInfo(
            bus="line1",
            name="pool",
            profile=TECLINE.id,
            address=ADDRESS,
            intervals={"serial_number": None, "concentration": 1.0},
        )
    )
    identify = device_refs(state)
    assert identify("pool") is None  # not read yet
    assert identify("nowhere") is None
    state.record(samples({"serial_number": "0104714601  "}, at=0.0, bus="line1"))
    assert identify("pool") == DeviceRef(
        name="pool", profile=TECLINE.id, bus="line1", address=ADDRESS, serial="0104714601"
    )


# --- the H10/H20 logbook ---------------------------------------------------------------------


def test_the_h10_logbook_is_copied_once_and_lengthens_this_caps_phase_drift(
    tmp_path: Path,
) -> None:
    """Twelve zero points a week apart on one cap, drifting 0.05 ° a week; the logbook
    holds 10. The records keep twelve, and the drift is fitted over the twelve."""
    now = datetime(2026, 11, 27, 12, 0, tzinfo=UTC)
    week = 7 * 86400.0
    done = [
        LogbookEntry(
            kind="zero_point",
            manual=False,
            rating="ok",
            operating_s=1_000_000.0 + k * week,
            date=now - timedelta(days=3 + 7 * (11 - k)),
            cap_counter=2.0,
            phase=60.0 + 0.05 * k,
        )
        for k in range(12)
    ]
    h10 = DeviceRef(name="dig", profile=H10.id, serial="H1")
    keeper = HistoryKeeper(store_at(tmp_path))
    for k in range(1, 13):
        newest_first = list(reversed(done[:k]))[:10]
        keeper.copy(h10, [_numbered(e, n) for n, e in enumerate(newest_first, start=1)])
        keeper.copy(h10, [_numbered(e, n) for n, e in enumerate(newest_first, start=1)])
    assert len(history_records(keeper.store)) == 12
    assert keeper.history(h10) == tuple(done)  # back from the records, oldest first
    reopened = HistoryKeeper(keeper.store)
    assert reopened.history(h10) == tuple(done)

    values = logbook_values(newest_first, operating_s=done[-1].operating_s or 0.0)
    rules = resolve(H10, [])
    assert rules is not None
    alone = assess(Records(values=values), rules, device="dig", bus="b", profile=H10.id, now=now)
    whole = assess(
        Records(values=values),
        rules,
        device="dig",
        bus="b",
        profile=H10.id,
        now=now,
        past=keeper.history(h10),
    )
    assert alone.figures["zero_point_phase_drift_points"] == 10
    assert whole.figures["zero_point_phase_drift_points"] == 12
    assert whole.figures["zero_point_phase_drift_per_week"] == pytest.approx(0.05)
    assert (
        whole.figures["cap_operating_days_at_least"] > alone.figures["cap_operating_days_at_least"]
    )
    assert keeper.store.verify().intact


# --- the real simulator: six calibrations of a simulated tecLine -----------------------------


def test_six_calibrations_of_a_simulated_tecline_leave_six_records_though_it_keeps_five(
    tmp_path: Path,
) -> None:
    """Each calibration as a master makes it (X_Zero and X_Span, then the date stamp that
    activates it, annex 7.2); after each, care's records read back over the wire."""
    bus = build_bus(
        parse_settings({"devices": [{"profile": TECLINE.id, "address": ADDRESS, "animate": False}]})
    )
    bus.start(0.0)
    master = ClockedMaster(bus)
    serial = str(read(master, "serial_number")).strip()
    sensor = DeviceRef(name="pool", profile=TECLINE.id, address=ADDRESS, serial=serial)
    store = store_at(tmp_path)
    keeper = HistoryKeeper(store)
    rings = []
    for ratio, stamp in zip(RATIOS, STAMPS, strict=True):
        write(master, "x_zero", 0.0)
        write(master, "x_span", ratio * NOMINAL)
        write(master, "calibration_stamp", stamp)
        records = Records(values={name: read(master, name) for name in care_points_of_tecline()})
        ring = ring_entries(records, TECLINE.ring("history"))
        rings.append(ring)
        keeper.copy(sensor, ring)

    assert [len(ring) for ring in rings] == [1, 2, 3, 4, 5, 5]  # the sensor keeps five
    assert stamps_of(rings[-1]) == list(reversed(STAMPS[1:]))
    copied = history_records(store)
    assert len(copied) == 6
    assert [d["entry"]["stamp"] for d in copied] == [s.isoformat() for s in STAMPS]
    assert {d["sensor"] for d in copied} == {f"serial:{serial}"}
    spans = [d["entry"]["x_span"] for d in copied]
    assert spans == pytest.approx([r * NOMINAL for r in RATIOS], rel=1e-6)  # float32 on the wire
    assert store.verify().intact

    report = tecline(dict(records.values), past=keeper.history(sensor))
    assert report.slope_trend is not None
    assert report.slope_trend.points == 6
    assert report.slope_trend.per_week == pytest.approx(-0.06, abs=1e-5)

    store.close()
    again = HistoryKeeper(store_at(tmp_path))  # a restart: the same ring read again
    assert again.copy(sensor, rings[-1]) == []
    assert len(again.history(sensor)) == 6


@pytest.mark.line
async def test_the_running_care_copies_six_calibrations_made_on_a_real_line(tmp_path: Path) -> None:
    """The simulator on a pseudo-terminal, the bus worker polling it, care's book wired to
    the keeper as the app wires it: six calibrations written through the line, each read
    back at once (the stamp's write moves the history, profiles/effects), six records."""
    profile = TECLINE
    intervals: dict[str, float | None] = {"concentration": 0.5, "unit": 60.0}
    intervals |= {p.name: 60.0 for p in profile.points if p.group is PollGroup.DIAGNOSTICS}
    intervals |= {"serial_number": None, "nominal_slope": None}
    polled = DeviceTarget(name="pool", address=ADDRESS, profile=profile, intervals=intervals)
    sensor = {"profile": profile.id, "address": ADDRESS, "animate": False}
    store = store_at(tmp_path)
    state = GatewayState(care=CareBook(clock=lambda: NOW))
    state.add_device(
        DeviceInfo(
            bus="line1", name="pool", profile=profile.id, address=ADDRESS, intervals=intervals
        )
    )
    state.care.add_device(
        bus="line1", device="pool", profile=profile, rules=resolve(profile, []), polled=intervals
    )
    state.care.keep_history(HistoryKeeper(store).for_care(device_refs(state)))
    async with rig(tmp_path, [sensor], [polled]) as base:
        base.worker.sinks.append(StateSink(state))
        link = DeviceLink(base.worker, "pool")
        polling = asyncio.create_task(base.worker.run())
        try:
            await eventually(lambda: state.care.report("pool"), within_s=20)
            for k, (ratio, stamp) in enumerate(zip(RATIOS, STAMPS, strict=True), start=1):
                await link.write(profile.point("x_zero"), 0.0)
                await link.write(profile.point("x_span"), ratio * NOMINAL)
                await link.write(profile.point("calibration_stamp"), stamp)
                await eventually(holds(store, k), within_s=10)
        finally:
            base.worker.request_stop()
            polling.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await polling
        held = base.server.bus.devices[ADDRESS].get("history_4_stamp")
        serial = str(base.server.bus.devices[ADDRESS].get("serial_number")).strip()

    assert held == STAMPS[1]  # the sensor keeps five: the first calibration is gone from it
    copied = history_records(store)
    assert [d["entry"]["stamp"] for d in copied] == [s.isoformat() for s in STAMPS]
    assert {d["sensor"] for d in copied} == {f"serial:{serial}"}
    report = state.care.report("pool")
    assert report is not None
    assert report.slope_trend is not None
    assert report.slope_trend.points == 6
    assert report.slope_trend.per_week == pytest.approx(-0.06, abs=1e-5)
    assert store.verify().intact


# --- helpers -----------------------------------------------------------------------------------


def care_points_of_tecline() -> tuple[str, ...]:
    return care_points(TECLINE, CareKind.AMPEROMETRIC)


def read(master: ClockedMaster, name: str) -> codec.Decoded:
    """One point over the simulated wire, decoded as the gateway decodes it."""
    point = TECLINE.point(name)
    response = master.ask(frames.read_request(ADDRESS, point.address, point.count))
    return codec.decode(point.format, response.registers)


def write(master: ClockedMaster, name: str, value: object) -> None:
    point = TECLINE.point(name)
    master.ask(frames.write_request(ADDRESS, point.address, encoding.encode(point.format, value)))


def history_values(ring: Sequence[Calibration]) -> dict[str, Any]:
    """A tecLine's care records holding ``ring`` (newest first), entries past it never set."""
    values: dict[str, Any] = {"nominal_slope": NOMINAL, "unit": codec.EnumValue(3, "ppm")}
    for index in range(5):
        entry = ring[index] if index < len(ring) else None
        values |= {
            f"history_{index}_x_zero": 0.0,
            f"history_{index}_x_span": 0.0 if entry is None else entry.x_span,
            f"history_{index}_stamp": None if entry is None else entry.stamp,
        }
    return values | {
        "x_zero": values["history_0_x_zero"],
        "x_span": values["history_0_x_span"],
        "calibration_stamp": values["history_0_stamp"],
    }


def tecline(
    values: dict[str, Any], *, now: datetime = NOW, past: Sequence[SensorEntry] = ()
) -> CareReport:
    rules = resolve(TECLINE, [])
    assert rules is not None
    return assess(
        Records(values=values),
        rules,
        device="pool",
        bus="line1",
        profile=TECLINE.id,
        now=now,
        zone=UTC,
        past=past,
    )


def _numbered(entry: LogbookEntry, number: int) -> LogbookEntry:
    return LogbookEntry(
        kind=entry.kind,
        manual=entry.manual,
        rating=entry.rating,
        operating_s=entry.operating_s,
        date=entry.date,
        cap_counter=entry.cap_counter,
        phase=entry.phase,
        number=number,
    )


def logbook_values(newest_first: Sequence[LogbookEntry], *, operating_s: float) -> dict[str, Any]:
    """H10 care records holding those logbook entries (1 newest), the counters in range."""
    values: dict[str, Any] = {
        "operating_seconds": operating_s + 3 * 86400,
        "sensor_replacement_counter": 2,
        "measurement_counter": 100_000,
        "measurement_counter_max": 1_000_000,
        "cip_cycles_since_calibration": 0,
        "sip_cycles_since_calibration": 0,
        "hours_outside_operating_temperature": 0.0,
        "error_register": codec.BitfieldValue(
            raw=0, flags=(("measurement_counter_overflow", False),)
        ),
        "status": codec.BitfieldValue(raw=0, flags=(("cap_missing", False),)),
    }
    for number, entry in enumerate(newest_first, start=1):
        prefix = f"logbook_{number}_"
        values |= {
            f"{prefix}entry_type": codec.EnumValue(20, entry.kind),
            f"{prefix}manual_change": codec.EnumValue(1, "calibration"),
            f"{prefix}rating": codec.EnumValue(1, entry.rating),
            f"{prefix}operating_seconds": entry.operating_s,
            f"{prefix}date": entry.date,
            f"{prefix}sensor_replacement_counter": entry.cap_counter,
            f"{prefix}phase": entry.phase,
        }
    return values


def samples(values: dict[str, Any], *, at: float, bus: str = "b") -> list[Sample]:
    return list(_samples(values, at=at, bus=bus))


def _samples(values: dict[str, Any], *, at: float, bus: str) -> Iterator[Sample]:
    for name, value in values.items():
        yield Sample(
            bus=bus,
            device="pool",
            profile=TECLINE.id,
            point=name,
            value=value,
            fault=None,
            unit=None,
            quality=Quality.GOOD,
            monotonic=at,
            time=NOW,
            group="diagnostics",
        )
