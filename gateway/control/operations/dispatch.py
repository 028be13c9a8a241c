"""One operation run by name, as the MQTT ``{base}/{device}/command/{name}`` handler does."""

from __future__ import annotations

from typing import TYPE_CHECKING

from gateway.control.operations.calibrations import CalibrationOffer, calibrations
from gateway.control.operations.catalogue import (
    CALIBRATIONS,
    MEASURE,
    MEASURE_TIMEOUT_S,
    SET_CLOCK,
    parse_arguments,
    require_operation,
)
from gateway.control.operations.clock import ClockSetting, set_clock
from gateway.control.operations.logbook import CalibrationLog, calibration_log
from gateway.control.operations.measurement import Measurement, measure

if TYPE_CHECKING:
    from collections.abc import Mapping
    from datetime import datetime

    from gateway.control.writes import SafeWriter


async def run_operation(
    name: str, writer: SafeWriter, arguments: Mapping[str, object], *, now: datetime
) -> dict[str, object]:
    """Run one operation by name on ``writer``'s device; its result as JSON-ready data.

    ``now`` is the gateway's clock (time-zone aware), used by ``set_clock``. An unknown
    name, an operation the device's profile does not support, or bad arguments raise
    :class:`CommandRejectedError` before anything is sent.
    """
    require_operation(name, writer.link.profile)
    parsed = parse_arguments(name, arguments)
    result: ClockSetting | Measurement | CalibrationLog | CalibrationOffer
    if name == SET_CLOCK:
        result = await set_clock(writer, now=now, local=parsed.get("local") is True)
    elif name == MEASURE:
        timeout = parsed.get("timeout", MEASURE_TIMEOUT_S)
        assert isinstance(timeout, float)  # noqa: S101 - measure_timeout returns a float
        result = await measure(writer, timeout_s=timeout)
    elif name == CALIBRATIONS:
        result = calibrations(writer.link.profile)
    else:
        result = await calibration_log(writer.link)
    return {"operation": name, "device": writer.device, **result.as_dict()}
