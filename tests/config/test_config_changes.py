"""What a reloaded config changes against the running one: buses, devices, sections."""

from __future__ import annotations

from gateway.config import parse_config
from gateway.config.changes import ConfigChanges

BASE = """\
buses:
  - {name: line1, port: /dev/ttyUSB0, baudrate: 19200, parity: E}
  - {name: line2, port: /dev/ttyUSB1}
devices:
  - {name: o2, bus: line1, address: 1, profile: jumo-digiline-odo-s10}
  - {name: cl2, bus: line1, address: 3, profile: jumo-tecline-cl2}
  - {name: m0c, bus: line2, address: 4, profile: reiss-m0c}
mqtt: {host: broker.local}
"""


def changes(after: str, before: str = BASE) -> ConfigChanges:
    return ConfigChanges.between(parse_config(before, environ={}), parse_config(after, environ={}))


def test_the_same_file_changes_nothing() -> None:
    same = changes(BASE)
    assert not same.any
    assert same.summary() == "nothing changed"


def test_a_device_added_changes_its_bus_only() -> None:
    after = BASE + "  - {name: h10, bus: line2, address: 2, profile: jumo-digiline-odo-h10}\n"
    after = after.replace("mqtt: {host: broker.local}\n", "") + "mqtt: {host: broker.local}\n"
    found = changes(after)
    assert found.devices_added == ("h10",)
    assert found.buses_changed == ("line2",)
    assert found.buses_added == found.buses_removed == ()
    assert found.sections == frozenset()


def test_a_device_moved_changes_both_buses_and_itself() -> None:
    found = changes(BASE.replace("{name: cl2, bus: line1", "{name: cl2, bus: line2"))
    assert found.devices_changed == ("cl2",)
    assert found.buses_changed == ("line1", "line2")


def test_a_device_setting_changes_the_device_and_its_bus() -> None:
    found = changes(
        BASE.replace("profile: jumo-tecline-cl2}", "profile: jumo-tecline-cl2, poll_interval: 5}")
    )
    assert found.devices_changed == ("cl2",)
    assert found.buses_changed == ("line1",)


def test_a_bus_setting_changes_the_bus_not_its_devices() -> None:
    found = changes(BASE.replace("baudrate: 19200", "baudrate: 9600"))
    assert found.buses_changed == ("line1",)
    assert found.devices_changed == ()


def test_buses_added_and_removed_with_their_devices() -> None:
    after = BASE.replace(
        "  - {name: line2, port: /dev/ttyUSB1}\n", "  - {name: line3, port: /dev/ttyUSB2}\n"
    ).replace("bus: line2", "bus: line3")
    found = changes(after)
    assert found.buses_added == ("line3",)
    assert found.buses_removed == ("line2",)
    assert found.devices_changed == ("m0c",)  # it moved to the new bus
    assert found.buses_changed == ()


def test_sections_are_told_apart_and_the_state_dir_takes_a_restart() -> None:
    found = changes(
        BASE.replace("host: broker.local", "host: broker.plant") + "state_dir: /srv/gw\n"
    )
    assert found.sections == frozenset({"mqtt"})
    assert found.restart_only == ("state_dir",)
    assert found.buses_changed == ()
    assert "sections changed: mqtt" in found.summary()
