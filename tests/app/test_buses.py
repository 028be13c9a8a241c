"""A reload's changes of the buses, as the running gateway applies them (:mod:`gateway.app.buses`).

The workers are built but not started (no port is opened): a worker that does not run
takes its new devices at once, so what each device's target became is read right after.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from gateway.app.buses import Buses
from gateway.config import parse_config
from gateway.config.changes import ConfigChanges
from gateway.control.flash import FlashLedger
from gateway.shared.state import GatewayState

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.config import GatewayConfig


def plant(bus: str = "", devices: str = "") -> GatewayConfig:
    return parse_config(
        "buses:\n"
        f"  - {{name: line1, port: /dev/ttyGW0, baudrate: 19200, parity: E{bus}}}\n"
        "devices:\n"
        "  - {name: cl2, bus: line1, address: 20, profile: jumo-tecline-cl2}\n"
        "  - {name: h10, bus: line1, address: 2, profile: jumo-digiline-odo-h10}\n"
        f"{devices}",
        environ={},
    )


async def changed(tmp_path: Path, old: GatewayConfig, new: GatewayConfig) -> Buses:
    buses = Buses(old, GatewayState(), FlashLedger(tmp_path / "flash.sqlite"), list)
    buses.config = new
    assert await buses.change(ConfigChanges.between(old, new), old, mqtt=None) == set()
    return buses


async def test_a_device_added_leaves_the_others_their_targets_and_slots(tmp_path: Path) -> None:
    old = plant()
    buses = Buses(old, GatewayState(), FlashLedger(tmp_path / "flash.sqlite"), list)
    before = {name: s.target for name, s in buses.workers["line1"].devices.items()}
    new = plant(devices="  - {name: m0c, bus: line1, address: 10, profile: reiss-m0c}\n")
    buses.config = new
    await buses.change(ConfigChanges.between(old, new), old, mqtt=None)
    after = buses.workers["line1"].devices
    assert after["cl2"].target is before["cl2"]  # not even a new phase among three
    assert after["h10"].target is before["h10"]
    assert after["m0c"].target.address == 10
    assert set(buses.writers) == {"cl2", "h10", "m0c"}


async def test_the_bus_s_own_retries_and_timeout_reach_its_devices(tmp_path: Path) -> None:
    buses = await changed(tmp_path, plant(), plant(bus=", retries: 4, timeout: 0.4"))
    for state in buses.workers["line1"].devices.values():
        assert state.target.retries == 4
        assert state.target.timeout_s == 0.4


async def test_a_device_removed_is_gone_with_its_write_path(tmp_path: Path) -> None:
    old = plant(devices="  - {name: m0c, bus: line1, address: 10, profile: reiss-m0c}\n")
    buses = await changed(tmp_path, old, plant())
    assert set(buses.workers["line1"].devices) == {"cl2", "h10"}
    assert set(buses.writers) == {"cl2", "h10"}
