"""Guided calibrations, step by step, as the sensor manuals describe them.

Two families calibrate over Modbus:

- **tecLine / Reiss** amperometric cells (tecLine annex 7, Reiss chapter 5): the master
  computes the calibration and writes it: X_Zero (0x0206, nA), X_Span (0x0208, nA per
  concentration unit), then the date stamp ``YYMMDDHHMM`` (0x020A), whose write activates
  it and moves the five-entry history (0x0210-0x022D). Procedures: slope
  (:func:`calibrate_slope`), zero point (:func:`calibrate_zero_point`), restoring the
  nominal slope (:func:`restore_nominal_slope`) and the regular check
  (:func:`check_slope`, which writes nothing).
- **digiLine O-DO H10/H20** (manual 6.2.4): the sensor calibrates itself with its last
  measured values when 0x3003 (zero point) or 0x3005 (end value) is written, after the
  calibration mode (0x3009) and date (0x300A) are set, and logs a new logbook entry.
  Procedures: :func:`calibrate_oxygen_zero`, :func:`calibrate_oxygen_end_value`.

Every flow reads what it needs and shows it, computes, shows the registers it is about to
write, asks the :class:`Operator` to confirm, writes through
:class:`gateway.control.writes.SafeWriter` (so flash writes are counted against the daily budget),
then reads back and checks the result as the manuals' "checking the calibration" sections
say. The arithmetic is in plain functions (:func:`slope_from`, :func:`judge_slope`,
:func:`calibration_stamp`, :func:`expected_history` ...) that need no I/O.

Outcomes: a :class:`CalibrationOutcome` whose status says calibrated, declined (nothing
written) or verification failed. A refusal before anything is written (bad input, the
flash budget, a wrong family) raises :class:`CommandRejectedError`; a failure part-way
through the writes raises :class:`CalibrationInterruptedError`, naming what was written.

Which procedures a device offers, their inputs and their defaults are the catalogue's
(:mod:`~gateway.control.calibration.catalogue`), which every front end reads: the command
line, the web page and MQTT's ``calibrations`` operation.

The pieces: the arithmetic in :mod:`~gateway.control.calibration.arithmetic`, the shared step
machinery in :mod:`~gateway.control.calibration.steps`, the tecLine/Reiss procedures in
:mod:`~gateway.control.calibration.amperometric`, the H10/H20 ones in
:mod:`~gateway.control.calibration.oxygen`, the catalogue in
:mod:`~gateway.control.calibration.catalogue`. Import from here (the catalogue as the
module ``catalogue``).
"""

from gateway.control.calibration import catalogue
from gateway.control.calibration.amperometric import (
    calibrate_slope,
    calibrate_zero_point,
    check_slope,
    restore_nominal_slope,
)
from gateway.control.calibration.arithmetic import (
    AMPEROMETRIC_POINTS,
    CHEMICAL_CHECK_TOLERANCE,
    OPTICAL_OXYGEN_POINTS,
    HistoryEffect,
    HistoryEntry,
    SlopeJudgement,
    calibration_stamp,
    expected_history,
    history_effect,
    judge_slope,
    nominal_in_unit,
    slope_from,
    stamp_number,
)
from gateway.control.calibration.oxygen import (
    calibrate_oxygen_end_value,
    calibrate_oxygen_zero,
    logbook_date,
)
from gateway.control.calibration.steps import (
    CalibrationOutcome,
    Check,
    Operator,
    PlannedWrite,
    Status,
    Step,
    StepKind,
)

__all__ = [
    "AMPEROMETRIC_POINTS",
    "CHEMICAL_CHECK_TOLERANCE",
    "OPTICAL_OXYGEN_POINTS",
    "CalibrationOutcome",
    "Check",
    "HistoryEffect",
    "HistoryEntry",
    "Operator",
    "PlannedWrite",
    "SlopeJudgement",
    "Status",
    "Step",
    "StepKind",
    "calibrate_oxygen_end_value",
    "calibrate_oxygen_zero",
    "calibrate_slope",
    "calibrate_zero_point",
    "calibration_stamp",
    "catalogue",
    "check_slope",
    "expected_history",
    "history_effect",
    "judge_slope",
    "logbook_date",
    "nominal_in_unit",
    "restore_nominal_slope",
    "slope_from",
    "stamp_number",
]
