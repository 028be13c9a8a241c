"""The gateway state kept by device: the latest and the last good sample of every point."""

from __future__ import annotations

from datetime import UTC, datetime

from gateway.line.samples import Quality, Sample
from gateway.shared.state import GatewayState


def sample(device: str, point: str, value: float | None, at: float, *, good: bool = True) -> Sample:
    return Sample(
        bus="line1",
        device=device,
        profile="reiss-m0c",
        point=point,
        value=value,
        fault=None if good else "overrange",
        unit="ppm",
        quality=Quality.GOOD if good else Quality.FAULT,
        monotonic=at,
        time=datetime.now(tz=UTC),
        group="process",
    )


def test_the_last_good_sample_outlives_faults_until_a_good_one_replaces_it() -> None:
    state = GatewayState()
    first = sample("basin", "concentration", 0.5, 1.0)
    state.record([first, sample("basin", "temperature", 17.5, 1.0)])
    fault = sample("basin", "concentration", None, 2.0, good=False)
    state.record([fault])
    state.record([sample("basin", "concentration", None, 3.0, good=False)])
    key = ("line1", "basin", "concentration")
    assert state.latest[key].monotonic == 3.0
    assert state.last_good[key] is first  # not the fault, nor lost after two of them
    snapshot = state.snapshot()
    assert snapshot.last_good[key] is first
    again = sample("basin", "concentration", 0.7, 4.0)
    state.record([again])
    assert state.last_good[key] is again
    assert snapshot.last_good[key] is first  # a snapshot does not follow the state
    assert dict(state.last_good) == {
        key: again,
        ("line1", "basin", "temperature"): state.latest["line1", "basin", "temperature"],
    }


def test_a_point_never_good_has_a_latest_sample_and_no_last_good_one() -> None:
    state = GatewayState()
    state.record([sample("pool", "concentration", None, 1.0, good=False)])
    key = ("line1", "pool", "concentration")
    assert list(state.latest) == [key]
    assert len(state.latest) == 1
    assert key not in state.last_good
    assert state.last_good.get(key) is None
    assert len(state.last_good) == 0
    assert list(state.latest.values()) == [state.latest[key]]
    assert state.device_samples("line1", "pool") == {"concentration": state.latest[key]}
