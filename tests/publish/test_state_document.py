"""The state document of ``{base}/{device}/state``: every point, its unit, fault and quality.

Pure: the document is built from the gateway state, no broker involved.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime

from gateway.config import MqttConfig
from gateway.line.samples import Quality
from gateway.publish.mqtt.topics import Topics
from gateway.shared.state import STALE_FACTOR, STALE_MARGIN_S, DeviceInfo, GatewayState
from tests.publish.prometheus.test_prometheus import sample

M0C = "reiss-m0c"


def topics_for(intervals: dict[str, float | None]) -> tuple[GatewayState, Topics]:
    state = GatewayState()
    state.add_device(
        DeviceInfo(bus="line1", name="basin", profile=M0C, address=10, intervals=intervals)
    )
    return state, Topics(MqttConfig(host="127.0.0.1", base_topic="gw"), state, client_id="t")


def document(topics: Topics) -> dict[str, object]:
    message = topics.documents.build("line1", "basin", datetime(2026, 11, 25, tzinfo=UTC))
    assert message.topic == "gw/basin/state"
    assert message.payload.startswith(b'{"time":"2026-11-25T00:00:00+00:00","seq":')  # compact
    loaded: dict[str, object] = json.loads(message.payload)
    return loaded


def test_a_device_with_nothing_recorded_yet_gets_an_empty_document() -> None:
    _, topics = topics_for({"concentration": 1.0})
    assert document(topics) == {
        "time": "2026-11-25T00:00:00+00:00",
        "seq": 1,
        "values": {},
        "units": {},
        "faults": {},
        "quality": {},
    }


def test_points_added_later_join_the_document_in_name_order() -> None:
    state, topics = topics_for({"concentration": 1.0, "temperature": 1.0, "serial": None})
    state.record([sample("basin", M0C, "temperature", 21.5, unit="°C")])
    first = document(topics)
    assert first["values"] == {"temperature": 21.5}
    state.record(
        [
            sample("basin", M0C, "concentration", 0.5, unit="mg/l"),
            sample("basin", M0C, "serial", 1234),
        ]
    )
    second = document(topics)
    assert second["seq"] == 2
    assert list(second["values"]) == ["concentration", "serial", "temperature"]  # type: ignore[call-overload]
    assert second["values"] == {"concentration": 0.5, "serial": 1234, "temperature": 21.5}
    assert second["units"] == {"concentration": "mg/l", "serial": None, "temperature": "°C"}


def test_quality_is_stale_past_its_interval_good_before_and_a_fault_is_named() -> None:
    interval = 10.0
    limit = STALE_FACTOR * interval + STALE_MARGIN_S
    state, topics = topics_for({"concentration": interval, "temperature": interval, "serial": None})
    state.record(
        [
            sample("basin", M0C, "concentration", 0.5, age_s=limit + 1.0),
            sample("basin", M0C, "temperature", 21.5, age_s=limit - 1.0),
            # Read once (no interval): never stale, however old.
            sample("basin", M0C, "serial", 1234, age_s=10 * limit),
        ]
    )
    assert document(topics)["quality"] == {
        "concentration": "stale",
        "serial": "good",
        "temperature": "good",
    }
    state.record([sample("basin", M0C, "concentration", fault="overrange", quality=Quality.FAULT)])
    after = document(topics)
    assert after["faults"] == {"concentration": "overrange"}
    assert after["quality"] == {"concentration": "fault", "serial": "good", "temperature": "good"}
    assert "concentration" not in after["values"]  # type: ignore[operator]
