"""Sparkplug B: the gateway as an edge node, against a real mosquitto and the simulator.

Every payload is read with the hand-written decoder of ``tests/sparkplug_decoder.py``, not
with the protobuf library the product encodes with.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import signal
import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import aiomqtt
import pytest

from gateway.profiles import get_profile
from gateway.publish.prometheus import GatewayCollector, health_report
from gateway.records import RecordStore, records_path
from tests.mqtt_broker import Broker, subscribed
from tests.publish.test_mqtt import gateway, simulated
from tests.sparkplug_decoder import DecodedPayload, command, decode

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Iterator
    from pathlib import Path

    from gateway.shared.state import GatewayState
    from gateway.simulator import SimulatorServer

pytestmark = [pytest.mark.line, pytest.mark.broker]

GROUP, EDGE = "plant", "gw1"
NODE = f"spBv1.0/{GROUP}"
SPARKPLUG_TYPE = {
    "float32": "Float",
    "uint8": "UInt8",
    "int8": "Int8",
    "bool": "Boolean",
    "uint16": "UInt16",
    "int16": "Int16",
    "uint32": "UInt32",
    "int32": "Int32",
    "enum": "UInt16",
    "enum32": "UInt32",
    "bitfield": "UInt16",
    "bitfield32": "UInt32",
    "string": "String",
    "yymmddhhmm": "DateTime",
    "datetime": "DateTime",
}


@dataclass
class Seen:
    topic: str
    payload: bytes
    at: float = field(default_factory=time.monotonic)

    @property
    def kind(self) -> str:
        parts = self.topic.split("/")
        return "STATE" if parts[1] == "STATE" else parts[2]

    def decoded(self) -> DecodedPayload:
        return decode(self.payload)


@dataclass
class SpRecorder:
    messages: list[Seen] = field(default_factory=list)

    def on(self, topic: str) -> list[DecodedPayload]:
        return [m.decoded() for m in self.messages if m.topic == topic]

    async def wait_for(self, topic: str, count: int = 1, within_s: float = 15.0) -> None:
        deadline = asyncio.get_running_loop().time() + within_s
        while asyncio.get_running_loop().time() < deadline:
            if len(self.on(topic)) >= count:
                return
            await asyncio.sleep(0.05)
        seen = [m.topic for m in self.messages[-5:]]
        raise AssertionError(f"not {count} on {topic}; last seen: {seen}")

    async def wait_until(self, check: Any, within_s: float = 15.0) -> None:
        deadline = asyncio.get_running_loop().time() + within_s
        while asyncio.get_running_loop().time() < deadline:
            if check():
                return
            await asyncio.sleep(0.05)
        raise AssertionError(f"never true; last seen: {[m.topic for m in self.messages[-5:]]}")

    def sequenced(self) -> list[Seen]:
        """Every message of the node that carries a seq (all but NDEATH and STATE)."""
        return [m for m in self.messages if m.kind not in {"NDEATH", "NCMD", "DCMD", "STATE"}]


@contextlib.asynccontextmanager
async def sp_recording(port: int) -> AsyncIterator[SpRecorder]:
    recorder = SpRecorder()

    def keep(message: aiomqtt.Message) -> None:
        payload = message.payload
        assert isinstance(payload, bytes)
        recorder.messages.append(Seen(str(message.topic), payload))

    async with subscribed(port, "spBv1.0/#", keep, name="sp-host"):
        yield recorder


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    """mosquitto that also queues QoS 0 for a persistent subscriber while it reconnects.

    Sparkplug publishes with QoS 0; without this a birth sent right after a broker restart,
    before the recorder is back, would be lost to the recorder (not to the test's point).
    """
    directory = tmp_path / "broker"
    directory.mkdir()
    running = Broker(directory, extra=["queue_qos0_messages true"])
    running.start()
    yield running
    running.stop()


def sp_yaml(tmp_path: Path, port: int, *, sparkplug: str = "", mqtt: str = "") -> str:
    return (
        f"buses:\n  - {{name: line1, port: {tmp_path / 'ttySIM'}}}\n"
        "devices:\n"
        "  - {name: aeration, bus: line1, address: 1, profile: jumo-digiline-odo-s10,"
        " poll_interval: 0.3, offline_after: 2}\n"
        "  - {name: basin, bus: line1, address: 10, profile: reiss-m0c, poll_interval: 0.3}\n"
        f"mqtt: {{host: 127.0.0.1, port: {port}, reconnect_max_s: 1{mqtt}}}\n"
        f"sparkplug: {{enabled: true, group_id: {GROUP}, edge_node_id: {EDGE}{sparkplug}}}\n"
        "prometheus: {enabled: false}\n"
        f"state_dir: {tmp_path / 'state'}\n"
    )


def assert_seq_never_skips(seen: SpRecorder) -> None:
    """Every NBIRTH starts at 0; every message after it takes the next seq, mod 256."""
    expected: int | None = None
    for message in seen.sequenced():
        seq = message.decoded().seq
        assert seq is not None, message.topic
        if message.kind == "NBIRTH":
            assert seq == 0
        else:
            assert seq == expected, (message.topic, seq, expected)
        expected = (seq + 1) % 256


def polled_points(profile_id: str) -> dict[str, Any]:
    """The points a host gets by default (process values and status), by name."""
    return {
        p.name: p
        for p in get_profile(profile_id).points
        if not p.view and p.group.value in {"process", "status"}
    }


async def test_births_name_every_point_with_type_unit_and_alias(
    tmp_path: Path, broker: Broker
) -> None:
    async with (
        simulated(tmp_path),
        sp_recording(broker.port) as seen,
        gateway(sp_yaml(tmp_path, broker.port)),
    ):
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/aeration")
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/basin")
        await asyncio.sleep(2.0)  # several cycles: a second DBIRTH would be out by now
    # The unit of a concentration is in a register of its own: the birth waits for it, so
    # each device has one DBIRTH, with its units.
    assert len(seen.on(f"{NODE}/DBIRTH/{EDGE}/basin")) == 1
    assert len(seen.on(f"{NODE}/DBIRTH/{EDGE}/aeration")) == 1
    nbirth = seen.on(f"{NODE}/NBIRTH/{EDGE}")[0]
    node = nbirth.by_name()
    assert node["bdSeq"].datatype == "Int64"
    assert isinstance(node["bdSeq"].value, int)
    assert node["Node Control/Rebirth"].datatype == "Boolean"
    assert node["Node Control/Rebirth"].value is False
    assert node["Node Control/Rebirth"].alias is None
    # A clean stop publishes the NDEATH with the NBIRTH's bdSeq.
    ndeath = seen.on(f"{NODE}/NDEATH/{EDGE}")[-1]
    assert ndeath.by_name()["bdSeq"].value == node["bdSeq"].value
    assert ndeath.seq is None

    aliases: set[int] = set()
    for device, profile_id in (("aeration", "jumo-digiline-odo-s10"), ("basin", "reiss-m0c")):
        birth = seen.on(f"{NODE}/DBIRTH/{EDGE}/{device}")[-1]
        metrics = birth.by_name()
        points = polled_points(profile_id)
        assert {n.split("/")[0] for n in metrics} == {*points, "Write"}  # process, status
        assert "Write/Result" in metrics
        for name, point in points.items():
            metric = metrics[name]
            assert metric.datatype == SPARKPLUG_TYPE[point.format.dtype.value], name
            if point.unit:
                assert metric.properties["engUnit"] == point.unit, name
            assert metric.properties["readOnly"] is (not point.writable), name
            if point.description:
                assert metric.properties["description"] == point.description
            assert metric.properties["Quality"] in {0, 192, 500}
        for bit in (
            get_profile(profile_id).point("status").format.bits.values()
            if ("status" in points)
            else ()
        ):
            assert metrics[f"status/{bit}"].datatype == "Boolean"
        device_aliases = [m.alias for m in birth.metrics]
        assert None not in device_aliases
        assert len(set(device_aliases)) == len(device_aliases)
        assert not aliases & set(device_aliases)  # unique across the edge node
        aliases |= {a for a in device_aliases if a is not None}
    aeration = seen.on(f"{NODE}/DBIRTH/{EDGE}/aeration")[0].by_name()
    assert aeration["temperature"].value == 20.25
    assert aeration["temperature"].properties["Quality"] == 192
    # The fault float the sensor sends (overrange) is a null with a bad quality.
    assert aeration["oxygen"].is_null
    assert aeration["oxygen"].value is None
    assert aeration["oxygen"].properties["Quality"] == 0
    assert aeration["oxygen"].properties["fault"] == "overrange"
    assert aeration["status/cap_missing"].value is True
    basin = seen.on(f"{NODE}/DBIRTH/{EDGE}/basin")[-1].by_name()
    assert abs(float(basin["concentration"].value) - 0.168) < 1e-6  # type: ignore[arg-type]
    assert basin["concentration"].properties["engUnit"] == "ppm"
    assert_seq_never_skips(seen)


async def test_data_by_exception_with_a_deadband(tmp_path: Path, broker: Broker) -> None:
    sensors = [
        {"profile": "jumo-digiline-odo-s10", "address": 1, "animate": True},
        {"profile": "reiss-m0c", "address": 10, "animate": True},
    ]
    deadbands = ", deadbands: {aeration: {temperature: 1000.0}}"
    async with (
        simulated(tmp_path, sensors),
        sp_recording(broker.port) as seen,
        gateway(sp_yaml(tmp_path, broker.port, sparkplug=deadbands)),
    ):
        await seen.wait_for(f"{NODE}/DDATA/{EDGE}/aeration", count=4)
    birth = seen.on(f"{NODE}/DBIRTH/{EDGE}/aeration")[0]
    alias = {m.name: m.alias for m in birth.metrics}
    data = seen.on(f"{NODE}/DDATA/{EDGE}/aeration")
    reported = [a for d in data for m in d.metrics if (a := m.alias) is not None]
    # The animated temperature moves, but never by 1000 °C: no DDATA carries it ...
    assert alias["temperature"] not in reported
    # ... while the oxygen (no deadband) moves and is reported, by alias, without name.
    assert alias["oxygen"] in reported
    assert all(m.name is None and m.datatype is None for d in data for m in d.metrics)
    # Report by exception: a metric that did not change is not repeated.
    for d in data:
        assert alias["status"] not in {m.alias for m in d.metrics}
    assert_seq_never_skips(seen)


async def test_rebirth_on_ncmd_and_a_bad_ncmd_is_refused(
    tmp_path: Path, broker: Broker, caplog: pytest.LogCaptureFixture
) -> None:
    state_holder: list[GatewayState] = []
    async with (
        simulated(tmp_path),
        sp_recording(broker.port) as seen,
        gateway(sp_yaml(tmp_path, broker.port)) as state,
        aiomqtt.Client("127.0.0.1", broker.port, identifier="host") as host,
    ):
        state_holder.append(state)
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/basin")
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/aeration")
        ncmd = f"{NODE}/NCMD/{EDGE}"
        with caplog.at_level(logging.WARNING):
            await host.publish(ncmd, b"\x12\x05garbage", qos=1)
            await host.publish(ncmd, command(("Node Control/Reboot", "Boolean", True)), qos=1)
            await host.publish(ncmd, command(("Node Control/Rebirth", "Float", 1.0)), qos=1)
            await asyncio.sleep(0.5)
        assert len(seen.on(f"{NODE}/NBIRTH/{EDGE}")) == 1  # none of them was a rebirth
        await host.publish(ncmd, command(("Node Control/Rebirth", "Boolean", True)), qos=1)
        await seen.wait_for(f"{NODE}/NBIRTH/{EDGE}", count=2)
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/basin", count=2)
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/aeration", count=2)
    births = seen.on(f"{NODE}/NBIRTH/{EDGE}")
    assert births[1].seq == 0
    assert births[1].by_name()["bdSeq"].value == births[0].by_name()["bdSeq"].value
    refusals = [r for r in caplog.records if "NCMD refused" in r.getMessage()]
    assert len(refusals) == 3, [r.getMessage() for r in refusals]
    assert "no metric 'Node Control/Reboot'" in refusals[1].getMessage()
    assert "is a Boolean, the command says Float" in refusals[2].getMessage()
    assert state_holder[0].writes.outcomes[EDGE, "sparkplug", "rejected"] == 3
    assert_seq_never_skips(seen)


def writes(server: SimulatorServer, address: int) -> list[tuple[int, int, tuple[int, ...]]]:
    return [(w.function, w.address, w.values) for w in server.bus.devices[address].write_log]


async def test_dcmd_writes_through_the_safe_path_and_bad_input_writes_nothing(
    tmp_path: Path, broker: Broker, caplog: pytest.LogCaptureFixture
) -> None:
    dcmd = f"{NODE}/DCMD/{EDGE}/aeration"
    # The S10's compensation values are configuration: the host gets them when asked.
    groups = ", groups: [process, status, configuration]"
    async with (
        simulated(tmp_path) as server,
        sp_recording(broker.port) as seen,
        gateway(sp_yaml(tmp_path, broker.port, sparkplug=groups)) as state,
        aiomqtt.Client("127.0.0.1", broker.port, identifier="host") as host,
    ):
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/aeration")
        birth = seen.on(f"{NODE}/DBIRTH/{EDGE}/aeration")[0].by_name()
        compensation = birth["compensation_temperature"]
        assert compensation.datatype == "Float"
        with caplog.at_level(logging.WARNING):
            bad = [
                b"\xff\xff\xff",  # not protobuf
                command(("no_such_metric", "Float", 1.0)),  # unknown name
                command((999_999, "Float", 1.0)),  # unknown alias
                command(("compensation_temperature", "Boolean", True)),  # wrong datatype
                command(("compensation_temperature", "Int32", 21)),  # wrong datatype
                command(("oxygen", "Float", 8.0)),  # read-only
                command(("analog_output_function/label", "String", "inactive")),  # a label
                # One bad metric refuses the whole payload: the good one is not written.
                command(("compensation_temperature", "Float", 21.5), ("nope", "Float", 1.0)),
            ]
            for payload in bad:
                await host.publish(dcmd, payload, qos=1)
            await asyncio.sleep(1.0)
        assert writes(server, 1) == []
        refused = [
            r.getMessage() for r in caplog.records if "DCMD to aeration refused" in r.getMessage()
        ]
        assert len(refused) == len(bad), refused
        assert "not a Sparkplug B payload" in refused[0]
        assert "no metric 'no_such_metric'" in refused[1]
        assert "no metric of alias 999999" in refused[2]
        assert "is a Float, the command says Boolean" in refused[3]
        assert "read-only" in refused[5]
        assert "'analog_output_function/label' is read-only" in refused[6]
        assert "by its code" in refused[6]
        assert state.writes.outcomes["aeration", "sparkplug", "rejected"] == len(bad)
        scrape = "".join(
            str(s)
            for f in GatewayCollector(state).collect()
            for s in f.samples
            if "writes" in f.name
        )
        assert "sparkplug" in scrape
        assert "rejected" in scrape

        # A good DCMD, by alias, reaches the sensor and is read back.
        await host.publish(
            dcmd, command((compensation.alias or 0, "Float", 21.5), datatype_given=False), qos=1
        )

        def result_seen() -> bool:
            return any(
                (m.alias == birth["Write/Result"].alias)
                for d in seen.on(f"{NODE}/DDATA/{EDGE}/aeration")
                for m in d.metrics
            )

        await seen.wait_until(result_seen)
        assert len(writes(server, 1)) == 1, "nothing reached the simulator"
        # A flash-backed point the device's flash_writes do not name: the flash guard
        # refuses it, the result says so, and nothing is written.
        await host.publish(dcmd, command(("analog_output_fixed_value", "Float", 5.0)), qos=1)
        await seen.wait_until(lambda: len(results_of(seen, birth["Write/Result"].alias)) == 2)
        # One bit of a bit field: that bit written, the others kept as the sensor holds them.
        await host.publish(
            dcmd, command(("compensation_control/salinity_from_ram", "Boolean", True)), qos=1
        )
        await seen.wait_until(lambda: len(results_of(seen, birth["Write/Result"].alias)) == 3)
    results = results_of(seen, birth["Write/Result"].alias)
    assert results[0]["status"] == "ok"
    assert results[0]["metric"] == "compensation_temperature"
    assert results[0]["value"] == 21.5
    assert results[1]["status"] == "error"
    assert "flash-backed point not allowed" in results[1]["reason"]
    assert results[2]["status"] == "ok", results[2]
    assert results[2]["value"]["salinity_from_ram"] is True
    control = get_profile("jumo-digiline-odo-s10").point("compensation_control")
    assert [(a, v) for _, a, v in writes(server, 1)][1:] == [(control.address, (0b010,))]
    read_back = [
        m.value
        for d in seen.on(f"{NODE}/DDATA/{EDGE}/aeration")
        for m in d.metrics
        if m.alias == compensation.alias
    ]
    assert read_back[-1] == 21.5
    assert state.writes.outcomes["aeration", "sparkplug", "ok"] == 2
    assert state.writes.outcomes["aeration", "sparkplug", "rejected"] == len(bad) + 1
    assert_seq_never_skips(seen)
    assert_recorded_as_sparkplugs(tmp_path)


def assert_recorded_as_sparkplugs(tmp_path: Path) -> None:
    """The two writes recorded as the Sparkplug session's (its client id); none refused."""
    store = RecordStore(records_path(tmp_path / "state"), read_only=True)
    recorded = [r.body for r in store.records() if r.kind == "write"]
    assert [b["points"][0]["point"] for b in recorded] == [
        "compensation_temperature",
        "compensation_control",
    ]
    assert {b["actor"]["via"] for b in recorded} == {"sparkplug"}
    assert all(b["actor"]["detail"].startswith("client id spb-") for b in recorded)


def results_of(seen: SpRecorder, alias: int | None) -> list[dict[str, Any]]:
    """The ``Write/Result`` documents of the device ``aeration``, in order."""
    return [
        json.loads(str(m.value))
        for d in seen.on(f"{NODE}/DDATA/{EDGE}/aeration")
        for m in d.metrics
        if m.alias == alias
    ]


async def test_ddeath_when_a_device_goes_offline_and_dbirth_when_it_returns(
    tmp_path: Path, broker: Broker
) -> None:
    async with (
        simulated(tmp_path) as server,
        sp_recording(broker.port) as seen,
        gateway(sp_yaml(tmp_path, broker.port)),
    ):
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/aeration")
        server.bus.silence(1, 4.0, asyncio.get_running_loop().time())
        silent_until = time.monotonic() + 4.0
        await seen.wait_for(f"{NODE}/DDEATH/{EDGE}/aeration")
        assert not seen.on(f"{NODE}/DDEATH/{EDGE}/basin")
        await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/aeration", count=2, within_s=30)
        await asyncio.sleep(1.0)  # a flicker of births would show by now
    mine = [m for m in seen.messages if m.topic.endswith("/aeration")]
    kinds = [m.kind for m in mine]
    death = kinds.index("DDEATH")
    # Dead from its DDEATH until its first answer: nothing, then one DBIRTH, then data.
    assert kinds[death + 1] == "DBIRTH"
    assert kinds.count("DBIRTH") == 2
    assert "DDEATH" not in kinds[death + 1 :]
    assert mine[death + 1].at >= silent_until - 0.05, "born again before it answered"
    reborn = mine[death + 1].decoded().by_name()
    assert reborn["temperature"].value == 20.25
    assert reborn["temperature"].properties["Quality"] == 192
    assert_seq_never_skips(seen)


@pytest.mark.parametrize(
    "birth_delay", ["", ", birth_delay_max_s: 1.5"], ids=["at-once", "delayed"]
)
async def test_primary_host_offline_stores_and_its_return_births_and_forwards(
    tmp_path: Path, broker: Broker, birth_delay: str
) -> None:
    """The host away: data stored; back: births (at once, or after a fleet's random delay,
    data measured meanwhile stored too), then the history in order, then live data."""
    sensors = [
        {"profile": "jumo-digiline-odo-s10", "address": 1, "animate": True},
        {"profile": "reiss-m0c", "address": 10, "animate": True},
    ]
    state_topic = "spBv1.0/STATE/scada"
    async with aiomqtt.Client("127.0.0.1", broker.port, identifier="scada") as host:
        await host.publish(state_topic, b'{"online": true, "timestamp": 1}', qos=1, retain=True)
        async with (
            simulated(tmp_path, sensors),
            sp_recording(broker.port) as seen,
            gateway(
                sp_yaml(tmp_path, broker.port, sparkplug=f", primary_host_id: scada{birth_delay}")
            ) as state,
        ):
            await seen.wait_for(f"{NODE}/DDATA/{EDGE}/aeration")
            assert state.sparkplug.host_online
            assert state.sparkplug.births == 1
            # An offline STATE older than the online one (a stale will of the host): ignored
            # (tck-id-operational-behavior-edge-node-termination-host-offline-timestamp).
            data_before = len(seen.on(f"{NODE}/DDATA/{EDGE}/aeration"))
            await host.publish(
                state_topic, b'{"online": false, "timestamp": 0}', qos=1, retain=True
            )
            await seen.wait_for(f"{NODE}/DDATA/{EDGE}/aeration", count=data_before + 3)
            assert not seen.on(f"{NODE}/NDEATH/{EDGE}")
            assert state.sparkplug.host_online
            await host.publish(
                state_topic, b'{"online": false, "timestamp": 2}', qos=1, retain=True
            )
            await seen.wait_for(f"{NODE}/NDEATH/{EDGE}")
            stored_from = len(seen.messages)
            await asyncio.sleep(2.0)  # the host is away: nothing is published meanwhile
            # ... and the metrics and /healthz say so, with what is stored.
            healthy, health = health_report(state)
            assert healthy
            assert health["sparkplug"]["host_online"] is False  # type: ignore[index]
            assert health["sparkplug"]["queue_depth"] > 0  # type: ignore[index]
            families = {f.name: f for f in GatewayCollector(state).collect()}
            assert families["gateway_sparkplug_host_online"].samples[0].value == 0
            assert families["gateway_sparkplug_queue_depth"].samples[0].value > 0
            assert families["gateway_sparkplug_connected"].samples[0].value == 1
            assert [m.kind for m in seen.messages[stored_from:] if m.kind != "STATE"] == []
            await host.publish(state_topic, b'{"online": true, "timestamp": 3}', qos=1, retain=True)
            await seen.wait_for(f"{NODE}/NBIRTH/{EDGE}", count=2)
            # What the test reads below reaches the recorder after the gateway sent it (the
            # store may be empty by the time the NBIRTH arrives): waited for, each.
            for device in ("aeration", "basin"):
                await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/{device}", count=2)
            await seen.wait_until(
                lambda: any(
                    m.is_historical
                    for d in seen.messages[stored_from:]
                    if d.topic == f"{NODE}/DDATA/{EDGE}/aeration"
                    for m in d.decoded().metrics
                )
            )
            # The first historical DDATA is out; the rest of what was stored follows it.
            await seen.wait_until(lambda: state.sparkplug.queue_depth == 0)  # forwarded
    # (After the stop the store may hold again what was unsent at that moment: kept for
    # the next start, not lost.)
    assert state.sparkplug.births == 2
    births = seen.on(f"{NODE}/NBIRTH/{EDGE}")
    deaths = seen.on(f"{NODE}/NDEATH/{EDGE}")
    first, second = (b.by_name()["bdSeq"].value for b in births[:2])
    assert deaths[0].by_name()["bdSeq"].value == first
    assert second == (int(first) + 1) % 256  # type: ignore[call-overload]
    after = [m for m in seen.messages[stored_from:] if m.kind != "STATE"]
    kinds = [m.kind for m in after]
    assert kinds[0] == "NBIRTH"
    assert kinds[1:3] == ["DBIRTH", "DBIRTH"]
    historical = [
        m for s in after if s.kind == "DDATA" for m in s.decoded().metrics if m.is_historical
    ]
    # What was measured while the host was away, with the time it was measured.
    assert len(historical) >= 2
    assert all(m.timestamp is not None for m in historical)
    assert_seq_never_skips(seen)


def deaths_bd_seq(deaths: list[Any]) -> list[Any]:
    """The ``bdSeq`` each NDEATH carries."""
    return [death.by_name()["bdSeq"].value for death in deaths]


async def test_a_broker_restart_and_a_killed_gateway_give_the_right_ndeath(
    tmp_path: Path, broker: Broker
) -> None:
    config = tmp_path / "gateway.yaml"
    config.write_text(sp_yaml(tmp_path, broker.port), encoding="utf-8")
    async with simulated(tmp_path), sp_recording(broker.port) as seen:
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "gateway",
            "run",
            "--config",
            str(config),
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.DEVNULL,
        )
        try:
            await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/basin", within_s=30)
            broker.stop()
            broker.start()
            await seen.wait_for(f"{NODE}/NBIRTH/{EDGE}", count=2, within_s=30)
            await seen.wait_for(f"{NODE}/DBIRTH/{EDGE}/basin", count=2)
            last_birth = seen.on(f"{NODE}/NBIRTH/{EDGE}")[-1].by_name()["bdSeq"].value
            process.send_signal(signal.SIGKILL)
            await process.wait()
            # The broker sees the socket close and publishes the will (keep-alive aside).
            # The first session's will may come too, and in either order: a broker that
            # stops can publish it to the recorder's persistent session, delivered after
            # the restart. What counts is the will of the session that was killed.
            await seen.wait_until(
                lambda: last_birth in deaths_bd_seq(seen.on(f"{NODE}/NDEATH/{EDGE}")),
                within_s=30,
            )
        finally:
            if process.returncode is None:
                process.kill()
                await process.wait()
    births = seen.on(f"{NODE}/NBIRTH/{EDGE}")
    deaths = deaths_bd_seq(seen.on(f"{NODE}/NDEATH/{EDGE}"))
    assert births[0].by_name()["bdSeq"].value != last_birth  # a new session, a new bdSeq
    assert deaths.count(last_birth) == 1
    assert set(deaths) <= {b.by_name()["bdSeq"].value for b in births}  # each a session's
    assert_seq_never_skips(seen)
