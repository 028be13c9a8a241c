"""A least-squares line through a sensor's calibrations, and where it crosses a limit.

As transmitters that track their sensors do (Yokogawa SENCOM's slope and zero logs, Mettler
ISM's dynamic lifetime indicator), the trend is an ordinary least-squares fit of the value
over the calibration dates, judged by its coefficient of determination (r²). A projection
is made only from enough points that lie well on the line and fall; its range is the
fitted fall rate at both ends of its 90 % confidence interval (Student's t).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import TYPE_CHECKING, Final

from gateway.care.report import Projection, Trend

if TYPE_CHECKING:
    from collections.abc import Sequence

WEEK_S: Final = 7 * 86400.0
MIN_POINTS: Final = 3  # a line through two points always fits: no trend from fewer than 3
# Two-sided 90 % quantiles of Student's t by degrees of freedom (n - 2). A sensor holds at
# most 5 calibrations (tecLine annex 7.2) or 10 logbook entries (H10/H20 manual 6.1.6), but
# the records copy every one, so a membrane cap's trend may have dozens; past 30 degrees of
# freedom the normal quantile, 1.645, which is within 3 % of t's and closer with more.
_T90: Final = {
    1: 6.314, 2: 2.920, 3: 2.353, 4: 2.132, 5: 2.015, 6: 1.943, 7: 1.895, 8: 1.860,
    9: 1.833, 10: 1.812, 11: 1.796, 12: 1.782, 13: 1.771, 14: 1.761, 15: 1.753, 16: 1.746,
    17: 1.740, 18: 1.734, 19: 1.729, 20: 1.725, 21: 1.721, 22: 1.717, 23: 1.714, 24: 1.711,
    25: 1.708, 26: 1.706, 27: 1.703, 28: 1.701, 29: 1.699, 30: 1.697,
}  # fmt: skip
HIGH_CONFIDENCE_R2: Final = 0.95  # our threshold for calling a projection's fit "high"
HIGH_CONFIDENCE_POINTS: Final = 4
LONGEST_PROJECTION: Final = timedelta(days=3650)  # further out than this is not a date


@dataclass(frozen=True, slots=True)
class Fit:
    """``value = intercept + slope * weeks`` since ``origin``, with its quality."""

    origin: datetime
    intercept: float
    slope: float  # per week
    r2: float
    slope_se: float  # standard error of the slope (per week); 0 for a perfect fit
    points: int

    def value_at(self, when: datetime) -> float:
        """The fitted value at ``when``."""
        return self.intercept + self.slope * _weeks(when, self.origin)

    def trend(self) -> Trend:
        """The fit as the care document shows it."""
        return Trend(per_week=self.slope, r2=self.r2, points=self.points, since=self.origin)


def _weeks(when: datetime, origin: datetime) -> float:
    return (when - origin).total_seconds() / WEEK_S


def fit(points: Sequence[tuple[datetime, float]]) -> Fit | None:
    """The least-squares line through ``points``; None from fewer than 3 or one date only."""
    if len(points) < MIN_POINTS:
        return None
    ordered = sorted(points)
    origin = ordered[0][0]
    xs = [_weeks(when, origin) for when, _ in ordered]
    ys = [value for _, value in ordered]
    n = len(xs)
    mean_x, mean_y = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mean_x) ** 2 for x in xs)
    if sxx <= 0:
        return None
    sxy = sum((x - mean_x) * (y - mean_y) for x, y in zip(xs, ys, strict=True))
    slope = sxy / sxx
    intercept = mean_y - slope * mean_x
    residual = sum((y - intercept - slope * x) ** 2 for x, y in zip(xs, ys, strict=True))
    total = sum((y - mean_y) ** 2 for y in ys)
    r2 = 1.0 if total == 0 else max(0.0, 1.0 - residual / total)
    slope_se = math.sqrt(residual / (n - 2) / sxx) if n > 2 else 0.0  # noqa: PLR2004
    return Fit(origin=origin, intercept=intercept, slope=slope, r2=r2, slope_se=slope_se, points=n)


def _crossing(fitted: Fit, slope: float, limit: float, after: datetime) -> datetime | None:
    """When a line of ``slope`` through the fit's centre reaches ``limit``, after ``after``."""
    if slope >= 0:
        return None
    # Pivot at the newest point's fitted value, so both ends start from where it is now.
    start = fitted.value_at(after)
    weeks = (limit - start) / slope
    if weeks < 0:
        return after
    span = timedelta(seconds=weeks * WEEK_S)
    return after + span if span <= LONGEST_PROJECTION else None


def project(
    fitted: Fit, *, limit: float, newest: datetime, min_r2: float
) -> tuple[Projection | None, str]:
    """When the fitted value falls to ``limit``, or why that cannot be said.

    ``newest`` is the latest calibration: the projection starts from the line's value
    there. The note says why there is no projection (too few points, a poor fit, not
    falling, or further away than ten years).
    """
    if fitted.r2 < min_r2:
        return None, (
            f"no projection: the {fitted.points} calibrations do not lie on a line "
            f"(r² {fitted.r2:.2f}, below {min_r2:.2f})"
        )
    if fitted.slope >= 0:
        return None, "no projection: the slope is not falling"
    at = _crossing(fitted, fitted.slope, limit, newest)
    if at is None:
        return None, "no projection: at this rate the limit is more than ten years away"
    t = _T90.get(fitted.points - 2, 1.645)
    earliest = _crossing(fitted, fitted.slope - t * fitted.slope_se, limit, newest) or at
    latest = _crossing(fitted, fitted.slope + t * fitted.slope_se, limit, newest)
    high = fitted.r2 >= HIGH_CONFIDENCE_R2 and fitted.points >= HIGH_CONFIDENCE_POINTS
    return (
        Projection(
            at=at, earliest=earliest, latest=latest, confidence="high" if high else "medium"
        ),
        "",
    )
