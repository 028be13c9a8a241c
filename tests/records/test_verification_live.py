"""Grab-sample verification in a running gateway: over MQTT, from ``gateway verify``, in care.

A real mosquitto, the gateway in this process, the simulator on a pseudo-terminal. The
sensor's concentration is moved after the sample is taken: the verification compares the
value the gateway read at the sample's time (from its window of recent values), not the
value now; it writes nothing to the sensor; its record names the rule and the deviation;
sensor care turns a failed one into ``due`` with the deviation in its reason.
"""

from __future__ import annotations

import asyncio
import json
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import aiomqtt
import pytest
from typer.testing import CliRunner

from gateway.cli.root import app
from gateway.records import RecordStore, records_path
from tests.mqtt_broker import free_port, recording
from tests.publish.test_mqtt import gateway, simulated

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.simulator import SimulatorServer
    from tests.mqtt_broker import Broker, Recorder

pytestmark = [pytest.mark.line, pytest.mark.broker]

SENSORS: list[dict[str, Any]] = [
    {"profile": "reiss-m0c", "address": 10, "animate": False, "values": {"unit": 4}}
]


def config(tmp_path: Path, port: int, metrics_port: int) -> str:
    return (
        f"buses:\n  - {{name: line1, port: {tmp_path / 'ttySIM'}}}\n"
        "devices:\n"
        "  - {name: basin, bus: line1, address: 10, profile: reiss-m0c, poll_interval: 0.2}\n"
        f"mqtt: {{host: 127.0.0.1, port: {port}, base_topic: gw, client_id: cab-3,"
        " reconnect_max_s: 1}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics_port}}}\n"
        "verification: {window_minutes: 10, resolution_s: 0.5}\n"
        f"state_dir: {tmp_path / 'state'}\n"
    )


async def settled(seen: Recorder, topic: str, differs_from: str | None = None) -> str:
    """The value the gateway publishes on ``topic`` once it is steady (and not ``differs_from``)."""
    for _ in range(200):
        values = seen.on(topic)
        if len(values) >= 3 and values[-1] == values[-2] == values[-3] != differs_from:
            return values[-1]
        await asyncio.sleep(0.1)
    raise AssertionError(f"{topic} never settled: {seen.on(topic)[-5:]}")


def move_concentration(server: SimulatorServer, value: float) -> None:
    behaviour = server.bus.devices[10].behaviour
    behaviour.true_concentration = value  # type: ignore[attr-defined]


async def test_verifications_over_mqtt_and_the_command_line(tmp_path: Path, broker: Broker) -> None:
    metrics_port = free_port()
    path = tmp_path / "gateway.yaml"
    path.write_text(config(tmp_path, broker.port, metrics_port), encoding="utf-8")
    async with (
        simulated(tmp_path, SENSORS) as server,
        recording(broker.port, "gw/#") as seen,
        gateway(config(tmp_path, broker.port, metrics_port)),
        aiomqtt.Client("127.0.0.1", broker.port, identifier="lims") as client,
    ):
        await seen.wait_for("gw/basin/availability", "online")
        move_concentration(server, 0.50)
        then_value = float(await settled(seen, "gw/basin/concentration"))
        sampled_at = datetime.now(UTC)
        await asyncio.sleep(1.0)
        move_concentration(server, 0.90)
        now_value = float(
            await settled(seen, "gw/basin/concentration", differs_from=str(then_value))
        )
        assert now_value > then_value + 0.3

        # Over MQTT: the sample of a few seconds ago, compared with the value then.
        reference = round(then_value + 0.04, 2)
        payload = {
            "reference": reference,
            "method": "DPD",
            "instrument": "photometer P-12",
            "sampled_at": sampled_at.isoformat(),
            "reason": "weekly check",
            "id": "v-1",
        }
        await client.publish("gw/basin/command/verify", json.dumps(payload), qos=1)
        await seen.wait_for("gw/basin/command/verify/result", within_s=15)
        result = json.loads(seen.on("gw/basin/command/verify/result")[-1])
        assert result["status"] == "ok", result
        verified = result["result"]
        assert verified["passed"] is True
        assert verified["sensor_value"] == pytest.approx(then_value, abs=1e-6)
        assert verified["unit"] == "mg/l"
        assert verified["rule"]["name"] == "EPA 334.0"
        assert verified["limit"] == pytest.approx(0.1)
        assert server.bus.devices[10].write_log == []  # a verification writes nothing

        # From the command line, through the running gateway: now, and off by ~0.4.
        runner = CliRunner()
        args = ["verify", "--config", str(path), "--device", "basin", "--reference", "0.50"]
        outcome = await asyncio.to_thread(
            runner.invoke, app, [*args, "--method", "DPD", "--reason", "after cleaning", "--json"]
        )
        assert outcome.exit_code == 1, outcome.output  # recorded, not passed
        answer = json.loads(outcome.output.splitlines()[0])
        assert answer["passed"] is False
        assert answer["sensor_value"] == pytest.approx(now_value, abs=1e-6)
        late = await asyncio.to_thread(
            runner.invoke,
            app,
            [*args, "--method", "DPD", "--sampled-at", "2020-01-01T00:00:00Z"],
        )
        assert late.exit_code == 2, late.output  # refused: nothing recorded
        assert "more than the 10 min of values" in late.output

        # Sensor care: the failed one makes the sensor due, with the deviation said.
        def care_state() -> dict[str, Any] | None:
            for text in reversed(seen.on("gw/basin/care")):
                document: dict[str, Any] = json.loads(text)
                if (document.get("last_verification") or {}).get("passed") is False:
                    return document
            return None

        for _ in range(100):
            if care_state() is not None:
                break
            await asyncio.sleep(0.1)
        care = care_state()
        assert care is not None
        assert care["state"] == "due"
        assert any("grab sample" in str(finding) for finding in care["reasons"])

    recorded_as_asked(tmp_path)


def recorded_as_asked(tmp_path: Path) -> None:
    """The two verifications' records: who, why, the instrument, the rule; the chain."""
    store = RecordStore(records_path(tmp_path / "state"), read_only=True)
    checks = [r for r in store.records() if r.kind == "verification"]
    assert [c.body["result"] for c in checks] == ["passed", "failed-check"]
    mqtt_check, cli_check = checks
    assert mqtt_check.body["actor"]["via"] == "mqtt"
    assert mqtt_check.body["actor"]["reason"] == "weekly check"
    assert mqtt_check.body["data"]["instrument"] == "photometer P-12"
    assert mqtt_check.body["data"]["rule"]["relative"] == 0.15
    assert cli_check.body["actor"]["via"] == "cli"
    assert cli_check.body["actor"]["reason"] == "after cleaning"
    assert store.verify().intact
