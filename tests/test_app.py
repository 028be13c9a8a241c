"""The running gateway: several buses in parallel, each in its own task, stopped cleanly."""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING

from gateway.app import run
from gateway.config import parse_config
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from tests.rigs import ListSink

if TYPE_CHECKING:
    from pathlib import Path


async def test_two_buses_poll_in_parallel_one_over_tcp(tmp_path: Path) -> None:
    serial_line = SimulatorServer(
        build_bus(
            parse_settings(
                {
                    "devices": [
                        {
                            "profile": "reiss-m0c",
                            "address": 10,
                            "animate": False,
                            "values": {"concentration": 0.168},
                        }
                    ]
                }
            )
        )
    )
    tcp_line = SimulatorServer(
        build_bus(
            parse_settings(
                {
                    "line": {"baudrate": 19200},
                    "devices": [
                        {
                            "profile": "jumo-digiline-odo-s10",
                            "address": 1,
                            "animate": False,
                            "values": {"temperature": 20.25},
                        }
                    ],
                }
            )
        )
    )
    port = tmp_path / "ttyA"
    serial_line.open_pty(port)
    tcp_port = await tcp_line.open_tcp("127.0.0.1", 0)
    config = parse_config(
        f"buses:\n"
        f"  - {{name: basin, port: {port}}}\n"
        f"  - {{name: aeration, port: 'socket://127.0.0.1:{tcp_port}', baudrate: 19200}}\n"
        "devices:\n"
        "  - {name: basin_chlorine, bus: basin, address: 10, profile: reiss-m0c, poll_interval: 0.3}\n"
        "  - {name: aeration_oxygen, bus: aeration, address: 1, profile: jumo-digiline-odo-s10, poll_interval: 0.3}\n"
        "mqtt: {enabled: false}\n"
        "prometheus: {enabled: false}\n",
        environ={},
    )
    sink = ListSink()
    stop = asyncio.Event()
    task = asyncio.create_task(run(config, [sink], stop=stop))
    await asyncio.sleep(1.5)
    names = {t.get_name() for t in asyncio.all_tasks()}
    stop.set()
    await asyncio.wait_for(task, timeout=6)
    await serial_line.close()
    await tcp_line.close()
    assert {"bus[basin]", "bus[aeration]"} <= names
    assert [s.value for s in sink.good("basin_chlorine", "concentration")][:1] == [0.168]
    assert [s.value for s in sink.good("aeration_oxygen", "temperature")][:1] == [20.25]
    assert {s.bus for s in sink.samples} == {"basin", "aeration"}
