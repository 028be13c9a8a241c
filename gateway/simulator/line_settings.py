"""What a simulated sensor's interface registers say of the line it answers on.

A sensor answers only on the line its interface registers are set to, so at power-up they
say the simulated line (or the format given for RTU over TCP).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.simulator.registers import RegisterImage
    from gateway.wire.timing import LineFormat

_LOGGER = logging.getLogger(__name__)

# The interface registers, by the names every profile gives them (digiLine 0x0300-0x0302,
# S10 6.4 and H10 6.1.4; tecLine and Reiss 0x0400-0x0402, "Device data Modbus"), and what
# of the line each holds. Their enum labels say the line in one form across the families
# (``baud_19200``, ``8e1``), so the line's own labels find the codes.
_ADDRESS: Final = ("device_address", "modbus_address")
_BAUD_RATE: Final = ("baud_rate",)
_FRAMING: Final = ("data_format", "parity_stop_bits")
# (profile, point, setting) already warned of: a bench of 256 sensors says it once a profile.
_WARNED: set[tuple[str, str, str]] = set()


def report_line(image: RegisterImage, address: int, line: LineFormat) -> None:
    """Put the device address and ``line`` into the interface registers the profile has.

    A held point keeps its value; a line the sensor has no code for is logged and left out.
    """
    profile = image.profile
    framing = f"8{line.parity}{line.stopbits}".lower()
    settings: Mapping[tuple[str, ...], object] = {
        _ADDRESS: address,
        _BAUD_RATE: f"baud_{line.baudrate}",
        _FRAMING: framing,
    }
    for names, value in settings.items():
        for point in (profile.point(n) for n in names if profile.has_point(n)):
            if point.format.enum and value not in point.format.enum.values():
                # A real sensor cannot be set to this line (tests run faster ones): say
                # so, once a profile, and leave the register as the behaviour set it.
                said = (profile.id, point.name, str(value))
                log = _LOGGER.debug if said in _WARNED else _LOGGER.warning
                _WARNED.add(said)
                log(
                    "%s at %d: %s has no code for %s (codes: %s)",
                    profile.id,
                    address,
                    point.name,
                    value,
                    ", ".join(point.format.enum.values()),
                )
                continue
            image.put(point.name, value)
