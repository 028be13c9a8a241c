"""Sensor care as the page shows it: every device care follows, most urgent first, without I/O.

Each document is the device's :meth:`~gateway.care.CareReport.as_dict` (the one MQTT
publishes as ``{base}/{device}/care`` and the metrics port serves at ``/care``), in
:func:`~gateway.care.care_order`, with two keys the page adds: ``kind`` and
``calibration``, the guided calibration the care state asks for where the device offers
one (``{"procedure", "title"}``, else None), as the calibration catalogue decides it
(:func:`gateway.control.calibration.catalogue.asked_by_care`). A device care follows whose
records were not all read yet has no report: it is listed as ``unknown``, "records not read
yet", after the unknown reports and before the due ones.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

from gateway.care import CareState, care_kind, care_order
from gateway.control.calibration import catalogue
from gateway.profiles import get_profile

if TYPE_CHECKING:
    from gateway.care import CareReport
    from gateway.shared.state import DeviceInfo, GatewayState

NOT_READ: Final = "records not read yet"
# What a document holds besides device, bus, profile, state and reasons: nothing known yet.
_UNREAD_FIGURES: Final = (
    "last_calibration",
    "due",
    "interval_days",
    "interval_source",
    "slope_ratio",
    "slope_limit",
    "slope_trend",
    "projection",
    "projection_note",
    "cap_usage",
    "assessed_at",
)


def calibration_offer(profile_id: str) -> dict[str, str] | None:
    """The calibration care asks for on a device of this profile, if the device offers it.

    The profile is the built-in one of that id, as every configured device's write path
    has it (``gateway.app.build_writers``), so the link leads to the calibration the page's
    own calibration flow (``#/calibrate/DEVICE/PROCEDURE``) runs for that device.
    """
    procedure = catalogue.asked_by_care(get_profile(profile_id))
    if procedure is None:
        return None
    return {"procedure": procedure.id, "title": procedure.title}


def _document(report: CareReport) -> dict[str, object]:
    return {
        **report.as_dict(),
        "kind": report.kind,
        "calibration": calibration_offer(report.profile),
    }


def _unread(info: DeviceInfo) -> dict[str, object]:
    kind = care_kind(get_profile(info.profile))
    return {
        "device": info.name,
        "bus": info.bus,
        "profile": info.profile,
        "state": CareState.UNKNOWN.value,
        "reasons": [NOT_READ],
        **dict.fromkeys(_UNREAD_FIGURES),
        "figures": {},
        "records": {},
        "kind": kind.value if kind is not None else None,
        "calibration": calibration_offer(info.profile),
    }


def care_documents(state: GatewayState) -> list[dict[str, object]]:
    """Every configured device care follows, most urgent first: what ``/api/care`` sends."""
    book = state.care
    reports: list[CareReport] = []
    unread: list[DeviceInfo] = []
    for info in list(state.devices.values()):
        if not book.tracked(info.name):
            continue  # care is off for it, or its family keeps no records care reads
        report = book.report(info.name)
        if report is None:
            unread.append(info)
        else:
            reports.append(report)
    ordered = care_order(reports)
    unknown = CareState.UNKNOWN.severity
    cut = sum(1 for report in ordered if report.state.severity >= unknown)
    return [
        *(_document(report) for report in ordered[:cut]),
        *(_unread(info) for info in sorted(unread, key=lambda i: i.name)),
        *(_document(report) for report in ordered[cut:]),
    ]


def care_version(state: GatewayState) -> int:
    """Changes whenever a device's care document does (not with its time alone).

    The live overview carries it, so the page asks ``/api/care`` again only then.
    """
    book = state.care
    return sum(book.version(info.name) for info in list(state.devices.values()))
