"""What each sensor family needs, from its manual, and the settings that override it.

Each default carries its source; where a manual is silent the comment says the number is
ours. The config (``care:`` at the top, per profile or family, per device) overrides any of
them (:func:`resolve`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from enum import StrEnum
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from gateway.config import DeviceConfig, GatewayConfig
    from gateway.config.care import CareSettings
    from gateway.profiles import Profile, Ring, Slope


class CareKind(StrEnum):
    """Which records a family keeps, so which rules apply."""

    AMPEROMETRIC = "amperometric"  # tecLine, Reiss: active calibration, history of 5
    OPTICAL_HYGIENIC = "optical_hygienic"  # O-DO H10/H20: logbook of 10, counters, cap
    OPTICAL = "optical"  # O-DO S10: operating time and cap status bits only


# The ring each kind of records includes; its entries and fields are the profile's
# (``Profile.ring``, from its ``repeats``), as is the kind (``care:`` in its data).
HISTORY: Final = "history"  # tecLine annex 7.2 / Reiss 5.1
LOGBOOK: Final = "logbook"  # H10/H20 6.1.6
RING_OF: Final[Mapping[CareKind, str]] = {
    CareKind.AMPEROMETRIC: HISTORY,
    CareKind.OPTICAL_HYGIENIC: LOGBOOK,
}

# The guided calibration care asks for, by the records a family keeps (the procedure ids of
# the calibration catalogue, which every front end offers). Amperometric cells: the slope
# against a reference sample (tecLine annex 7.3.4, the weekly check). O-DO H10/H20: the end
# value in the reference medium; the zero point in an oxygen-free medium is the rarer one.
# The S10 offers no guided calibration over Modbus.
CALIBRATION_PROCEDURE: Final[Mapping[CareKind, str]] = {
    CareKind.AMPEROMETRIC: "slope",
    CareKind.OPTICAL_HYGIENIC: "oxygen_end_value",
}


@dataclass(frozen=True, slots=True, kw_only=True)
class CareRules:
    """The rules in force for one device, every value decided."""

    kind: CareKind
    calibration_interval_days: float | None  # None: no calibration record to time it from
    interval_source: str
    due_soon_days: float
    slope_limit: float | None  # the profile's (Profile.slope) unless set; None: no slope judged
    min_fit_r2: float
    projection_warn_days: float
    cap_usage_warn: float
    cip_cycles_limit: int | None = None
    sip_cycles_limit: int | None = None
    hours_outside_temperature_limit: float | None = None
    ring: Ring | None = None  # the sensor's ring of past calibrations, as its profile has it
    slope: Slope | None = None  # an amperometric cell's slope facts, from its profile


def _defaults(
    kind: CareKind, interval_days: float | None, source: str, *, due_soon_days: float
) -> CareRules:
    """A family's rules: its interval, and the limits every family shares."""
    return CareRules(
        kind=kind,
        calibration_interval_days=interval_days,
        interval_source=source,
        due_soon_days=due_soon_days,
        slope_limit=None,  # the profile's, by resolve()
        # Ours: SENCOM-style fits are trusted from about r² 0.8; below it the points
        # scatter more than they trend, and a date would be made up.
        min_fit_r2=0.8,
        # Ours: two weeks is enough to order a membrane cap and electrolyte.
        projection_warn_days=14.0,
        # Ours: a new H10/H20 cap is due soon at 90 % of the measurement counter's maximum
        # (6.2.9: at 100 % the sensor sets "counter overflow", error bit 7 of 0x2005).
        cap_usage_warn=0.9,
    )


DEFAULTS: Final[Mapping[CareKind, CareRules]] = {
    CareKind.AMPEROMETRIC: _defaults(
        CareKind.AMPEROMETRIC,
        7.0,
        "tecLine manual annex 7.3.4: check the calibration ideally weekly",
        due_soon_days=1.0,  # ours: a weekly check reported a day ahead
    ),
    CareKind.OPTICAL_HYGIENIC: _defaults(
        CareKind.OPTICAL_HYGIENIC,
        30.0,
        "gateway default: the H10/H20 manual gives no calibration interval",
        due_soon_days=7.0,  # ours
    ),
    CareKind.OPTICAL: _defaults(
        CareKind.OPTICAL,
        None,
        "the S10 keeps no calibration record that Modbus can read",
        due_soon_days=7.0,
    ),
}

_SETTABLE: Final = (
    "calibration_interval_days",
    "due_soon_days",
    "slope_limit",
    "min_fit_r2",
    "projection_warn_days",
    "cap_usage_warn",
    "cip_cycles_limit",
    "sip_cycles_limit",
    "hours_outside_temperature_limit",
)
assert set(_SETTABLE) <= {f.name for f in fields(CareRules)}  # noqa: S101 - a typo guard


def care_kind(profile: Profile) -> CareKind | None:
    """The records a profile's family keeps, as its data says; None: none care knows of."""
    return None if profile.care is None else CareKind(profile.care)


def care_ring(profile: Profile, kind: CareKind) -> Ring | None:
    """The ring of ``profile`` that care reads for ``kind`` (None: the S10 keeps none)."""
    name = RING_OF.get(kind)
    return None if name is None else profile.ring(name)


def resolve(
    profile: Profile, layers: Sequence[tuple[str, CareSettings | None]]
) -> CareRules | None:
    """The rules of a device: the family's defaults, then each layer that sets a key.

    ``layers`` go from the widest (the top-level ``care:``) to the narrowest (the
    device's own), each named for ``interval_source``. None: care is off for it (an
    ``enabled: false`` that no narrower layer turns on again), or its family has no rules.
    """
    kind = care_kind(profile)
    if kind is None:
        return None
    slope = profile.slope
    rules = replace(
        DEFAULTS[kind],
        ring=care_ring(profile, kind),
        slope=slope,
        slope_limit=None if slope is None else slope.limit,
    )
    enabled = True
    for name, settings in layers:
        if settings is None:
            continue
        if settings.enabled is not None:
            enabled = settings.enabled
        changes = {key: value for key in _SETTABLE if (value := getattr(settings, key)) is not None}
        if "calibration_interval_days" in changes:
            changes["interval_source"] = f"configured: {name}"
        rules = replace(rules, **changes)
    return rules if enabled else None


def rules_for(config: GatewayConfig, device: DeviceConfig) -> CareRules | None:
    """The rules of a configured device: top-level ``care:``, its family, profile, its own."""
    profile = device.get_profile()
    by_profile = config.care.profiles
    return resolve(
        profile,
        [
            ("care", config.care),
            (f"care.profiles.{profile.family}", by_profile.get(profile.family)),
            (f"care.profiles.{profile.id}", by_profile.get(profile.id)),
            (f"devices.{device.name}.care", device.care),
        ],
    )
