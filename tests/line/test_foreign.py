"""Other masters' bus time, without I/O: the bucket that holds them to their share."""

from __future__ import annotations

import pytest

from gateway.line.engine.foreign import BURST_S, BusTimeBucket


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


def test_a_request_goes_when_the_share_covers_it_not_before() -> None:
    bucket = BusTimeBucket(0.25, now=0.0)
    bucket.spend(0.4, now=0.0)  # 0.1 s left
    assert bucket.allows(0.05, 0.0)  # a short read fits
    assert not bucket.allows(0.29, 0.0)  # a long one waits: it would overdraw the share
    assert bucket.available_at(0.0, 0.29) == pytest.approx(0.76)  # 0.19 s at 0.25 s/s
    assert bucket.allows(0.29, 0.76)
    # One longer than the window (0.5 s here) waits for a full window, then overdraws.
    assert bucket.available_at(0.76, 0.8) == pytest.approx(0.76 + 0.21 / 0.25)
    assert not bucket.allows(0.8, 1.5)
    assert bucket.allows(0.8, 1.6)


def test_long_reads_that_wait_to_be_covered_still_get_the_whole_share() -> None:
    bucket = BusTimeBucket(0.25, now=0.0)
    now, spent = 0.0, 0.0
    while now < 600.0:
        if bucket.allows(0.29, now):
            bucket.spend(0.29, now)  # a read of 120 registers at 9600 baud
            spent += 0.29
        now = max(now + 0.01, bucket.available_at(now, 0.29))
    assert spent / 600.0 == pytest.approx(0.25, abs=0.005)
