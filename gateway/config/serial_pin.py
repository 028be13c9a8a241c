"""The check of a pinned serial number (``devices[].serial_number``) against the device's profile.

A pin the line can never confirm would keep the device unpublished for ever, so it is a
config error at load: a profile that reads no serial number, the serial-number point
switched off under ``points:``, or a value the point cannot report (text for a number).
The value's own type (no floats, no booleans) is the model's to refuse.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from gateway.profiles.serial_number import SERIAL_NUMBER_POINT, PinnedSerial, serial_point

if TYPE_CHECKING:
    from collections.abc import Iterator, Mapping

    from gateway.config.problems import KeyPath
    from gateway.profiles import Profile


def check_serial_number(
    here: KeyPath, profile: Profile | None, device: Mapping[str, object]
) -> Iterator[tuple[KeyPath, str]]:
    """Problems of the serial number pinned in one device entry (``here``); none if unpinned."""
    value = device.get("serial_number")
    if profile is None or value is None or isinstance(value, bool):
        return  # no pin, an unknown profile or a value the model refuses: reported there
    if not isinstance(value, str | int):
        return
    if (isinstance(value, str) and not value.strip()) or (isinstance(value, int) and value < 0):
        return
    where: KeyPath = (*here, "serial_number")
    point = serial_point(profile)
    if point is None:
        yield (
            where,
            (
                f"profile {profile.id} has no {SERIAL_NUMBER_POINT} point, so the serial "
                "number cannot be checked; remove serial_number from this device"
            ),
        )
        return
    points = device.get("points")
    settings = points.get(point.name) if isinstance(points, dict) else None
    if isinstance(settings, dict) and settings.get("enabled") is False:
        yield (
            where,
            (
                f"the serial number is pinned, but points.{point.name}.enabled is false, so "
                "it is never read and the device would never be published; enable the point "
                "or remove serial_number"
            ),
        )
    try:
        PinnedSerial.for_point(point, value)
    except ValueError as exc:
        yield where, f"{exc} ({profile.id} reads it at 0x{point.address:04X})"
