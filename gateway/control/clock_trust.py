"""The gate on writes that put the host's wall clock into a sensor: refused until it is trusted.

A date written into a sensor stays there: ``set-clock`` sets the S10's clock (which stamps
its records) or the H10/H20 calibration date (which goes into every logbook entry after
it); a tecLine/Reiss calibration is activated by writing its date stamp, and a stamp
earlier than the last calibration's overwrites history entry 0 instead of adding an entry
(tecLine annex 7.2, Reiss 5.1): a clock that is days behind loses calibration history.

So every write that reaches a date-and-time register (a writable ``datetime`` or
``yymmddhhmm`` point, or a view over one: the S10's ``clock_year``) is refused while the
host clock is not synchronised (:class:`~gateway.shared.host_clock.HostClock`), whoever
asks: ``set-clock``, a guided calibration (before it reads or asks anything), a
``…/set`` or Sparkplug DCMD or the page (:class:`~gateway.control.writes.SafeWriter`),
another master on the shared bus. One rule for every path: the gateway cannot vouch for a
date while its own clock is a guess. ``clock.trust_unsynchronised: true`` lifts it, for a
plant without time sync whose clock is set by hand.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

from gateway.errors import CommandRejectedError
from gateway.shared.host_clock import FIX
from gateway.wire.codec import DataType

if TYPE_CHECKING:
    from gateway.profiles.model import Point, Profile
    from gateway.shared.host_clock import HostClock

TIME_TYPES: Final = frozenset({DataType.DATETIME, DataType.YYMMDDHHMM})

# What a wrong date does in each kind of register, for the refusal (the manuals' sections).
_CONSEQUENCE: Final = {
    DataType.YYMMDDHHMM: (
        "; a calibration stamp earlier than the sensor's last overwrites its history entry "
        "0 instead of adding one, so calibration history is lost (tecLine annex 7.2)"
    ),
    DataType.DATETIME: "; the sensor keeps it and dates its records or logbook entries by it",
}


def time_points(profile: Profile) -> tuple[Point, ...]:
    """The profile's writable date-and-time points (the S10 clock, a calibration stamp)."""
    return tuple(p for p in profile.points if p.writable and p.dtype in TIME_TYPES)


def time_point_touched(profile: Profile, address: int, count: int) -> Point | None:
    """The date-and-time point a write of ``count`` registers at ``address`` reaches, if any."""
    last = address + count - 1
    for point in time_points(profile):
        if point.address <= last and point.last >= address:
            return point
    return None


def clock_refusal(clock: HostClock, action: str, point: Point | None = None) -> str | None:
    """Why ``action`` must not write the wall clock now (``None``: it may).

    ``point`` is the date-and-time point it writes, for what a wrong date does there.
    """
    status = clock.status()
    if status.trusted:
        return None
    consequence = _CONSEQUENCE.get(point.dtype, "") if point is not None else ""
    return (
        f"{action} refused: {status.problem}, so the date written could be hours or days "
        f"wrong{consequence}. To fix: {FIX}"
    )


def require_trusted_clock(clock: HostClock, action: str, point: Point | None = None) -> None:
    """Refuse ``action`` (a :class:`CommandRejectedError`, nothing sent) unless trusted."""
    reason = clock_refusal(clock, action, point)
    if reason is not None:
        raise CommandRejectedError(reason, point=point.name if point is not None else "")


def require_trusted_for(clock: HostClock, profile: Profile, point: Point, action: str) -> None:
    """Refuse a write of ``point`` that reaches a date-and-time register, unless trusted."""
    touched = time_point_touched(profile, point.address, point.count)
    if touched is not None:
        require_trusted_clock(clock, action, touched)
