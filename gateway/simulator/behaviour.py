"""What each sensor family does on its own: moving values, triggers, calibration rules.

A behaviour fills in a plausible nameplate at start, moves process values on ``tick``
(unless the device is static or a point is held), and reacts to writes as the manuals
describe. Where a manual is silent the choice is named in a comment. With an ``aging:``
block a behaviour also lays out the records of a sensor in service (:mod:`.aging`) at start.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING

from gateway.simulator import aging as ages
from gateway.wire import codec, encoding

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.profiles import Point
    from gateway.simulator.aging import Aged, AgingSettings
    from gateway.simulator.device import Behaviour, SimulatedDevice

    WallClock = Callable[[], datetime]  # an aware datetime: the simulator's wall-clock now

STANDARD_PRESSURE_HPA = 1013.25
OXYGEN_FRACTION = 0.2095  # of dry air
SINGLE_MEASUREMENT_S = 0.3  # H10/H20: not documented; long enough to observe bit 1
IN_SERVICE_SLOPE = 0.95  # of nominal: the real slope of a cell without an aging block


def _utc_now() -> datetime:
    return datetime.now(tz=UTC)


def saturation_mg_per_l(temperature_c: float, salinity: float = 0.0) -> float:
    """Oxygen solubility in water at 1013.25 hPa (Benson-Krause style polynomial).

    Salinity (the S10's electrolytic conductivity in mS/cm) lowers it by a simple linear
    factor; good enough for a simulator whose values must only move plausibly.
    """
    t = temperature_c
    fresh = 14.652 - 0.41022 * t + 0.007991 * t**2 - 0.000077774 * t**3
    return max(0.0, fresh * (1.0 - 0.0035 * salinity))


@dataclass(slots=True)
class _Process:
    """The true state of the simulated water, shared by the family behaviours."""

    rng: random.Random
    started: float = 0.0
    temperature_c: float = 20.0
    saturation_pct: float = 92.0

    def advance(self, now: float) -> None:
        t = now - self.started
        self.temperature_c = 20.0 + 1.5 * math.sin(2 * math.pi * t / 600) + self.rng.gauss(0, 0.02)
        self.saturation_pct = 92.0 + 3.0 * math.sin(2 * math.pi * t / 240) + self.rng.gauss(0, 0.1)

    @property
    def partial_pressure_hpa(self) -> float:
        return OXYGEN_FRACTION * STANDARD_PRESSURE_HPA * self.saturation_pct / 100


@dataclass(slots=True)
class _Digiline:
    """Parts common to the S10 and H10/H20."""

    process: _Process
    device_name: str
    sensor_type: int
    sub_type: int
    clock: WallClock = _utc_now
    started_wall: datetime = field(default_factory=_utc_now)
    started: float = 0.0
    operating_base_s: int = ages.OPERATING_SECONDS_AT_START

    def nameplate(self, device: SimulatedDevice, now: float) -> None:
        self.started = now
        self.started_wall = self.clock().astimezone(UTC)
        self.process.started = now
        device.put("device_name", self.device_name)
        device.put("software_version", "312.01.02")
        device.put("software_number", 312)
        device.put("hardware_version_major", 1)
        device.put("serial_number", f"{device.profile.id[-3:].upper()}{device.address:07d}")
        device.put("sensor_type", self.sensor_type)
        device.put("oxygen_sub_type", self.sub_type)
        device.put("part_number", "00753777")
        device.put("order_code", f"{device.profile.title}/SIM")
        device.put("manufacture_date", datetime(2024, 3, 1, 8, 0, tzinfo=UTC))
        device.put("commissioning_date", datetime(2025, 1, 15, 9, 30, tzinfo=UTC))
        device.put("float_format", 0)

    def operating_seconds(self, device: SimulatedDevice, now: float) -> None:
        device.put("operating_seconds", self.operating_base_s + int(now - self.started))

    def wall(self, now: float) -> datetime:
        return self.started_wall + timedelta(seconds=now - self.started)


@dataclass(slots=True)
class S10Behaviour:
    """JUMO digiLine O-DO S10: oxygen from partial pressure with flash or RAM compensation."""

    common: _Digiline
    clock_offset_s: float = 0.0  # sensor clock minus simulator clock, set by writes
    aging: AgingSettings | None = None

    def start(self, device: SimulatedDevice, now: float) -> None:
        self.common.nameplate(device, now)
        device.put("oxygen_unit", "ppm")
        device.put("compensation_salinity_fixed", 0.0)
        device.put("compensation_pressure_fixed", STANDARD_PRESSURE_HPA)
        device.put("compensation_temperature", 20.0)
        device.put("compensation_salinity", 0.0)
        device.put("compensation_pressure", STANDARD_PRESSURE_HPA)
        if self.aging is not None:
            self.common.operating_base_s = ages.operating_seconds(self.aging)
            apply_aged(device, ages.s10_values(self.aging, now=self.common.started_wall))
        self.tick(device, now)

    def compensation(self, device: SimulatedDevice) -> tuple[float, float, float]:
        """Temperature, salinity and pressure the sensor uses, by the control byte (6.8.1)."""
        control = device.get("compensation_control")
        ram = set(control.active) if isinstance(control, codec.BitfieldValue) else set()
        temperature = device.get(
            "compensation_temperature" if "temperature_from_ram" in ram else "temperature"
        )
        salinity = device.get(
            "compensation_salinity" if "salinity_from_ram" in ram else "compensation_salinity_fixed"
        )
        pressure = device.get(
            "compensation_pressure" if "pressure_from_ram" in ram else "compensation_pressure_fixed"
        )
        return _num(temperature, 20.0), _num(salinity, 0.0), _num(pressure, STANDARD_PRESSURE_HPA)

    def tick(self, device: SimulatedDevice, now: float) -> None:
        common = self.common
        if device.animate:
            common.process.advance(now)
        device.put("temperature", round(common.process.temperature_c, 3))
        common.operating_seconds(device, now)
        clock = (common.wall(now) + timedelta(seconds=self.clock_offset_s)).replace(microsecond=0)
        device.put("clock", clock)
        device.put("oxygen", self.oxygen(device))

    def oxygen(self, device: SimulatedDevice) -> float:
        """The measured value in the configured unit (6.5: salt only for ppm, pressure for %)."""
        temperature, salinity, pressure = self.compensation(device)
        p_o2 = self.common.process.partial_pressure_hpa
        unit = device.get("oxygen_unit")
        label = unit.label if isinstance(unit, codec.EnumValue) else "ppm"
        if label == "percent_saturation":
            return round(100 * p_o2 / (OXYGEN_FRACTION * pressure), 3)
        if label == "percent_volume":
            return round(100 * p_o2 / pressure, 3)
        if label == "mbar":
            return round(p_o2, 3)
        air_saturated = OXYGEN_FRACTION * STANDARD_PRESSURE_HPA
        return round(saturation_mg_per_l(temperature, salinity) * p_o2 / air_saturated, 3)

    def filter_write(self, _device: SimulatedDevice, points: list[Point]) -> list[Point]:
        return points

    def on_write(self, device: SimulatedDevice, points: list[Point], now: float) -> None:
        names = {p.name for p in points}
        if names & {"clock", "clock_year"}:
            written = device.get("clock")
            if isinstance(written, datetime):
                self.clock_offset_s = (written - self.common.wall(now)).total_seconds()
        device.put("oxygen", self.oxygen(device))


@dataclass(slots=True)
class H10Behaviour:
    """JUMO digiLine O-DO H10/H20: measurement cycle, triggers, calibration logbook."""

    common: _Digiline
    measuring_until: float | None = None
    next_measurement: float = 0.0
    aging: AgingSettings | None = None
    # How long a triggered single measurement runs (bit 1 set): a test that polls the
    # line meanwhile lengthens it, so that a poll before the status read cannot hide it.
    single_measurement_s: float = SINGLE_MEASUREMENT_S

    def start(self, device: SimulatedDevice, now: float) -> None:
        self.common.nameplate(device, now)
        trace = self.common.sub_type == 1
        device.put("oxygen_unit", "ppb" if trace else "ppm")
        device.put("compensation_temperature", 20.0)
        device.put("compensation_pressure", STANDARD_PRESSURE_HPA)
        device.put("default_compensation_pressure", STANDARD_PRESSURE_HPA)
        device.put("measurement_interval", 1.0)
        device.put("measurement_max_temperature", 100.0)
        device.put("measurement_counter_control", "active")
        device.put("measurement_counter_max", 1_000_000)
        device.put("operating_temperature_min", -50.0)
        device.put("operating_temperature_max", 130.0)
        device.put("oxygen_temperature_min", -40.0)
        device.put("oxygen_temperature_max", 60.0)
        device.put("pressure", STANDARD_PRESSURE_HPA)
        device.put("measurement_status", {"continuous_measurement": True})
        device.put("cap_serial_number", f"CAP{device.address:06d}")
        device.put("cap_part_number", "00123456")
        if self.aging is not None:
            self.common.operating_base_s = ages.operating_seconds(self.aging)
        self.measure(device, now)
        if self.aging is not None:  # after the first measurement: its counter as configured
            aged = ages.h10_values(self.aging, now=self.common.started_wall, profile=device.profile)
            apply_aged(device, aged)
            self.common.operating_seconds(device, now)

    def measure(self, device: SimulatedDevice, now: float) -> None:
        """One oxygen and temperature measurement, as after the interval or a trigger."""
        process = self.common.process
        noise = 0.0
        if device.animate:
            process.advance(now)
            noise = process.rng.gauss(0, 2)
        device.put("temperature", round(process.temperature_c, 3))
        device.put("raw_reference_amplitude", round(1500.0 + noise, 3))
        device.put("raw_oxygen_amplitude", round(900.0 - noise, 3))
        device.put("phase_shift", round(60.0 - 0.25 * process.saturation_pct, 3))
        device.put("oxygen", self.oxygen(device))
        if _label(device.get("measurement_counter_control")) == "active":
            device.put("measurement_counter", int(_num(device.get("measurement_counter"), 0)) + 1)
            _flag_counter_overflow(device)
        self._set_status_bit(device, "new_values", state=True)

    def oxygen(self, device: SimulatedDevice) -> float:
        process = self.common.process
        temperature = _num(device.get("temperature"), 20.0)
        label = _label(device.get("oxygen_unit"))
        ppm = saturation_mg_per_l(temperature) * process.saturation_pct / 100
        if self.common.sub_type == 1:
            ppm /= 1000  # H20 trace range: simulate a low residual oxygen
        values = {
            "percent_saturation": process.saturation_pct,
            "percent_volume": 100 * OXYGEN_FRACTION * process.saturation_pct / 100,
            "ppb": ppm * 1000,
            "ppm": ppm,
            "hpa": process.partial_pressure_hpa,
            "ppm_gas": 1e6 * OXYGEN_FRACTION * process.saturation_pct / 100,
        }
        return round(values.get(label, ppm), 4)

    @staticmethod
    def _set_status_bit(device: SimulatedDevice, name: str, *, state: bool) -> None:
        if "status" in device.held:
            return
        status = device.get("status")
        bits = dict(status.flags) if isinstance(status, codec.BitfieldValue) else {}
        bits[name] = state
        device.put("status", bits)

    def _set_measuring(self, device: SimulatedDevice, *, measuring: bool) -> None:
        interval = _num(device.get("measurement_interval"), 1.0)
        device.put(
            "measurement_status",
            {"continuous_measurement": interval != 0, "measuring": measuring},
        )

    def tick(self, device: SimulatedDevice, now: float) -> None:
        self.common.operating_seconds(device, now)
        if self.measuring_until is not None and now >= self.measuring_until:
            self.measuring_until = None
            self.measure(device, now)
            self._set_measuring(device, measuring=False)
        interval = _num(device.get("measurement_interval"), 1.0)
        if interval > 0 and now >= self.next_measurement:
            self.next_measurement = now + interval
            self.measure(device, now)

    def filter_write(self, _device: SimulatedDevice, points: list[Point]) -> list[Point]:
        # 6.2.2: 0x2017, 0x2019 and 0x201F do not change when part of a multi-register
        # write that spans several values.
        if len(points) <= 1:
            return points
        ignored = {0x2017, 0x2019, 0x201F}
        return [p for p in points if p.address not in ignored]

    def on_write(self, device: SimulatedDevice, points: list[Point], now: float) -> None:
        names = {p.name for p in points}
        if "measurement_status" in names:
            status = device.get("measurement_status")
            if (
                isinstance(status, codec.BitfieldValue)
                and "single_measurement_trigger" in status.active
            ):
                self.measuring_until = now + self.single_measurement_s
                self._set_status_bit(device, "new_values", state=False)
            self._set_measuring(device, measuring=self.measuring_until is not None)
        if "measurement_interval" in names:
            self._set_measuring(device, measuring=self.measuring_until is not None)
            self.next_measurement = now
        if (
            "measurement_counter_control" in names
            and _label(device.get("measurement_counter_control")) == "reset"
        ):
            device.put("measurement_counter", 0)
            device.put("measurement_counter_control", "active")
            _flag_counter_overflow(device)
        if "zero_point_calibration_trigger" in names:
            self._calibrate(device, now, end_value=False)
        if "end_value_calibration_trigger" in names:
            self._calibrate(device, now, end_value=True)
        if "oxygen_unit" in names:
            device.put("oxygen", self.oxygen(device))

    def _calibrate(self, device: SimulatedDevice, now: float, *, end_value: bool) -> None:
        """6.2.4: take the last measured values into the calibration registers, log it."""
        phase = _num(device.get("phase_shift"), 0.0)
        temperature = _num(device.get("temperature"), 20.0)
        mode = float(_code(device.get("calibration_mode")))
        if end_value:
            pressure = _num(device.get("pressure"), STANDARD_PRESSURE_HPA)
            device.put("end_value_phase", phase)
            device.put("end_value_temperature", temperature)
            device.put("end_value_pressure", pressure)
            oxygen = _num(device.get("end_value_oxygen"), 0.0)
            unit = device.profile.point("end_value_oxygen_unit")
            unit_text = unit.enum_units.get(_code(device.get("end_value_oxygen_unit")), "")
            values = (phase, temperature, mode, oxygen, pressure, 0.0)
            units = ("°", "°C", "", unit_text, "mbar", "")
        else:
            device.put("zero_point_phase", phase)
            device.put("zero_point_temperature", temperature)
            values = (phase, temperature, mode, 0.0, 0.0, 0.0)
            units = ("°", "°C", "", "", "", "")
        device.put("calibration_mode", "as_configured")  # 6.2.4: reset after 3003/3005
        device.put("sip_cycles_since_calibration", 0)
        device.put("cip_cycles_since_calibration", 0)
        self._log(device, now, entry_type=21 if end_value else 20, values=values, units=units)

    def _log(
        self,
        device: SimulatedDevice,
        now: float,
        *,
        entry_type: int,
        values: tuple[float, float, float, float, float, float],
        units: tuple[str, str, str, str, str, str],
    ) -> None:
        """Newest entry first; older ones move down and the tenth is dropped.

        The manual documents ten entries but not their order; newest-first matches the
        tecLine/Reiss history and lets a master read the latest entry at a fixed address.
        """
        entries = [p for p in device.profile.points if p.repeat == "logbook"]
        count = max(p.index or 0 for p in entries)
        for index in range(count, 1, -1):
            for point in (p for p in entries if p.index == index):
                source = point.name.replace(f"logbook_{index}_", f"logbook_{index - 1}_", 1)
                _copy(device, source, point.name)
        date = device.get("calibration_date")
        if not isinstance(date, datetime):
            date = self.common.wall(now).replace(microsecond=0)
        entry = ages.LogbookEntry(
            entry_type=entry_type,
            date=date,
            operating_seconds=int(_num(device.get("operating_seconds"), 0)),
            sensor_replacement_counter=min(
                255, int(_num(device.get("sensor_replacement_counter"), 0))
            ),
            rating="ok",
            values=values,
            units=units,
        )
        for name, value in ages.entry_values(1, entry).items():
            device.put(name, value)


@dataclass(slots=True)
class AmperometricBehaviour:
    """JUMO tecLine and Reiss M0c/M3c: concentration = (cell current - X_Zero) / X_Span."""

    process: _Process
    nominal_slope: float
    true_concentration: float = 0.5
    aging: AgingSettings | None = None
    clock: WallClock = _utc_now
    started_wall: datetime = field(default_factory=_utc_now)
    aged_since: datetime | None = None  # the first calibration, from which the slope falls

    def start(self, device: SimulatedDevice, now: float) -> None:
        self.process.started = now
        self.started_wall = self.clock().astimezone(UTC)
        profile = device.profile
        device.put("hardware_version", 1130)
        device.put("firmware_version", 1503)
        device.put("nominal_slope", self.nominal_slope)
        device.put("serial_number", f"0104714601{device.address:09d}")
        device.put("part_number", "00705172")
        if profile.has_point("sensor_type"):
            device.put("sensor_type", "CP4.0N-M0" if profile.id.endswith("m0c") else "CP4.0N-M3")
        device.put("unit", "ppm")
        device.put("decimal_places", 2)
        device.put("measuring_range", 20.0)
        device.put("x_zero", 0.0)
        device.put("x_span", self.nominal_slope)
        # modbus_address, baud_rate and parity_stop_bits: the device reports its line.
        if self.aging is not None:
            wall = self.started_wall
            self.aged_since = ages.first_calibration(self.aging, wall)
            aged = ages.amperometric_values(
                self.aging, now=wall, profile=profile, nominal_slope=self.nominal_slope
            )
            apply_aged(device, aged)
        self.tick(device, now)

    def slope_fraction(self, now: float) -> float:
        """The cell's real slope as a fraction of nominal: falling at real time when aged."""
        if self.aging is None or self.aged_since is None:
            return IN_SERVICE_SLOPE
        wall = self.started_wall + timedelta(seconds=now - self.process.started)
        return ages.real_slope_fraction(self.aging, first=self.aged_since, at=wall)

    def tick(self, device: SimulatedDevice, now: float) -> None:
        concentration = self.true_concentration
        if device.animate:
            self.process.advance(now)
            t = now - self.process.started
            concentration += 0.05 * math.sin(2 * math.pi * t / 180) + self.process.rng.gauss(
                0, 0.001
            )
        # The cell's real slope is below nominal, as on a sensor in service.
        slope = self.slope_fraction(now)
        device.put("cell_current", round(concentration * self.nominal_slope * slope, 4))
        device.put("temperature", round(self.process.temperature_c, 3))
        current = _num(device.get("cell_current"), 0.0)
        zero = _num(device.get("x_zero"), 0.0)
        span = _num(device.get("x_span"), self.nominal_slope) or self.nominal_slope
        device.put("concentration", round((current - zero) / span, 5))

    def filter_write(self, _device: SimulatedDevice, points: list[Point]) -> list[Point]:
        return points

    def on_write(self, device: SimulatedDevice, points: list[Point], now: float) -> None:
        if any(p.name == "calibration_stamp" for p in points):
            self._activate(device)
        self.tick(device, now)

    @staticmethod
    def _activate(device: SimulatedDevice) -> None:
        """Activate a calibration: tecLine annex 7.2 / Reiss 5.1, on writing the date stamp.

        A later stamp than history entry 0 pushes the history down by one and drops the
        oldest; an equal or earlier stamp overwrites entry 0 only.
        """
        if _u32(device, "calibration_stamp") > _u32(device, "history_0_stamp"):
            for index in range(4, 0, -1):
                for part in ("x_zero", "x_span", "stamp"):
                    _copy(device, f"history_{index - 1}_{part}", f"history_{index}_{part}")
        for part, source in (
            ("x_zero", "x_zero"),
            ("x_span", "x_span"),
            ("stamp", "calibration_stamp"),
        ):
            _copy(device, source, f"history_0_{part}")


def apply_aged(device: SimulatedDevice, aged: Aged) -> None:
    """Put an aged sensor's values, and merge its bits into the bit fields' current words."""
    for name, value in aged.values.items():
        device.put(name, value)
    for name, bits in aged.flags.items():
        point = device.profile.point(name)
        current = device.get(name)
        raw = current.raw if isinstance(current, codec.BitfieldValue) else 0
        changes: dict[object, object] = dict(bits.items())
        device.put(name, encoding.with_bits(point.format, raw, changes))


def _flag_counter_overflow(device: SimulatedDevice) -> None:
    """H10/H20 6.2.9: reaching the maximum 0x2095 sets error register bit 7 (and below, not)."""
    current = device.get("error_register")
    if not isinstance(current, codec.BitfieldValue):
        return
    counter = int(_num(device.get("measurement_counter"), 0))
    overflow = ages.counter_overflows(counter, int(_num(device.get("measurement_counter_max"), 0)))
    if dict(current.flags).get("measurement_counter_overflow") != overflow:
        point = device.profile.point("error_register")
        bits: dict[object, object] = {"measurement_counter_overflow": overflow}
        device.put("error_register", encoding.with_bits(point.format, current.raw, bits))


def _raw(device: SimulatedDevice, name: str) -> tuple[int, ...]:
    point = device.profile.point(name)
    return tuple(device.registers[a] for a in range(point.address, point.last + 1))


def _u32(device: SimulatedDevice, name: str) -> int:
    high, low = _raw(device, name)
    return high << 16 | low


def _copy(device: SimulatedDevice, source: str, target: str) -> None:
    point = device.profile.point(target)
    for offset, value in enumerate(_raw(device, source)):
        device.registers[point.address + offset] = value


def _num(value: codec.Decoded, default: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return default
    return float(value)


def _label(value: codec.Decoded) -> str:
    return value.label if isinstance(value, codec.EnumValue) else str(value)


def _code(value: codec.Decoded) -> int:
    return value.code if isinstance(value, codec.EnumValue) else int(_num(value, 0))


_NOMINAL_SLOPES = {"cl2": 22.0, "tc": 7.5, "cl2-om": 22.0}  # tecLine annex 7.5 examples


def behaviour_for(
    profile_id: str,
    family: str,
    *,
    seed: int,
    aging: AgingSettings | None = None,
    clock: WallClock | None = None,
) -> Behaviour:
    """The behaviour of a profile's family, seeded for repeatable runs.

    ``aging`` lays out the records of a sensor in service at start; ``clock`` is the
    simulator's wall clock (an aware ``datetime``), read once at start.
    """
    process = _Process(rng=random.Random(seed))
    clock = clock or _utc_now
    if family == "jumo-digiline-odo-s10":
        s10 = _Digiline(
            process=process, device_name="ODO S10", sensor_type=4, sub_type=0, clock=clock
        )
        return S10Behaviour(common=s10, aging=aging)
    if family == "jumo-digiline-odo-h10-h20":
        h20 = profile_id.endswith("h20")
        name = "ODO H20" if h20 else "ODO H10"
        common = _Digiline(
            process=process, device_name=name, sensor_type=3, sub_type=int(h20), clock=clock
        )
        return H10Behaviour(common=common, aging=aging)
    variant = profile_id.removeprefix("jumo-tecline-").removeprefix("reiss-")
    return AmperometricBehaviour(
        process=process,
        nominal_slope=_NOMINAL_SLOPES.get(variant, 10.0),
        aging=aging,
        clock=clock,
    )
