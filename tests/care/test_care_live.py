"""Sensor care on real parts: the simulator on a pseudo-terminal, mosquitto, ``/metrics``.

A tecLine Cl2 (nominal slope 22 nA/ppm, annex 7.5.1 of jumo-tecline.modbus.en.txt) whose
history holds five weekly calibrations falling from 68 % to 44 % of nominal: care says it
is due, with a projection, on MQTT (retained, with Home Assistant entities), in the
metrics (which promtool accepts) and on ``/care``. Then another master calibrates it
through the shared bus, as the vendor's software would: care notices it at once, long
before the next diagnostics read.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
import urllib.request
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Any

import pytest
from pymodbus.client import AsyncModbusTcpClient

from gateway.app import run
from gateway.config import parse_config
from gateway.line.engine.devices import DeviceTarget
from gateway.profiles import PollGroup, get_profile
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire import codec, encoding
from tests.app.test_app import scrape
from tests.mqtt_broker import Broker, free_port, recording
from tests.rigs import link_rig, run_gateway, simulate_process

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line]

PROMTOOL = shutil.which("promtool") or "/usr/bin/promtool"
NOMINAL = 22.0
RATIOS = [0.44, 0.50, 0.56, 0.62, 0.68]  # history entries 0 (newest) to 4, a week apart
CARE_FAMILIES = (
    "gateway_care_state",
    "gateway_last_calibration_timestamp_seconds",
    "gateway_calibration_due_timestamp_seconds",
    "gateway_slope_ratio",
    "gateway_slope_limit_projected_timestamp_seconds",
    "gateway_cap_usage_ratio",
)
CARE_ENTITIES = {"care_state", "calibration_due", "calibration_due_date", "slope_ratio"}
FLOAT = codec.Format(dtype=codec.DataType.FLOAT32, count=2)
STAMP = codec.Format(dtype=codec.DataType.YYMMDDHHMM, count=2)


def _history(newest: datetime) -> dict[str, Any]:
    """The simulated sensor's calibration records, stamps in local wall-clock time."""
    values: dict[str, Any] = {}
    for index, ratio in enumerate(RATIOS):
        values |= {
            f"history_{index}_x_zero": 0.0,
            f"history_{index}_x_span": ratio * NOMINAL,
            f"history_{index}_stamp": newest - timedelta(days=7 * index),
        }
    return values | {"x_zero": 0.0, "x_span": RATIOS[0] * NOMINAL, "calibration_stamp": newest}


async def _care(seen: Any, topic: str, *, within_s: float = 20.0) -> dict[str, Any]:
    """The first care document on ``topic``."""
    await seen.wait_for(topic, within_s=within_s)
    document: dict[str, Any] = json.loads(seen.on(topic)[-1])
    return document


async def _care_where(
    seen: Any,
    topic: str,
    *,
    last_calibration: str,
    within_s: float = 20.0,
) -> dict[str, Any]:
    """The first care document on ``topic`` whose last calibration is the one given."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + within_s
    while loop.time() < deadline:
        for payload in seen.on(topic):
            document: dict[str, Any] = json.loads(payload)
            if document["last_calibration"] == last_calibration:
                return document
        await asyncio.sleep(0.05)
    raise AssertionError(f"no care document with last_calibration {last_calibration}")


def _fetch(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=5) as reply:  # noqa: S310 - a local test server
        return json.loads(reply.read())


def _promtool_check(exposition: str) -> subprocess.CompletedProcess[str]:
    """``promtool check metrics`` on an exposition: its lint of names, types and units."""
    return subprocess.run(
        [PROMTOOL, "check", "metrics"],
        input=exposition,
        capture_output=True,
        text=True,
        check=False,
    )


def _families_text(port: int) -> str:
    """The exposition of the care families only, as Prometheus scrapes it."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as reply:
        lines = reply.read().decode().splitlines()
    keep = [
        line
        for line in lines
        if any(
            line.startswith((f"# HELP {name} ", f"# TYPE {name} ", f"{name}{{", f"{name} "))
            for name in CARE_FAMILIES
        )
    ]
    return "\n".join(keep) + "\n"


@pytest.mark.broker
async def test_a_falling_tecline_is_due_with_a_projection_and_a_calibration_by_another_master_shows_at_once(  # noqa: PLR0915
    tmp_path: Path, broker: Broker
) -> None:
    # Whole minutes, local and zone-less as the sensor keeps them; 9 days ago: overdue.
    local_now = datetime.now().astimezone().replace(second=0, microsecond=0)
    newest = (local_now - timedelta(days=9)).replace(tzinfo=None)
    sensor = {
        "profile": "jumo-tecline-cl2",
        "address": 20,
        "animate": False,
        "values": _history(newest),
    }
    server = SimulatorServer(build_bus(parse_settings({"devices": [sensor]})))
    port = tmp_path / "ttySIM"
    server.open_pty(port)
    metrics_port, modbus_port = free_port(), free_port()
    config = parse_config(
        f"buses:\n  - {{name: line1, port: {port}}}\n"
        "devices:\n"
        "  - {name: pool, bus: line1, address: 20, profile: jumo-tecline-cl2,"
        " poll_interval: 0.5, diagnostics_interval: 30}\n"
        f"mqtt: {{host: 127.0.0.1, port: {broker.port}, base_topic: gw,"
        " discovery: {enabled: true}}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics_port}}}\n"
        "shared_bus:\n"
        f"  listen: [{{host: 127.0.0.1, port: {modbus_port}}}]\n"
        "  clients:\n"
        "    - name: service_laptop\n"
        "      networks: [127.0.0.1/32]\n"
        "      writes: [{device: pool, registers: ['0x0206-0x020B']}]\n"
        f"state_dir: {tmp_path / 'state'}\n",
        environ={},
    )
    stop = asyncio.Event()
    try:
        async with recording(broker.port, "#") as seen:
            task = asyncio.create_task(run(config, [], stop=stop))
            before = await _care(seen, "gw/pool/care")
            metrics = await asyncio.to_thread(scrape, metrics_port)
            exposition = await asyncio.to_thread(_families_text, metrics_port)
            served = await asyncio.to_thread(_fetch, f"http://127.0.0.1:{metrics_port}/care")
            # The vendor's software calibrates: X_Zero 0, X_Span 90 % of nominal, then the
            # stamp, which activates it (annex 7.2), written as one master writes them.
            stamp = local_now.replace(tzinfo=None)
            span = 0.9 * NOMINAL
            client = AsyncModbusTcpClient("127.0.0.1", port=modbus_port, timeout=3)
            await client.connect()
            registers = [*encoding.encode(FLOAT, 0.0), *encoding.encode(FLOAT, span)]
            wrote_values = await client.write_registers(0x0206, registers, device_id=20)
            written_at = asyncio.get_running_loop().time()
            wrote_stamp = await client.write_registers(
                0x020A, list(encoding.encode(STAMP, stamp)), device_id=20
            )
            client.close()
            # Between the two writes a document may say the new values are not active yet;
            # the one that counts carries the new calibration's stamp.
            stamped = stamp.astimezone().astimezone(UTC).isoformat(timespec="seconds")
            after = await _care_where(seen, "gw/pool/care", last_calibration=stamped)
            noticed_s = asyncio.get_running_loop().time() - written_at
            stop.set()
            await asyncio.wait_for(task, timeout=15)
        async with recording(broker.port, "gw/pool/care", name="late") as late:
            await late.wait_for("gw/pool/care")  # what a subscriber gets later: retained
    finally:
        await server.close()

    # Before: hand-computed from the history.
    last = newest.astimezone()
    assert before["state"] == "due"
    assert before["last_calibration"] == last.astimezone(UTC).isoformat(timespec="seconds")
    assert before["due"] == (last + timedelta(days=7)).astimezone(UTC).isoformat(timespec="seconds")
    assert before["slope_ratio"] == pytest.approx(0.44)
    assert before["slope_limit"] == 0.3
    assert before["slope_trend"]["per_week"] == pytest.approx(-0.06, abs=1e-6)
    assert before["slope_trend"]["points"] == 5
    # 0.14 left to 30 % at 0.06 a week: 2 1/3 weeks after the newest calibration.
    crossing = last + timedelta(weeks=0.14 / 0.06)
    projected = datetime.fromisoformat(before["projection"]["at"])
    assert abs((projected - crossing).total_seconds()) < 60
    assert before["projection"]["confidence"] == "high"
    assert any("plan membrane cap and electrolyte" in r for r in before["reasons"])
    assert len(before["records"]["history"]) == 5
    assert [(m.retain, json.loads(m.payload)) for m in late.messages] == [(True, after)]
    # Home Assistant: the care entities, diagnostic, reading the care document.
    configs = {
        m.topic.split("/")[1] + "/" + m.topic.split("/")[3]: json.loads(m.payload)
        for m in seen.messages
        if m.topic.startswith("homeassistant/") and m.topic.split("/")[3] in CARE_ENTITIES
    }
    assert set(configs) == {
        "sensor/care_state",
        "binary_sensor/calibration_due",
        "sensor/calibration_due_date",
        "sensor/slope_ratio",
    }
    assert {c["state_topic"] for c in configs.values()} == {"gw/pool/care"}
    assert {c["entity_category"] for c in configs.values()} == {"diagnostic"}
    assert configs["sensor/calibration_due_date"]["device_class"] == "timestamp"

    # The metrics: a StateSet and the dates, the same figures.
    labels = {"bus": "line1", "device": "pool", "profile": "jumo-tecline-cl2"}
    states = {lab["state"]: value for lab, value in metrics["gateway_care_state"]}
    assert states == {"ok": 0.0, "due_soon": 0.0, "due": 1.0, "unknown": 0.0, "maintenance": 0.0}
    ((slope_labels, slope),) = metrics["gateway_slope_ratio"]
    assert slope_labels == labels
    assert slope == pytest.approx(0.44)
    assert metrics["gateway_last_calibration_timestamp_seconds"] == [(labels, last.timestamp())]
    assert metrics["gateway_calibration_due_timestamp_seconds"] == [
        (labels, (last + timedelta(days=7)).timestamp())
    ]
    (projection_sample,) = metrics["gateway_slope_limit_projected_timestamp_seconds"]
    assert projection_sample[1] == pytest.approx(projected.timestamp(), abs=1)
    assert "gateway_cap_usage_ratio" not in metrics  # a tecLine has no cap counter
    checked = await asyncio.to_thread(_promtool_check, exposition)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert checked.stdout + checked.stderr == ""
    assert [doc["device"] for doc in served] == ["pool"]
    assert served[0]["state"] == "due"

    # After the other master's calibration: noticed at once, not at the next 30 s read.
    assert not wrote_values.isError()
    assert not wrote_stamp.isError()
    assert noticed_s < 10
    assert after["state"] == "ok"
    assert after["slope_ratio"] == pytest.approx(0.9)
    assert after["last_calibration"] == stamped  # the stamp written, read in local time
    assert after["records"]["history"][1]["x_span"] == pytest.approx(0.44 * NOMINAL, rel=1e-6)
    # A rise to 90 % is a service: the trend starts again, from one calibration.
    assert after["projection"] is None
    assert after["projection_note"].startswith("no projection: 1 calibration")


async def test_the_gateways_own_calibration_write_makes_the_history_read_again_at_once(
    tmp_path: Path,
) -> None:
    """Writing the date stamp (annex 7.2) moves the history: the worker reads 0x0206-0x022D
    again at once, not at the next diagnostics read a minute later."""
    profile = get_profile("jumo-tecline-cl2")
    intervals: dict[str, float | None] = {
        p.name: 60.0 for p in profile.points if p.group is PollGroup.DIAGNOSTICS
    }
    intervals["concentration"] = 0.5
    polled = DeviceTarget(name="pool", address=20, profile=profile, intervals=intervals)
    sensor = {"profile": "jumo-tecline-cl2", "address": 20, "animate": False}
    stamp = datetime(2026, 11, 27, 9, 30)
    async with link_rig(tmp_path, [sensor], [polled], poll=True) as lr:
        link = lr.links["pool"]
        for _ in range(100):  # the first diagnostics read, then none for a minute
            if lr.rig.sink.good("pool", "history_0_stamp"):
                break
            await asyncio.sleep(0.1)
        first = len(lr.rig.sink.good("pool", "history_0_stamp"))
        await link.write(profile.point("x_span"), 0.9 * NOMINAL)
        await link.write(profile.point("calibration_stamp"), stamp)
        for _ in range(50):
            if len(lr.rig.sink.good("pool", "history_0_stamp")) > first:
                break
            await asyncio.sleep(0.1)
        read_again = lr.rig.sink.good("pool", "history_0_stamp")[first:]
        spans = lr.rig.sink.good("pool", "history_0_x_span")
    assert first == 1
    assert [s.value for s in read_again] == [stamp]
    assert spans[-1].value == pytest.approx(0.9 * NOMINAL)


AGED_PLANT = """\
line: {baudrate: 19200, parity: E, stopbits: 1}
devices:
  - profile: jumo-tecline-cl2
    address: 20
    animate: false
    aging: {weeks_in_service: 8, last_calibration_days: 9, slope_start: 0.8, slope_decay_per_week: 0.06}
  - profile: jumo-digiline-odo-s10
    address: 1
    animate: false
    aging: {cap_replacement_recommended: true}
"""


def test_gateway_care_reads_the_sensors_when_no_gateway_runs(tmp_path: Path) -> None:
    """`gateway care --json` with nothing on the metrics port: it reads the records itself.

    The aged tecLine: calibrated weekly for 8 weeks from 80 % of nominal, 6 % less a week,
    the last 9 days ago: 0.80 - 6 x 0.06 = 0.44 of nominal, overdue; the S10 asks for a cap.
    """
    with simulate_process(tmp_path, AGED_PLANT) as (port, _):
        config = tmp_path / "plant.yaml"
        config.write_text(
            f"buses: [{{name: line1, port: {port}, baudrate: 19200, parity: E}}]\n"
            "devices:\n"
            "  - {name: pool, bus: line1, address: 20, profile: jumo-tecline-cl2}\n"
            "  - {name: aeration, bus: line1, address: 1, profile: jumo-digiline-odo-s10}\n"
            f"prometheus: {{host: 127.0.0.1, port: {free_port()}}}\n",
            encoding="utf-8",
        )
        result = run_gateway("care", "--config", str(config), "--json", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    documents = json.loads(result.stdout)
    assert [(d["device"], d["state"]) for d in documents] == [
        ("aeration", "maintenance"),
        ("pool", "due"),
    ]
    pool = documents[1]
    assert pool["slope_ratio"] == pytest.approx(0.44, abs=1e-4)
    assert pool["slope_trend"]["per_week"] == pytest.approx(-0.06, abs=1e-4)
    assert pool["projection"]["confidence"] == "high"
    assert any("replacing its cap" in reason for reason in documents[0]["reasons"])
