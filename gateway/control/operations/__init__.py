"""Operations on one sensor: its clock, a single measurement, its calibration log and offers.

Each operation is a plain function (async where it talks to the sensor) that the command
line calls directly (:func:`set_clock`, :func:`measure`, :func:`calibration_log`; the
calibrations a device offers it lists with ``gateway calibrate procedures``) and returns a
frozen value with an ``as_dict()`` of JSON-ready data. :func:`run_operation` runs one by
name, as the MQTT ``{base}/{device}/command/{name}`` handler does, after checking the name,
the device's profile and the arguments; a refusal there raises
:class:`~gateway.errors.CommandRejectedError` before anything reaches the bus.

Which operation applies is decided from the profile's data (the points it declares), not
from vendor names:

- ``set_clock``: a writable date-and-time block: the S10 clock (0x2840-0x2846, S10 manual
  6.9) or the H10/H20 calibration date (0x300A-0x3010, manual 6.2.4), which the sensor
  copies into the logbook entries that follow and which does not run;
- ``measure``: the H10/H20 measurement control word 0x3001 (bit 1 "a measurement is in
  progress", bit 2 "set to trigger a single measurement") and the status word 0x3007
  (bit 15 "new measured values"), manual 6.2.2 and 6.2.10;
- ``calibration_log``: the H10/H20 logbook of 10 entries (manual 6.1.6) or the tecLine /
  Reiss history of 5 entries with the current calibration (tecLine annex 7.2, Reiss 5.1);
- ``calibrations``: the guided calibrations the device offers, with their inputs and
  defaults, from the calibration catalogue (MQTT lists them; it does not start them, see
  :mod:`~gateway.control.operations.calibrations`).

Every write goes through :class:`~gateway.control.writes.SafeWriter` as an explicit operator action:
flash-backed points need no allow-list entry but are counted against the daily budget,
and the link keeps every timing rule (the H10/H20 250 ms post-write wait included).

The pieces: the names, which operation applies and the arguments in
:mod:`~gateway.control.operations.catalogue`; one module per operation
(:mod:`~gateway.control.operations.clock`, :mod:`~gateway.control.operations.measurement`,
:mod:`~gateway.control.operations.logbook`,
:mod:`~gateway.control.operations.calibrations`); :func:`run_operation` in
:mod:`~gateway.control.operations.dispatch`. Import from here.
"""

from gateway.control.operations.calibrations import (
    NOT_OVER_MQTT,
    CalibrationOffer,
    calibrations,
)
from gateway.control.operations.catalogue import (
    CALIBRATION_LOG,
    CALIBRATIONS,
    CLOCK_POINTS,
    LOG_LAYOUTS,
    MEASURE,
    MEASURE_TIMEOUT_MAX_S,
    MEASURE_TIMEOUT_S,
    MEASURED_POINTS,
    MEASUREMENT_STATUS,
    MEASURING_BIT,
    NEW_VALUES_BIT,
    OPERATION_NAMES,
    SET_CLOCK,
    STATUS,
    TRIGGER_BIT,
    ClockPoint,
    LogLayout,
    as_json,
    clock_point,
    log_layout,
    offers_calibrations,
    operations_for,
    parse_arguments,
    require_operation,
)
from gateway.control.operations.clock import (
    ClockSetting,
    set_clock,
)
from gateway.control.operations.dispatch import (
    run_operation,
)
from gateway.control.operations.logbook import (
    UNIT_TEXT_SUFFIX,
    CalibrationLog,
    LogEntry,
    calibration_log,
)
from gateway.control.operations.measurement import (
    MEASURE_POLL_S,
    Measurement,
    measure,
)

__all__ = [
    "CALIBRATIONS",
    "CALIBRATION_LOG",
    "CLOCK_POINTS",
    "LOG_LAYOUTS",
    "MEASURE",
    "MEASURED_POINTS",
    "MEASUREMENT_STATUS",
    "MEASURE_POLL_S",
    "MEASURE_TIMEOUT_MAX_S",
    "MEASURE_TIMEOUT_S",
    "MEASURING_BIT",
    "NEW_VALUES_BIT",
    "NOT_OVER_MQTT",
    "OPERATION_NAMES",
    "SET_CLOCK",
    "STATUS",
    "TRIGGER_BIT",
    "UNIT_TEXT_SUFFIX",
    "CalibrationLog",
    "CalibrationOffer",
    "ClockPoint",
    "ClockSetting",
    "LogEntry",
    "LogLayout",
    "Measurement",
    "as_json",
    "calibration_log",
    "calibrations",
    "clock_point",
    "log_layout",
    "measure",
    "offers_calibrations",
    "operations_for",
    "parse_arguments",
    "require_operation",
    "run_operation",
    "set_clock",
]
