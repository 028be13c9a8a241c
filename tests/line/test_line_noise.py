"""A line that never falls silent: the request is held back, for a bounded time, and said so.

An unbiased or badly earthed line (or another master) can put a byte on the wire every
millisecond. The gateway used to wait for silence without end: a request went out 2.6 s
late and no error was counted. Now the wait has a bound, the request is never sent into
the noise, and the error has a kind of its own that /healthz shows.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import pytest

from gateway.errors import LineNoiseError
from gateway.line.engine.devices import DeviceTarget
from gateway.line.stats import ErrorKind
from gateway.line.transports.rtu import QUIET_WAIT_FRAMES, QUIET_WAIT_MIN_S
from gateway.profiles import get_profile
from gateway.publish.prometheus import health_report
from gateway.shared.state import GatewayState
from gateway.wire import frames
from tests.shimmed import shimmed

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line, pytest.mark.timing]

S10 = {
    "profile": "jumo-digiline-odo-s10",
    "address": 1,
    "animate": False,
    "values": {"temperature": 21.5},
}
# A 100 ms gap asked for by the device: a busy machine can hold a pty's bytes back for tens
# of milliseconds (a kernel worker moves them), which a shorter gap would take for silence.
TARGETS = [
    DeviceTarget(
        name="s10",
        address=1,
        profile=get_profile("jumo-digiline-odo-s10"),
        intervals={},
        extra_gap_s=0.1,
    )
]


async def test_no_request_goes_into_a_line_that_never_falls_silent(tmp_path: Path) -> None:
    async with shimmed(tmp_path, [S10], TARGETS, noise_interval_s=0.0005) as rig:
        state = rig.state("s10")
        state.values["min_response_time"] = 0  # known: this read is not the register's
        request = frames.read_request(1, 0x2620, 2)
        await rig.shim.noisy()
        started = time.monotonic()
        with pytest.raises(LineNoiseError) as caught:
            await rig.worker.transactions.transact(state, request, 9)
        waited = time.monotonic() - started
        # Two of the longest frames at 9600 8E1 (11 bits a character): 0.59 s.
        bound = max(QUIET_WAIT_MIN_S, QUIET_WAIT_FRAMES * 11 / 9600)
        assert bound <= waited < bound + 0.25
        assert "the line never fell silent for the 100.0 ms gap in 0.6 s" in str(caught.value)
        assert "the request to device 1 was not sent" in str(caught.value)
        assert "bytes of noise" in str(caught.value)
        assert rig.shim.counters.to_line == 0  # nothing reached the sensors
        assert rig.server.bus.counters["requests"] == 0 or not rig.server.bus.frame_log
        assert rig.errors().get(ErrorKind.NO_SILENCE) == 1
        assert rig.line.stats.requests[1] == 0

        state_view = GatewayState()
        state_view.add_line("line1", rig.line.stats, list)
        healthy, body = health_report(state_view)
        assert not healthy
        bus = body["buses"]["line1"]  # type: ignore[index]
        assert bus["no_silence_errors"] == 1
        assert bus["line_noise"].startswith(str(tmp_path / "ttyUSB0"))
        assert any("never fell silent" in reason for reason in body["reasons"])  # type: ignore[attr-defined]

        # The noise stops: the next read goes out after the gap, and the line is healthy.
        rig.shim.noise_interval_s = 0.0
        (sample,) = await rig.read("s10", "temperature")
        assert sample.value == 21.5
        assert rig.server.bus.violations == []
        healthy, body = health_report(state_view)
        assert healthy, body
        assert body["buses"]["line1"]["line_noise"] is None  # type: ignore[index]
