"""The sensor's own minimum response time (digiLine 0x0305): read, applied, and explained.

A digiLine sensor set to answer no sooner than 200 ms, on a config that says nothing of it,
used to time out on every read, and its late answers counted as stale frames with no hint.
"""

from __future__ import annotations

import logging
import re
from typing import TYPE_CHECKING

import pytest

from gateway.line.stats import ErrorKind
from tests.rigs import rig, target

if TYPE_CHECKING:
    from pathlib import Path


pytestmark = [pytest.mark.line, pytest.mark.timing]

SLOW_S10 = {
    "profile": "jumo-digiline-odo-s10",
    "address": 1,
    "animate": False,
    "values": {"temperature": 21.5},
    "registers": {0x0305: 200},  # minimum response time 200 ms
}


async def test_a_sensor_set_slower_than_the_config_is_read_at_its_own_pace(
    tmp_path: Path,
) -> None:
    s10 = target("s10", "jumo-digiline-odo-s10", 1, interval=0.5)
    assert s10.timeout_s is None
    assert s10.min_response_time_s == 0.0  # the config says nothing of it
    async with rig(tmp_path, [SLOW_S10], [s10]) as r:
        await r.run_for(6.0)
        state = r.worker.devices["s10"]
        assert state.values["min_response_time"] == 200  # read first, from the sensor
        timeouts = sum(n for (_, kind), n in r.line.stats.errors.items() if kind == "timeout")
        # Without the register every read timed out. One may still, on a machine so busy
        # that the event loop is held past the timeout's 50 ms margin.
        assert timeouts <= 1
        assert r.line.stats.responses[1] >= 10
        assert r.server.bus.violations == []
        latency = r.line.stats.latency_sum_s[1] / r.line.stats.responses[1]
    temperatures = r.sink.good("s10", "temperature")
    # Each read takes the sensor's 200 ms: identity first, then values as often as they fit.
    assert len(temperatures) >= 4
    assert {s.value for s in temperatures} == {21.5}
    assert latency >= 0.2  # every answer took the sensor's 200 ms, and was waited for


async def test_a_timeout_too_short_for_the_sensor_is_named_once_with_the_lateness(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # The configured timeout caps the wait: 100 ms, while the sensor takes 200 ms.
    s10 = target("s10", "jumo-digiline-odo-s10", 1, interval=0.5, timeout_s=0.1)
    async with rig(tmp_path, [SLOW_S10], [s10], late_answer_window_s=0.3) as r:
        await r.run_for(3.0)
        stale = sum(n for (_, kind), n in r.line.stats.errors.items() if kind == ErrorKind.STALE)
    assert stale >= 2
    hints = [
        r.getMessage() for r in caplog.records if "after the gateway had given up" in r.getMessage()
    ]
    assert len(hints) == 1  # once per device, not per late answer
    (hint,) = hints
    assert hint.startswith("line1/s10: an answer came ")
    after_ms = int(re.search(r"an answer came (\d+) ms after its request", hint)[1])  # type: ignore[index]
    assert 200 <= after_ms < 400  # 200 ms of the sensor plus both frames at 9600 8E1
    assert "(timeout 100 ms)" in hint
    assert "the timeout is too short for this device" in hint
    suggested = float(re.search(r"`timeout: ([\d.]+)` for device s10", hint)[1])  # type: ignore[index]
    assert suggested >= after_ms / 1000
    assert (
        caplog.records[[r.getMessage() for r in caplog.records].index(hint)].levelno
        == logging.WARNING
    )
