"""Readable copies of the records: CSV, JSON and a printable HTML report, with the chain's verdict.

21 CFR Part 11 §11.10(b) asks for "accurate and complete copies of records in both human
readable and electronic form suitable for inspection"; EU GMP Annex 11 §8 for clear
printed copies. Every field goes out, the hashes included, and each copy ends with the
verdict of the whole chain (not only of the records selected), so a copy says whether
the store it came from was intact when it was made.

Pure: records and a verdict in, text out.
"""

from __future__ import annotations

import csv
import html
import io
import json
from collections import defaultdict
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping, Sequence

    from gateway.records.chain import Verdict
    from gateway.records.model import Record

FORMATS: Final = ("csv", "json", "html")
CSV_COLUMNS: Final = (
    "seq",
    "time",
    "clock_synchronised",
    "kind",
    "user",
    "via",
    "detail",
    "signed",
    "reason",
    "device",
    "profile",
    "serial",
    "bus",
    "address",
    "action",
    "point",
    "unit",
    "as_found",
    "sent",
    "registers",
    "as_left",
    "result",
    "note",
    "completes",
    "corrects",
    "data",
    "hash",
)


def _text(value: object) -> str:
    """A cell: text as it is, anything else as compact JSON, nothing as empty."""
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    return json.dumps(value, ensure_ascii=False, separators=(",", ":"))


def _mapping(value: object) -> Mapping[str, object]:
    return value if isinstance(value, dict) else {}


def rows(record: Record) -> list[dict[str, str]]:
    """A record as CSV rows: one per point it touched (one row if it touched none)."""
    body = record.body
    actor = _mapping(body.get("actor"))
    device = _mapping(body.get("device"))
    common = {
        "seq": str(record.seq),
        "time": _text(body.get("time")),
        "clock_synchronised": _text(body.get("clock_synchronised")),
        "kind": _text(body.get("kind")),
        "user": _text(actor.get("user")),
        "via": _text(actor.get("via")),
        "detail": _text(actor.get("detail")),
        "signed": _text(actor.get("signed")),
        "reason": _text(actor.get("reason")),
        "device": _text(device.get("name")),
        "profile": _text(device.get("profile")),
        "serial": _text(device.get("serial")),
        "bus": _text(device.get("bus")),
        "address": _text(device.get("address")),
        "action": _text(body.get("action")),
        "result": _text(body.get("result")),
        "note": _text(body.get("note")),
        "completes": _text(body.get("completes")),
        "corrects": _text(body.get("corrects")),
        "data": _text(body.get("data") or None),
        "hash": record.hash,
    }
    points = body.get("points")
    changes = [_mapping(p) for p in points] if isinstance(points, list) and points else [{}]
    out = []
    for change in changes:
        registers = change.get("registers")
        out.append(
            common
            | {
                "point": _text(change.get("point")),
                "unit": _text(change.get("unit")),
                "as_found": _text(change.get("as_found")),
                "sent": _text(change.get("sent")),
                "registers": " ".join(registers) if isinstance(registers, list) else "",
                "as_left": _text(change.get("as_left")),
            }
        )
    return out


def _verdict_line(verdict: Verdict) -> str:
    if verdict.intact:
        return (
            f"chain intact: {verdict.checked} records, head {verdict.head.seq}:{verdict.head.hash}"
        )
    return f"chain BROKEN at record {verdict.broken_at}: {verdict.problem}"


def to_csv(records: Iterable[Record], verdict: Verdict) -> str:
    """CSV with a header row; the verdict as the last line, a ``#`` comment."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for record in records:
        writer.writerows(rows(record))
    buffer.write(f"# {_verdict_line(verdict)}\n")
    return buffer.getvalue()


def to_json(records: Iterable[Record], verdict: Verdict) -> str:
    """One JSON document: the records (each with its hash) and the verdict."""
    document = {
        "records": [{**record.body, "hash": record.hash} for record in records],
        "verdict": verdict.as_dict(),
    }
    return json.dumps(document, ensure_ascii=False, indent=1) + "\n"


_STYLE: Final = """
body { font: 11pt/1.35 system-ui, sans-serif; margin: 1.5em; color: #111; }
h1 { font-size: 16pt; } h2 { font-size: 13pt; margin-top: 1.5em; }
table { border-collapse: collapse; width: 100%; margin: .5em 0 1em; font-size: 9pt; }
th, td { border: 1px solid #999; padding: 2px 4px; text-align: left; vertical-align: top; }
th { background: #eee; } .hash { font-family: monospace; font-size: 7pt; word-break: break-all; }
.broken { color: #a00; font-weight: bold; } .intact { color: #060; font-weight: bold; }
section.device { page-break-before: always; }
svg.plot { font: 9pt sans-serif; border: 1px solid #ccc; }
@media print { body { margin: 0; } }
"""
_TABLE_COLUMNS: Final = (
    ("seq", "#"),
    ("time", "UTC time"),
    ("clock_synchronised", "clock sync."),
    ("user", "who"),
    ("via", "via"),
    ("action", "what"),
    ("point", "point"),
    ("as_found", "as found"),
    ("sent", "sent"),
    ("as_left", "as left"),
    ("result", "result"),
    ("reason", "why"),
    ("note", "note"),
    ("hash", "hash"),
)


def _table(records: Sequence[Record]) -> str:
    head = "".join(f"<th>{html.escape(title)}</th>" for _key, title in _TABLE_COLUMNS)
    lines = [f"<table><thead><tr>{head}</tr></thead><tbody>"]
    for record in records:
        for row in rows(record):
            cells = "".join(
                f"<td{' class=hash' if key == 'hash' else ''}>{html.escape(row[key])}</td>"
                for key, _title in _TABLE_COLUMNS
            )
            lines.append(f"<tr>{cells}</tr>")
    lines.append("</tbody></table>")
    return "\n".join(lines)


PLOT_W: Final = 640
PLOT_H: Final = 200
_MARGIN: Final = 48


def _slope_points(records: Sequence[Record]) -> list[tuple[str, float]]:
    """The (stamp, X_Span) of a device's copied history, oldest first."""
    points = []
    for record in records:
        entry = (record.body.get("data") or {}).get("entry")
        if record.kind == "history" and isinstance(entry, dict):
            span, stamp = entry.get("x_span"), entry.get("stamp")
            if isinstance(span, int | float) and isinstance(stamp, str):
                points.append((stamp, float(span)))
    return sorted(points)


def slope_plot(records: Sequence[Record]) -> str:
    """The slope (X_Span) over the copied calibration history as an inline SVG, or "".

    Evenly spaced by calibration, labelled with the first and last stamps and the range:
    a printed report needs no script and no library.
    """
    points = _slope_points(records)
    if len(points) < 2:  # noqa: PLR2004 - a line needs two
        return ""
    spans = [span for _, span in points]
    low, high = min(spans), max(spans)
    room = (high - low) or 1.0
    width, height = PLOT_W - 2 * _MARGIN, PLOT_H - 2 * _MARGIN
    step = width / (len(points) - 1)
    xy = [
        (_MARGIN + i * step, _MARGIN + height - (span - low) / room * height)
        for i, (_, span) in enumerate(points)
    ]
    line = " ".join(f"{x:.1f},{y:.1f}" for x, y in xy)
    dots = "".join(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="3"/>' for x, y in xy)
    first, last = html.escape(points[0][0][:10]), html.escape(points[-1][0][:10])
    return (
        f'<svg class="plot" width="{PLOT_W}" height="{PLOT_H}" viewBox="0 0 {PLOT_W} {PLOT_H}" '
        'role="img" aria-label="slope (X_Span) by calibration">'
        f'<polyline fill="none" stroke="#036" stroke-width="2" points="{line}"/>'
        f'<g fill="#036">{dots}</g>'
        f'<text x="{_MARGIN}" y="{PLOT_H - 12}">{first}</text>'
        f'<text x="{PLOT_W - _MARGIN}" y="{PLOT_H - 12}" text-anchor="end">{last}</text>'
        f'<text x="4" y="{_MARGIN}">{high:g}</text>'
        f'<text x="4" y="{_MARGIN + height}">{low:g}</text>'
        f'<text x="{PLOT_W / 2}" y="20" text-anchor="middle">slope (X_Span) by calibration, '
        f"{len(points)} calibrations</text></svg>"
    )


def to_html(records: Iterable[Record], verdict: Verdict, *, title: str = "Records") -> str:
    """A printable report: the verdict, then one page per device, then the gateway's own.

    Each device's page plots the slope over its copied calibration history, lists its
    calibrations, verifications and copied history, then every record of it.
    """
    by_device: dict[str, list[Record]] = defaultdict(list)
    for record in records:
        by_device[record.device or ""].append(record)
    status = "intact" if verdict.intact else "broken"
    parts = [
        "<!doctype html><html lang=en><head><meta charset=utf-8>",
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f'<p class="{status}">{html.escape(_verdict_line(verdict))}</p>',
    ]
    for device in sorted(name for name in by_device if name):
        chosen = by_device[device]
        checks = [r for r in chosen if r.kind in {"calibration", "verification", "history"}]
        parts.append(f'<section class="device"><h2>{html.escape(device)}</h2>')
        plot = slope_plot(chosen)
        if plot:
            parts.append(f"<h3>The slope's history</h3>{plot}")
        if checks:
            parts.append("<h3>Calibrations and verifications</h3>")
            parts.append(_table(checks))
        parts.append("<h3>Every record</h3>")
        parts.append(_table(chosen))
        parts.append("</section>")
    if by_device.get(""):
        parts.append('<section class="device"><h2>The gateway</h2>')
        parts.append(_table(by_device[""]))
        parts.append("</section>")
    parts.append(f'<p class="{status}">{html.escape(_verdict_line(verdict))}</p>')
    parts.append("</body></html>\n")
    return "\n".join(parts)


def export(records: Iterable[Record], verdict: Verdict, fmt: str) -> str:
    """The records in ``fmt`` (one of :data:`FORMATS`)."""
    if fmt == "csv":
        return to_csv(records, verdict)
    if fmt == "json":
        return to_json(records, verdict)
    if fmt == "html":
        return to_html(records, verdict)
    msg = f"unknown format {fmt!r}: one of {', '.join(FORMATS)}"
    raise ValueError(msg)
