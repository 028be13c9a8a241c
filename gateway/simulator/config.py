"""What to simulate: devices on one line, from the command line or a YAML file."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from gateway.errors import ConfigError, GatewayError
from gateway.profiles import get_profile
from gateway.simulator.aging import AgingSettings  # noqa: TC001 - pydantic resolves it at run time
from gateway.simulator.behaviour import behaviour_for
from gateway.simulator.bus import FaultPlan, SimulatedBus
from gateway.simulator.device import SimulatedDevice
from gateway.wire.codec import Fault
from gateway.wire.timing import LineFormat

if TYPE_CHECKING:
    from collections.abc import Callable
    from datetime import datetime
    from pathlib import Path


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class FaultSettings(_Model):
    """Fault injection for one device; rates are probabilities per answer."""

    crc: Annotated[float, Field(ge=0, le=1)] = 0.0
    drop: Annotated[float, Field(ge=0, le=1)] = 0.0
    late: Annotated[float, Field(ge=0, le=1)] = 0.0
    late_s: Annotated[float, Field(gt=0)] = 0.5
    noise: Annotated[float, Field(ge=0, le=1)] = 0.0
    wrong_address: Annotated[float, Field(ge=0, le=1)] = 0.0
    string_byte_count_16bit: bool = False
    silences: list[tuple[float, float]] = []


class DeviceSettings(_Model):
    """One simulated sensor."""

    profile: str
    address: Annotated[int, Field(ge=1, le=247)]
    animate: bool = True
    processing_ms: Annotated[float, Field(ge=0, le=1000)] = 5.0
    values: dict[str, Any] = {}
    faults: FaultSettings = FaultSettings()
    unmapped: list[Annotated[int, Field(ge=0, le=0xFFFF)]] = []  # answer 02 for these
    # Raw words by register address, held from start: what no encoder writes (an S10 clock
    # with month 13), or registers the manual does not document that a real unit answers
    # anyway (a tecLine that reads 0 at the digiLine sensor type 0x010A).
    registers: dict[
        Annotated[int, Field(ge=0, le=0xFFFF)], Annotated[int, Field(ge=0, le=0xFFFF)]
    ] = {}
    # A sensor with a past: its records laid out as after this time in service (aging.py).
    aging: AgingSettings | None = None


class LineSettings(_Model):
    """The line's format."""

    baudrate: Annotated[int, Field(gt=0)] = 9600
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1


class SimulationSettings(_Model):
    """A simulated bus: its line and its devices (each address once)."""

    line: LineSettings = LineSettings()
    pace: bool = False
    seed: int = 0
    devices: list[DeviceSettings]

    @model_validator(mode="after")
    def _unique_addresses(self) -> SimulationSettings:
        seen: dict[int, int] = {}
        for index, device in enumerate(self.devices):
            if device.address in seen:
                raise ValueError(
                    f"devices.{index}.address: address {device.address} is already used by "
                    f"devices.{seen[device.address]}"
                )
            seen[device.address] = index
        return self


def load_settings(path: Path) -> SimulationSettings:
    """Read a simulator YAML file; errors name the key."""
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read {path}: {exc}") from exc
    return parse_settings(data, source=str(path))


def parse_settings(data: object, *, source: str = "simulator settings") -> SimulationSettings:
    """Validate simulator settings from plain data."""
    try:
        return SimulationSettings.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in err['loc'])}: {err['msg']}" if err["loc"] else err["msg"]
            for err in exc.errors()
        )
        raise ConfigError(f"{source}: {problems}") from exc


def parse_device_option(text: str) -> DeviceSettings:
    """``PROFILE:ADDRESS`` from the command line."""
    profile, sep, address = text.rpartition(":")
    if not sep or not address.isdigit():
        raise ConfigError(f"--device {text!r}: expected PROFILE:ADDRESS, e.g. reiss-m0c:10")
    try:
        return DeviceSettings(profile=profile, address=int(address))
    except ValidationError as exc:
        raise ConfigError(f"--device {text!r}: the address must be 1..247") from exc


def _value(raw: object) -> object:
    if isinstance(raw, dict) and set(raw) == {"fault"}:
        return Fault(name=str(raw["fault"]), raw=0.0)
    return raw


def build_bus(
    settings: SimulationSettings, *, clock: Callable[[], datetime] | None = None
) -> SimulatedBus:
    """Devices with their behaviours and fault plans, checked against their profiles.

    ``clock`` is the simulator's wall clock (an aware ``datetime``; default: now), from which
    an aged device dates its records at start: tests pass a fixed one.
    """
    devices: dict[int, SimulatedDevice] = {}
    faults: dict[int, FaultPlan] = {}
    for index, entry in enumerate(settings.devices):
        try:
            profile = get_profile(entry.profile)
            for name in entry.values:
                profile.point(name)
        except GatewayError as exc:
            raise ConfigError(str(exc), key=f"devices.{index}") from exc
        device = SimulatedDevice(
            profile=profile,
            address=entry.address,
            behaviour=behaviour_for(
                profile.id,
                profile.family,
                seed=settings.seed + entry.address,
                aging=entry.aging,
                clock=clock,
            ),
            processing_s=entry.processing_ms / 1000,
            animate=entry.animate,
            initial={name: _value(value) for name, value in entry.values.items()},
            unmapped=set(entry.unmapped),
            raw=dict(entry.registers),
        )
        devices[entry.address] = device
        faults[entry.address] = FaultPlan(**entry.faults.model_dump())
    line = LineFormat(
        baudrate=settings.line.baudrate,
        parity=settings.line.parity,
        stopbits=settings.line.stopbits,
    )
    return SimulatedBus(
        line=line, devices=devices, faults=faults, pace=settings.pace, seed=settings.seed
    )
