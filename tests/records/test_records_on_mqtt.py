"""The records of a running gateway: a set command over MQTT, its records, and their head.

A real mosquitto, the gateway in this process, the simulator on a pseudo-terminal. A plant
system publishes ``…/set`` with a reason; the records name the gateway's broker
connection (MQTT does not say who published) and the reason; each record is one QoS 1
message on ``{base}/records`` (not retained) and the chain's head is retained on
``{base}/records/head``, in ``/metrics`` and in ``/healthz``, equal to the store's.
``gateway records export`` reads the store while the gateway runs.
"""

from __future__ import annotations

import json
import urllib.request
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

    from tests.mqtt_broker import Broker

pytestmark = [pytest.mark.line, pytest.mark.broker]

SENSORS: list[dict[str, Any]] = [{"profile": "jumo-digiline-odo-s10", "address": 1}]


def config(tmp_path: Path, port: int, metrics_port: int) -> str:
    return (
        f"buses:\n  - {{name: line1, port: {tmp_path / 'ttySIM'}}}\n"
        "devices:\n"
        "  - {name: aeration, bus: line1, address: 1, profile: jumo-digiline-odo-s10,"
        " poll_interval: 0.5}\n"
        f"mqtt: {{host: 127.0.0.1, port: {port}, base_topic: gw, client_id: cabinet-7,"
        " username: gateway-7, reconnect_max_s: 1}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics_port}}}\n"
        f"state_dir: {tmp_path / 'state'}\n"
    )


def get(url: str) -> str:
    with urllib.request.urlopen(url, timeout=5) as answer:  # noqa: S310 - http://127.0.0.1
        return str(answer.read().decode())


async def test_a_set_command_is_recorded_published_and_its_head_shown(
    tmp_path: Path, broker: Broker
) -> None:
    metrics_port = free_port()
    async with (
        simulated(tmp_path, SENSORS) as server,
        recording(broker.port, "gw/#") as seen,
        gateway(config(tmp_path, broker.port, metrics_port)),
        aiomqtt.Client("127.0.0.1", broker.port, identifier="plant-system") as client,
    ):
        await seen.wait_for("gw/aeration/availability", "online")
        sensor = server.bus.devices[1]
        found = sensor.get("compensation_temperature")
        payload = json.dumps({"value": 22.5, "id": "c-1", "reason": "probe moved to basin 2"})
        await client.publish("gw/aeration/compensation_temperature/set", payload, qos=1)
        await seen.wait_for("gw/aeration/compensation_temperature/set/result", within_s=15)
        [result] = seen.on("gw/aeration/compensation_temperature/set/result")
        assert json.loads(result)["status"] == "ok"
        await seen.wait_for("gw/records/head", within_s=10)

        store = RecordStore(records_path(tmp_path / "state"), read_only=True)
        writes = [r for r in store.records() if r.kind in {"write", "outcome"}]
        write, outcome = writes
        assert write.body["actor"] == {
            "user": "gateway-7",
            "via": "mqtt",
            "detail": "client id cabinet-7; topic gw/aeration/compensation_temperature/set",
            "reason": "probe moved to basin 2",
            "signed": False,
        }
        assert write.body["points"][0]["as_found"] == found
        assert outcome.body["points"][0]["as_left"] == 22.5
        assert sensor.get("compensation_temperature") == 22.5

        # Every record as one message, not retained, with its hash; the head retained.
        head = store.head
        published = [json.loads(m) for m in seen.on("gw/records")]
        by_seq = {document["seq"]: document for document in published}
        assert by_seq[write.seq]["hash"] == write.hash
        assert by_seq[outcome.seq]["completes"] == write.seq
        assert not any(m.retain for m in seen.messages if m.topic == "gw/records")
        last_head = json.loads(seen.on("gw/records/head")[-1])
        assert (last_head["seq"], last_head["hash"]) == (head.seq, head.hash)

        exposition = get(f"http://127.0.0.1:{metrics_port}/metrics")
        assert f"gateway_records_head_sequence {float(head.seq)}" in exposition
        assert f'gateway_records_head{{hash="{head.hash}",seq="{head.seq}"}} 1.0' in exposition
        health = json.loads(get(f"http://127.0.0.1:{metrics_port}/healthz"))
        assert health["records"] == {"head": {"seq": head.seq, "hash": head.hash}}

        # A readable copy while the gateway runs, ending with the chain's verdict.
        exported = CliRunner().invoke(
            app,
            ["records", "export", "--state-dir", str(tmp_path / "state"), "--format", "json"],
        )
        assert exported.exit_code == 0, exported.output
        document = json.loads(exported.output)
        assert document["verdict"]["intact"] is True
        assert document["verdict"]["head"]["seq"] >= head.seq
        assert [r["seq"] for r in document["records"]][: head.seq] == list(range(1, head.seq + 1))

    # A retained head a later subscriber gets (what a copy kept elsewhere is made from).
    async with recording(broker.port, "gw/records/head", name="late") as late:
        await late.wait_for("gw/records/head")
        assert all(m.retain for m in late.messages)
