"""Sensor care: what each sensor needs and when, from the records it already holds.

The rules come from the manuals (:mod:`~gateway.care.rules`, each default with its
source); the records are points the gateway polls anyway (:mod:`~gateway.care.records`);
the verdict is pure (:mod:`~gateway.care.assess`, the trend and its projection in
:mod:`~gateway.care.trend`, grab-sample verifications as
:mod:`~gateway.care.verifications`) and kept current while the gateway runs by
:class:`~gateway.care.book.CareBook`. Import from here.
"""

from gateway.care.assess import assess
from gateway.care.book import CareBook
from gateway.care.records import (
    Calibration,
    LogbookEntry,
    PastEntries,
    Records,
    SensorEntry,
    care_points,
    ring_entries,
)
from gateway.care.report import (
    CARE_STATES,
    CareReport,
    CareState,
    Finding,
    Projection,
    Trend,
    care_order,
)
from gateway.care.rules import CareKind, CareRules, care_kind, resolve
from gateway.care.verifications import Verification

__all__ = [
    "CARE_STATES",
    "Calibration",
    "CareBook",
    "CareKind",
    "CareReport",
    "CareRules",
    "CareState",
    "Finding",
    "LogbookEntry",
    "PastEntries",
    "Projection",
    "Records",
    "SensorEntry",
    "Trend",
    "Verification",
    "assess",
    "care_kind",
    "care_order",
    "care_points",
    "resolve",
    "ring_entries",
]
