"""``calibrations``: the guided calibrations a device offers, from the calibration catalogue.

The same documents as ``gateway calibrate procedures --profile ID --json`` and the web
page's device view (:mod:`gateway.control.calibration.catalogue`): each procedure's id, the
command that runs it, what it is for, its inputs with their defaults and sources.

MQTT lists the calibrations; it does not start them. Every guided calibration shows the
operator what it read and computed and the registers it is about to write, and waits for
their yes before writing; the manuals' procedures need someone at the sensor (a sample
taken and analysed while the current is noted, a medium without disinfectant or oxygen, a
reading watched until it is stable). An MQTT command is one message and one result, run
within the command timeout, with nobody to answer that question. They are started from
``gateway calibrate`` or the web page; a plant system that writes calibration registers
itself does so with ``…/set`` under the flash guard.

The catalogue is imported here when the operation runs, not with the MQTT command router:
a gateway without its web page does not hold the calibration flows in memory
(``tests/cli/test_imports.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.control.operations.catalogue import CALIBRATIONS, require_operation

if TYPE_CHECKING:
    from gateway.profiles import Profile

NOT_OVER_MQTT: Final = (
    "MQTT lists the guided calibrations but does not start them: each asks the operator "
    "at the sensor to confirm its writes. Start them with 'gateway calibrate COMMAND' or "
    "on the web page."
)


@dataclass(frozen=True, slots=True)
class CalibrationOffer:
    """The procedures a device offers, as the catalogue describes them."""

    procedures: tuple[dict[str, object], ...]

    def as_dict(self) -> dict[str, object]:
        """JSON-ready: the MQTT result."""
        return {"procedures": list(self.procedures), "note": NOT_OVER_MQTT}


def calibrations(profile: Profile) -> CalibrationOffer:
    """The guided calibrations a device of ``profile`` offers; refused if it offers none."""
    from gateway.control.calibration import catalogue  # noqa: PLC0415 - see the docstring

    require_operation(CALIBRATIONS, profile)
    return CalibrationOffer(tuple(p.as_dict() for p in catalogue.offered(profile)))
