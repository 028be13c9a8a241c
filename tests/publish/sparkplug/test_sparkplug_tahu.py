"""Sparkplug B read as a host reads it: Eclipse Tahu's JavaScript library beside mosquitto.

A subscriber to ``spBv1.0/#`` on a real mosquitto hands every message, as it arrives, to
Eclipse Tahu's ``sparkplug-payload`` (npm, on protobufjs; ``tests/sparkplug_js``, installed
by ``scripts/setup test``) in a node process, which decodes it; commands are encoded by the
same library. Nothing of the gateway's encoding (its protobuf runtime, its generated code)
takes part in reading them. Each
payload is also read by the hand-written decoder of ``tests/sparkplug_decoder.py``, and the
two must agree metric by metric. Test names carry the Sparkplug 3.0 statement ids they prove
(docs/sparkplug-conformance.md).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import aiomqtt
import pytest

from gateway.profiles import get_profile
from tests import paths
from tests.mqtt_broker import Broker, subscribed
from tests.publish.sparkplug.test_sparkplug import (
    EDGE,
    NODE,
    SpRecorder,
    assert_seq_never_skips,
    sp_recording,
    sp_yaml,
)
from tests.publish.test_mqtt import gateway, simulated

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Iterator

    from tests.sparkplug_decoder import DecodedMetric

HOST_JS = paths.TESTS / "sparkplug_js" / "host.js"
NODE_JS = shutil.which("node")

pytestmark = [pytest.mark.line, pytest.mark.broker]


@pytest.fixture(autouse=True)
def _tahu_installed() -> None:
    """node and Tahu's library are test tools as mosquitto is: missing, the test fails."""
    assert NODE_JS, "node is missing: scripts/setup test installs it (as root)"
    installed = HOST_JS.parent / "node_modules" / "sparkplug-payload"
    assert installed.is_dir(), "Tahu's sparkplug-payload is missing: run scripts/setup test"


# Every metric type of the S10 and the Reiss: identity (String, DateTime, enums),
# configuration (writable Floats, enums, bit fields) and diagnostics besides the defaults.
EVERY_GROUP = ", device_groups: {aeration: [process, status, configuration, identity, diagnostics]}"


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    """mosquitto queueing QoS 0 for persistent subscribers, as the other Sparkplug tests."""
    directory = tmp_path / "broker"
    directory.mkdir()
    running = Broker(directory, extra=["queue_qos0_messages true"])
    running.start()
    yield running
    running.stop()


@dataclass
class TahuHost:
    """What the host received, in order, as Tahu decoded it."""

    messages: list[dict[str, Any]] = field(default_factory=list)

    def on(self, topic: str) -> list[dict[str, Any]]:
        return [m for m in self.messages if m["topic"] == topic]

    async def wait_until(self, check: Any, within_s: float = 20.0) -> None:
        deadline = asyncio.get_running_loop().time() + within_s
        while asyncio.get_running_loop().time() < deadline:
            if check():
                return
            await asyncio.sleep(0.05)
        raise AssertionError(f"never true; last: {[m['topic'] for m in self.messages[-5:]]}")


@contextlib.asynccontextmanager
async def tahu_host(port: int) -> AsyncIterator[TahuHost]:
    """A subscriber to ``spBv1.0/#`` handing every message to Tahu's decoder, in order."""
    assert NODE_JS is not None
    decoder = await asyncio.create_subprocess_exec(
        NODE_JS,
        str(HOST_JS),
        "decode",
        stdin=asyncio.subprocess.PIPE,
        stdout=asyncio.subprocess.PIPE,
    )
    assert decoder.stdin is not None
    assert decoder.stdout is not None
    host = TahuHost()

    async def take(stdout: asyncio.StreamReader) -> None:
        async for line in stdout:
            host.messages.append(json.loads(line))

    reader = asyncio.create_task(take(decoder.stdout), name="tahu-host")

    def hand_over(message: aiomqtt.Message) -> None:
        payload = message.payload
        assert isinstance(payload, bytes)
        line = f"{message.topic} {payload.hex()}\n"
        decoder.stdin.write(line.encode())  # type: ignore[union-attr]

    try:
        async with subscribed(port, "spBv1.0/#", hand_over, name="tahu-host"):
            yield host
    finally:
        decoder.stdin.close()
        await asyncio.wait_for(decoder.wait(), timeout=10)  # its input ended
        await asyncio.wait_for(reader, timeout=10)


def tahu_encode(payload: dict[str, Any]) -> bytes:
    """A payload encoded by Tahu's ``encodePayload`` (as a host sends a command)."""
    assert NODE_JS is not None
    import subprocess  # noqa: PLC0415 - only here, for one short child

    done = subprocess.run(
        [NODE_JS, str(HOST_JS), "encode"],
        input=json.dumps(payload).encode(),
        capture_output=True,
        check=True,
        timeout=30,
    )
    return bytes.fromhex(done.stdout.decode().strip())


def raw_value(raw: dict[str, Any], datatype: str) -> object:
    """A metric's value from the protobuf field its datatype uses, as protobufjs reads it.

    Tahu's ``decodePayload`` gives no value to a DDATA metric (it has no datatype there: a
    host looks the type up in the birth by alias), and Tahu 1.0.3 reads a UInt32 from
    ``long_value`` only, while the gateway sends it in ``int_value``, the schema's
    ``uint32`` field (README, Sparkplug B, Conformance). So values are compared here,
    field by field, by the datatype of the birth.
    """
    if raw.get("isNull"):
        return None
    if datatype in {"Int8", "Int16", "Int32"}:
        bits = {"Int8": 8, "Int16": 16, "Int32": 32}[datatype]
        value = int(raw["intValue"]) & ((1 << bits) - 1)
        return value - (1 << bits) if value >> (bits - 1) else value
    field_of = {
        "UInt8": "intValue",
        "UInt16": "intValue",
        "UInt32": "intValue",
        "Int64": "longValue",
        "UInt64": "longValue",
        "DateTime": "longValue",
        "Float": "floatValue",
        "Double": "doubleValue",
        "Boolean": "booleanValue",
        "String": "stringValue",
    }
    value = raw[field_of[datatype]]
    return int(value) if field_of[datatype] in {"intValue", "longValue"} else value


def assert_same_metric(
    tahu: dict[str, Any], raw: dict[str, Any], mine: DecodedMetric, datatype: str
) -> None:
    """Tahu and the hand-written decoder read one metric alike (``datatype``: the birth's)."""
    assert tahu.get("name") == mine.name
    assert (int(tahu["alias"]) if "alias" in tahu else None) == mine.alias
    assert (int(tahu["timestamp"]) if "timestamp" in tahu else None) == mine.timestamp
    assert tahu.get("type") == mine.datatype, mine.name
    assert bool(raw.get("isHistorical")) == mine.is_historical
    assert bool(raw.get("isNull")) == mine.is_null
    assert raw_value(raw, datatype) == mine.value, (mine.name, raw, mine)
    if mine.datatype is not None and datatype not in {"UInt32", "Int64", "UInt64", "DateTime"}:
        assert tahu["value"] == mine.value, (mine.name, tahu)  # Tahu's own reading
    properties = {key: p["value"] for key, p in tahu.get("properties", {}).items()}
    assert properties == mine.properties, mine.name
    for key, prop in tahu.get("properties", {}).items():
        expected = {"Quality": "Int32", "readOnly": "Boolean"}.get(key, "String")
        assert prop["type"] == expected, key


def pair(host: TahuHost, seen: SpRecorder) -> list[tuple[dict[str, Any], Any]]:
    """Each message Tahu decoded with the same message as the hand-written decoder read it.

    Both subscribers see each topic's messages in the order the broker sent them.
    """
    pairs: list[tuple[dict[str, Any], Any]] = []
    for topic in {m.topic for m in seen.messages if m.kind not in {"STATE", "NCMD", "DCMD"}}:
        tahu = host.on(topic)
        mine = seen.on(topic)
        count = min(len(tahu), len(mine))
        pairs.extend(zip(tahu[:count], mine[:count], strict=True))
    return pairs


async def test_tahu_decodes_births_data_and_deaths_as_the_gateway_means_them(
    tmp_path: Path, broker: Broker
) -> None:
    """tck-id-payloads-alias-birth-requirement, -metric-datatype-req, -name-birth-data-…

    …requirement, -alias-data-cmd-requirement, -metric-datatype-not-req, the timestamps and
    sequence numbers of every message, the Quality codes, and the device's death.
    """
    sensors = [
        {"profile": "jumo-digiline-odo-s10", "address": 1, "animate": True},
        {"profile": "reiss-m0c", "address": 10, "animate": True},
    ]
    async with (
        simulated(tmp_path, sensors) as server,
        tahu_host(broker.port) as host,
        sp_recording(broker.port) as seen,
        gateway(sp_yaml(tmp_path, broker.port, sparkplug=EVERY_GROUP)),
    ):
        await seen.wait_for(f"{NODE}/DDATA/{EDGE}/aeration", count=3)
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/basin")
        server.bus.silence(1, 2.5, asyncio.get_running_loop().time())
        await seen.wait_for(f"{NODE}/DDEATH/{EDGE}/aeration")
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/aeration", count=2, within_s=30)
        await host.wait_until(lambda: len(host.on(f"{NODE}/DBIRTH/{EDGE}/aeration")) == 2)
    await host.wait_until(lambda: host.on(f"{NODE}/NDEATH/{EDGE}"))
    assert not [m for m in host.messages if "error" in m], "Tahu could not decode them all"

    # Every payload: Tahu and the hand-written decoder agree on every field of every metric.
    pairs = pair(host, seen)
    assert len(pairs) > 10
    types: dict[int, str] = {}  # alias -> datatype, from the births
    for tahu, _ in pairs:
        if "BIRTH" in tahu["topic"]:
            types |= {
                int(m["alias"]): m["type"] for m in tahu["payload"]["metrics"] if "alias" in m
            }
    for tahu, mine in pairs:
        decoded = mine
        payload, raw = tahu["payload"], tahu["raw"]
        assert int(payload["timestamp"]) == decoded.timestamp  # tck-id-payloads-*-timestamp
        assert (int(payload["seq"]) if "seq" in payload else None) == decoded.seq
        metrics = payload.get("metrics", [])
        assert len(metrics) == len(decoded.metrics)
        for one, raw_one, my_one in zip(
            metrics, raw.get("metrics", []), decoded.metrics, strict=True
        ):
            datatype = one.get("type") or types[int(one["alias"])]
            assert_same_metric(one, raw_one, my_one, datatype)

    assert_node_messages(host)
    assert_births(host)
    assert_data_and_death(host)
    assert_seq_never_skips(seen)


def assert_node_messages(host: TahuHost) -> None:
    """NBIRTH: seq 0, bdSeq Int64, ``Node Control/Rebirth`` false, no alias; the NDEATH."""
    nbirth = host.on(f"{NODE}/NBIRTH/{EDGE}")[0]["payload"]
    assert int(nbirth["seq"]) == 0
    node = {m["name"]: m for m in nbirth["metrics"]}
    assert node["bdSeq"]["type"] == "Int64"
    assert node["Node Control/Rebirth"] == {
        "name": "Node Control/Rebirth",
        "type": "Boolean",
        "value": False,
        "timestamp": node["Node Control/Rebirth"]["timestamp"],
    }
    ndeath = host.on(f"{NODE}/NDEATH/{EDGE}")[-1]["payload"]
    assert "seq" not in ndeath  # tck-id-payloads-ndeath-seq
    assert [m["name"] for m in ndeath["metrics"]] == ["bdSeq"]  # tck-id-topics-ndeath-payload
    assert ndeath["metrics"][0]["value"] == node["bdSeq"]["value"]


def assert_births(host: TahuHost) -> None:
    """Every DBIRTH metric complete; one DBIRTH of the Reiss with its unit; enum labels."""
    aliases: set[int] = set()
    for device in ("aeration", "basin"):
        birth = host.on(f"{NODE}/DBIRTH/{EDGE}/{device}")[0]["payload"]
        for metric in birth["metrics"]:
            assert {"name", "alias", "type", "timestamp"} <= set(metric), metric
            assert metric["properties"]["Quality"]["value"] in {0, 192, 500}
        device_aliases = {int(m["alias"]) for m in birth["metrics"]}
        assert not aliases & device_aliases  # tck-id-payloads-alias-uniqueness
        aliases |= device_aliases
    # One DBIRTH of the Reiss, with the unit its unit register names.
    basin = host.on(f"{NODE}/DBIRTH/{EDGE}/basin")
    assert len(basin) == 1
    concentration = {m["name"]: m for m in basin[0]["payload"]["metrics"]}["concentration"]
    assert concentration["properties"]["engUnit"]["value"] == "ppm"
    # An enumeration's label beside its code, as the profile names it.
    aeration = {
        m["name"]: m for m in host.on(f"{NODE}/DBIRTH/{EDGE}/aeration")[0]["payload"]["metrics"]
    }
    unit = get_profile("jumo-digiline-odo-s10").point("oxygen_unit")
    code = aeration["oxygen_unit"]["value"]
    assert aeration["oxygen_unit/label"]["type"] == "String"
    assert aeration["oxygen_unit/label"]["value"] == unit.format.enum[code]


def assert_data_and_death(host: TahuHost) -> None:
    """DDATA by alias only; a DDEATH, then nothing until a DBIRTH with values."""
    for message in host.on(f"{NODE}/DDATA/{EDGE}/aeration"):
        for metric in message["payload"]["metrics"]:
            assert "name" not in metric
            assert "type" not in metric  # no datatype sent
            assert "alias" in metric
            assert "timestamp" in metric

    # The device's death: seq and timestamp, no metric; then dead until it answers again,
    # and born again with values, not nulls.
    kinds = [m["topic"].split("/")[2] for m in host.messages if m["topic"].endswith("/aeration")]
    death = kinds.index("DDEATH")
    assert kinds[death + 1] == "DBIRTH", kinds[death:]
    ddeath = host.on(f"{NODE}/DDEATH/{EDGE}/aeration")[0]["payload"]
    assert "seq" in ddeath
    assert "timestamp" in ddeath
    assert not ddeath.get("metrics")
    reborn = {
        m["name"]: m for m in host.on(f"{NODE}/DBIRTH/{EDGE}/aeration")[1]["payload"]["metrics"]
    }
    assert reborn["temperature"]["value"] is not None
    assert reborn["temperature"]["properties"]["Quality"]["value"] == 192


async def test_tck_id_operational_behavior_data_commands_ncmd_and_dcmd_encoded_by_tahu(
    tmp_path: Path, broker: Broker
) -> None:
    """A rebirth and a write, each encoded by Tahu's ``encodePayload`` as a host sends them."""
    configuration = ", device_groups: {aeration: [process, status, configuration]}"
    async with (
        simulated(tmp_path) as server,
        tahu_host(broker.port) as host,
        gateway(sp_yaml(tmp_path, broker.port, sparkplug=configuration)),
        aiomqtt.Client("127.0.0.1", broker.port, identifier="host") as client,
    ):
        await host.wait_until(lambda: host.on(f"{NODE}/DBIRTH/{EDGE}/aeration"))
        await host.wait_until(lambda: host.on(f"{NODE}/DBIRTH/{EDGE}/basin"))
        rebirth = {
            "timestamp": 1,
            "metrics": [{"name": "Node Control/Rebirth", "type": "Boolean", "value": True}],
        }
        await client.publish(f"{NODE}/NCMD/{EDGE}", tahu_encode(rebirth), qos=0)
        await host.wait_until(lambda: len(host.on(f"{NODE}/NBIRTH/{EDGE}")) == 2)
        await host.wait_until(lambda: len(host.on(f"{NODE}/DBIRTH/{EDGE}/aeration")) == 2)
        birth = {
            m["name"]: m for m in host.on(f"{NODE}/DBIRTH/{EDGE}/aeration")[1]["payload"]["metrics"]
        }
        alias = int(birth["compensation_temperature"]["alias"])
        write = {
            "timestamp": 2,
            "metrics": [{"alias": alias, "type": "Float", "value": 21.5}],
        }
        await client.publish(f"{NODE}/DCMD/{EDGE}/aeration", tahu_encode(write), qos=0)
        result = int(birth["Write/Result"]["alias"])

        def written() -> list[dict[str, Any]]:
            return [
                json.loads(str(raw_value(m, "String")))
                for d in host.on(f"{NODE}/DDATA/{EDGE}/aeration")
                for m in d["raw"]["metrics"]
                if int(m["alias"]) == result
            ]

        await host.wait_until(written)
    assert written()[0]["status"] == "ok"
    assert written()[0]["value"] == 21.5
    assert server.bus.devices[1].write_log, "nothing reached the sensor"
    read_back = [
        raw_value(m, "Float")
        for d in host.on(f"{NODE}/DDATA/{EDGE}/aeration")
        for m in d["raw"]["metrics"]
        if int(m["alias"]) == alias
    ]
    assert read_back[-1] == 21.5
