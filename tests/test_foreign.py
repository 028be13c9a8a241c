"""Other masters' bus time, without I/O: the bucket that holds them to their share."""

from __future__ import annotations

import pytest

from gateway.line.foreign import BURST_S, BusTimeBucket


def test_other_masters_spend_at_most_their_share_of_bus_time() -> None:
    bucket = BusTimeBucket(0.25, now=0.0)
    assert bucket.credit(0.0) == pytest.approx(0.25 * BURST_S)  # a first burst need not wait
    bucket.spend(0.6, now=0.0)  # one long transaction overspends
    assert bucket.credit(0.0) == pytest.approx(-0.1)
    assert bucket.available_at(0.0) == pytest.approx(0.4)  # 0.1 s paid back at 0.25 s/s
    assert bucket.credit(0.4) == pytest.approx(0.0)
    assert bucket.credit(100.0) == pytest.approx(0.5)  # refilled, never beyond the window


def test_over_any_long_run_the_bus_time_spent_is_the_share() -> None:
    bucket = BusTimeBucket(0.1, now=0.0)
    now, spent = 0.0, 0.0
    while now < 600.0:
        if bucket.credit(now) > 0:
            bucket.spend(0.05, now)  # a 50 ms transaction whenever allowed
            spent += 0.05
        now = max(now + 0.05, bucket.available_at(now))
    assert spent / 600.0 == pytest.approx(0.1, abs=0.002)
