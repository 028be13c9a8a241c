"""A pinned serial number in ``/metrics`` and ``/healthz``: the gateway run from a config.

The whole gateway (``app.run``) polls the simulator over a pseudo-terminal; the metrics are
scraped over HTTP from a started :class:`MetricsServer`, as Prometheus would.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING

import pytest

from gateway.app import run
from gateway.config import parse_config
from gateway.publish.prometheus import MetricsServer
from gateway.shared.state import GatewayState
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from tests.publish.prometheus.test_prometheus import Exposition, fetch, scrape_until
from tests.rigs import ListSink

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line]

S10 = "jumo-digiline-odo-s10"
PINNED = "S100000001"  # the serial the simulated S10 at address 1 reports
SWAPPED_IN = "S100000042"  # the other line's S10, behind the swapped adapter
DEVICE = {"bus": "line1", "device": "tank1_oxygen"}


def mismatch(metrics: Exposition) -> float | None:
    found = metrics.find("gateway_device_identity_mismatch", **DEVICE)
    return found[0][1] if found else None


async def test_a_mismatch_shows_in_metrics_and_healthz_and_clears(tmp_path: Path) -> None:
    simulator = SimulatorServer(
        build_bus(
            parse_settings(
                {
                    "devices": [
                        {
                            "profile": S10,
                            "address": 1,
                            "animate": False,
                            "values": {"serial_number": SWAPPED_IN, "temperature": 20.25},
                        }
                    ]
                }
            )
        )
    )
    port = tmp_path / "ttySIM"
    simulator.open_pty(port)
    config = parse_config(
        "buses:\n"
        f"  - {{name: line1, port: {port}}}\n"
        "devices:\n"
        "  - name: tank1_oxygen\n"
        "    bus: line1\n"
        "    address: 1\n"
        f"    profile: {S10}\n"
        "    poll_interval: 0.5\n"
        f'    serial_number: "{PINNED}"\n'
        "mqtt: {enabled: false}\n"
        "prometheus: {enabled: false}\n",  # served below, on a free port
        environ={},
    )
    state = GatewayState()
    sink = ListSink()
    stop = asyncio.Event()
    gateway = asyncio.create_task(run(config, [sink], stop=stop, state=state), name="gateway")
    server = MetricsServer(state, host="127.0.0.1", port=0)
    server.start()
    try:
        metrics = await scrape_until(server, lambda m: mismatch(m) == 1)
        assert mismatch(metrics) == 1
        assert metrics.value("gateway_device_online", **DEVICE, profile=S10) == 0
        # No value of the other sensor under this device's name, and no serial as a label.
        assert not metrics.find("gateway_temperature_celsius", **DEVICE)
        assert metrics.labels("gateway_device_info", **DEVICE)["serial"] == ""
        assert SWAPPED_IN not in metrics.text

        reply = await asyncio.to_thread(fetch, f"http://127.0.0.1:{server.port}/healthz")
        assert reply.status == 200  # a sensor's identity is the device's problem
        body = reply.json()
        assert body["identity"] == [
            {
                "bus": "line1",
                "device": "tank1_oxygen",
                "address": 1,
                "identity": "mismatch",
                "expected_serial": PINNED,
                "answered_serial": SWAPPED_IN,
                "action": (
                    "check which adapter is which: give each bus its /dev/serial/by-id/... "
                    "name as port (ls -l /dev/serial/by-id); if the sensor was replaced on "
                    "purpose, set the device's serial_number to the serial that answered"
                ),
            }
        ]
        assert body["buses"]["line1"]["devices_online"] == 0
        info = state.snapshot().devices["line1", "tank1_oxygen"]
        assert (info.online, info.reason) == (
            False,
            f"not the configured sensor: serial number {SWAPPED_IN} answered, {PINNED} is pinned",
        )
        assert sink.samples == []

        # The adapters swapped back: the pinned sensor answers at the address again.
        simulator.bus.devices[1].hold("serial_number", PINNED)
        metrics = await scrape_until(
            server,
            lambda m: mismatch(m) == 0 and bool(m.find("gateway_temperature_celsius", **DEVICE)),
        )
        assert mismatch(metrics) == 0
        assert metrics.value("gateway_temperature_celsius", **DEVICE, profile=S10) == 20.25
        assert metrics.value("gateway_device_online", **DEVICE, profile=S10) == 1
        assert metrics.labels("gateway_device_info", **DEVICE)["serial"] == PINNED
        body = (await asyncio.to_thread(fetch, f"http://127.0.0.1:{server.port}/healthz")).json()
        assert body["identity"] == []
        assert {s.device for s in sink.samples} == {"tank1_oxygen"}
        assert [s.value for s in sink.samples if s.point == "serial_number" and s.good] == [PINNED]
    finally:
        server.stop()
        stop.set()
        await asyncio.wait_for(gateway, timeout=10)
        await simulator.close()
