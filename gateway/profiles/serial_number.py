"""Which sensor is which: the serial number a profile reads, and a serial number pinned to it.

USB adapters renumber after a reboot, and two lines with the same formats and addresses
then swap their sensors without a single failed request. A device may pin the serial
number its sensor reports (``devices[].serial_number``); the line compares every serial it
reads with it (:mod:`gateway.line.engine.identity_guard`). This module is the pure part
both the config check and the line use: which point is a profile's serial number, what
a pinned value may be for that point, and when an answer matches it.

Serials come as the point's type says: a string on all four built-in families (digiLine
0x0100 char[20], tecLine and Reiss 0x030C char[20]), a whole number where a profile reads a
uint32. The config value may be text or a whole number either way, and is compared in the
form the decoded point has. Example::

    pinned = PinnedSerial.for_point(profile.point("serial_number"), "S19010593")
    pinned.matches("S19010593")  # True
    PinnedSerial.for_point(point, 12345678).matches("12345678")  # True: the same digits
"""

from __future__ import annotations

import string
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.errors import ConfigError
from gateway.wire import codec
from gateway.wire.codec import DataType

if TYPE_CHECKING:
    from gateway.profiles.model import Point, Profile

# The point every profile names its sensor's serial number by (digiLine 0x0100, tecLine and
# Reiss 0x030C): one name across families, as MQTT and the metrics already use it.
SERIAL_NUMBER_POINT: Final = "serial_number"
EMPTY_SERIAL: Final = (
    "an empty serial number pins nothing: give the serial number, or leave the key out"
)

_TEXT_TYPES: Final = frozenset({DataType.STRING})
_WHOLE_TYPES: Final = frozenset(
    {
        DataType.UINT8,
        DataType.INT8,
        DataType.UINT16,
        DataType.INT16,
        DataType.UINT32,
        DataType.INT32,
    }
)
_OCTAL_DIGITS: Final = frozenset(string.octdigits)


def serial_point(profile: Profile) -> Point | None:
    """The profile's serial-number point, or ``None`` if it reads none."""
    if not profile.has_point(SERIAL_NUMBER_POINT):
        return None
    return profile.point(SERIAL_NUMBER_POINT)


def _digits(text: str) -> bool:
    return text.isascii() and text.isdigit()


def _readings(digits: str) -> set[int]:
    """The numbers YAML may have made of these digits unquoted: decimal, or octal after a 0."""
    readings = {int(digits)}
    if digits.startswith("0") and set(digits) <= _OCTAL_DIGITS:
        readings.add(int(digits, 8))
    return readings


@dataclass(frozen=True, slots=True)
class PinnedSerial:
    """The serial number a device must report, as configured, for one serial-number point.

    Build it with :meth:`for_point`, which refuses a value the point can never report.
    """

    configured: str | int
    numeric_point: bool  # the point decodes to a whole number, not to text

    @classmethod
    def for_point(cls, point: Point, configured: str | int) -> PinnedSerial:
        """The pinned value for ``point``, or a :class:`ValueError` that says why not.

        Text stays text (surrounding spaces dropped); a whole number pinned to a string
        point is compared by its decimal digits; text pinned to a number point must be one.
        """
        dtype = point.format.dtype
        if isinstance(configured, str):
            configured = configured.strip()
            if not configured:
                raise ValueError(EMPTY_SERIAL)
        if dtype in _WHOLE_TYPES:
            if isinstance(configured, str) and not _digits(configured):
                raise ValueError(
                    f"{configured!r} is not a whole number, and {point.name} is a {dtype} "
                    "the sensor reports as a number"
                )
            return cls(configured=int(configured), numeric_point=True)
        if dtype not in _TEXT_TYPES:
            raise ValueError(f"{point.name} is a {dtype}, which cannot hold a serial number")
        return cls(configured=configured, numeric_point=False)

    def matches(self, answered: codec.Decoded) -> bool:
        """Whether a decoded serial number is the pinned one.

        Text is compared exactly, surrounding spaces (padding) aside. A whole number pinned
        to a string point matches the same digits, leading zeros included: YAML reads an
        unquoted ``serial_number: 0104714601000000201`` as an octal number, and that
        reading is undone here rather than turned into a mismatch nobody can explain.
        """
        if isinstance(answered, bool):
            return False
        if isinstance(answered, int):
            return self.numeric_point and answered == self.configured
        if not isinstance(answered, str):
            return False  # nothing read, a fault, or a value of another type
        text = answered.strip()
        if isinstance(self.configured, str):
            return text == self.configured
        return _digits(text) and self.configured in _readings(text)

    def __str__(self) -> str:
        """The pinned serial number as the config gives it."""
        return str(self.configured)


def pinned_serial(profile: Profile, configured: str | int | None) -> PinnedSerial | None:
    """The serial number a device of ``profile`` must report; ``None`` when none is pinned.

    The config check refuses every value this refuses; a :class:`ConfigError` here means
    a config that skipped that check.
    """
    if configured is None:
        return None
    point = serial_point(profile)
    if point is None:
        message = f"profile {profile.id} has no {SERIAL_NUMBER_POINT} point"
        raise ConfigError(message, key="serial_number")
    try:
        return PinnedSerial.for_point(point, configured)
    except ValueError as exc:
        raise ConfigError(str(exc), key="serial_number") from exc


def answered_text(answered: codec.Decoded) -> str:
    """A serial number that was read, for logs and ``/healthz``: text stripped, faults named."""
    if isinstance(answered, codec.Fault):
        shown = " ".join(f"0x{word:04X}" for word in answered.registers)
        return f"undecodable ({shown})" if shown else answered.name
    if answered is None:
        return "nothing"
    return str(answered).strip()
