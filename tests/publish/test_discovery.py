"""Home Assistant discovery: one device per sensor, entities on the contract's topics."""

from __future__ import annotations

import json
import re
from typing import Any

import pytest

from gateway.errors import ConfigError
from gateway.profiles import PollGroup, Profile, get_profile
from gateway.publish.discovery import (
    discovery_messages,
    entity_name,
    is_problem,
    removal_messages,
)
from gateway.publish.message import Message

BASE = "gateway"
GATEWAY_ID = "gateway-pi"
POLLED_GROUPS = (PollGroup.PROCESS, PollGroup.STATUS, PollGroup.DIAGNOSTICS)
SEGMENT = re.compile(r"[^/+#]+")


def polled(profile: Profile) -> list[str]:
    """Every point a device of the profile polls cyclically."""
    return [point.name for point in profile.points_in(*POLLED_GROUPS)]


def build(
    profile_id: str,
    *,
    device: str = "aeration_oxygen",
    gateway_id: str = GATEWAY_ID,
    identity: dict[str, object] | None = None,
    units: dict[str, str | None] | None = None,
) -> list[Message]:
    profile = get_profile(profile_id)
    return discovery_messages(
        prefix="homeassistant",
        base_topic=BASE,
        gateway_id=gateway_id,
        device=device,
        profile=profile,
        points=polled(profile),
        identity={"serial_number": "00012345", "software_version": "306.01.02"}
        if identity is None
        else identity,
        units={"oxygen": "mg/l"} if units is None else units,
    )


def configs(messages: list[Message]) -> dict[str, dict[str, Any]]:
    """Payloads by config topic."""
    return {message.topic: json.loads(message.payload) for message in messages}


def config(messages: list[Message], topic: str) -> dict[str, Any]:
    return configs(messages)[topic]


S10_NODE = "homeassistant/sensor/gateway-pi_aeration_oxygen"
S10_BITS = "homeassistant/binary_sensor/gateway-pi_aeration_oxygen"


@pytest.mark.parametrize("profile_id", ["jumo-digiline-odo-s10", "jumo-digiline-odo-h10"])
def test_temperature_sensor(profile_id: str) -> None:
    temperature = config(build(profile_id), f"{S10_NODE}/temperature/config")
    assert temperature["device_class"] == "temperature"
    assert temperature["unit_of_measurement"] == "°C"
    assert temperature["state_class"] == "measurement"
    assert temperature["state_topic"] == "gateway/aeration_oxygen/temperature"
    assert temperature["unique_id"] == "gateway-pi_aeration_oxygen_temperature"
    assert temperature["object_id"] == "aeration_oxygen_temperature"
    assert temperature["default_entity_id"] == "sensor.aeration_oxygen_temperature"
    assert temperature["name"] == "Temperature"
    assert "entity_category" not in temperature
    assert temperature["availability_mode"] == "all"
    assert temperature["availability"] == [
        {
            "topic": "gateway/status",
            "payload_available": "online",
            "payload_not_available": "offline",
        },
        {
            "topic": "gateway/aeration_oxygen/availability",
            "payload_available": "online",
            "payload_not_available": "offline",
        },
    ]


@pytest.mark.parametrize("profile_id", ["jumo-digiline-odo-s10", "jumo-digiline-odo-h10"])
def test_oxygen_takes_the_unit_read_from_the_sensor_and_no_device_class(profile_id: str) -> None:
    oxygen = config(build(profile_id), f"{S10_NODE}/oxygen/config")
    assert oxygen["unit_of_measurement"] == "mg/l"
    assert "device_class" not in oxygen
    assert oxygen["state_class"] == "measurement"
    assert oxygen["state_topic"] == "gateway/aeration_oxygen/oxygen"


def test_oxygen_unit_follows_the_unit_register() -> None:
    saturation = config(
        build("jumo-digiline-odo-s10", units={"oxygen": "%sat"}), f"{S10_NODE}/oxygen/config"
    )
    assert saturation["unit_of_measurement"] == "%"
    hpa = config(
        build("jumo-digiline-odo-h10", units={"oxygen": "hPa"}), f"{S10_NODE}/oxygen/config"
    )
    assert hpa["unit_of_measurement"] == "hPa"
    assert "device_class" not in hpa  # never a pressure: the unit is a setting
    unknown = config(build("jumo-digiline-odo-s10", units={}), f"{S10_NODE}/oxygen/config")
    assert "unit_of_measurement" not in unknown


def test_empty_value_payload_means_unknown_not_the_last_number() -> None:
    # The sink clears a value in fault with an empty retained payload.
    oxygen = config(build("jumo-digiline-odo-s10"), f"{S10_NODE}/oxygen/config")
    assert oxygen["value_template"] == "{{ 'None' if value == '' else value }}"


def test_tecline_concentration_and_current() -> None:
    messages = build("jumo-tecline-cl2", device="pool_chlorine", units={"concentration": "mg/l"})
    node = "homeassistant/sensor/gateway-pi_pool_chlorine"
    concentration = config(messages, f"{node}/concentration/config")
    assert concentration["unit_of_measurement"] == "mg/l"
    assert "device_class" not in concentration
    current = config(messages, f"{node}/cell_current/config")
    assert current["unit_of_measurement"] == "nA"
    assert "device_class" not in current  # Home Assistant's current class takes A and mA only
    assert config(messages, f"{node}/x_zero/config")["entity_category"] == "diagnostic"
    assert config(messages, f"{node}/temperature/config")["device_class"] == "temperature"
    device = concentration["device"]
    assert device["manufacturer"] == "JUMO"
    assert device["model"] == "JUMO tecLine Cl2 (202630, free chlorine)"


def test_reiss_manufacturer_and_firmware_version() -> None:
    messages = build("reiss-m0c", identity={"firmware_version": 112, "serial_number": 4711})
    device = json.loads(messages[0].payload)["device"]
    assert device["manufacturer"] == "Reiss"
    assert device["sw_version"] == "112"
    assert device["serial_number"] == "4711"


def test_diagnostics_sensors() -> None:
    messages = build("jumo-digiline-odo-h10")
    pressure = config(messages, f"{S10_NODE}/pressure/config")
    assert pressure["device_class"] == "pressure"
    assert pressure["unit_of_measurement"] == "hPa"
    assert pressure["entity_category"] == "diagnostic"
    seconds = config(messages, f"{S10_NODE}/operating_seconds/config")
    assert seconds["device_class"] == "duration"
    assert config(messages, f"{S10_NODE}/cip_cycles_total/config")["name"] == "CIP cycles total"
    amplitude = config(messages, f"{S10_NODE}/raw_oxygen_amplitude/config")
    assert "device_class" not in amplitude
    assert amplitude["unit_of_measurement"] == "µV"
    # Unitless counters carry no unit; calibration logbook entries are records, not sensors.
    assert "unit_of_measurement" not in config(messages, f"{S10_NODE}/measurement_counter/config")
    assert not [m for m in messages if "logbook" in m.topic]


def test_every_process_point_is_a_sensor() -> None:
    for profile_id in (
        "jumo-digiline-odo-s10",
        "jumo-digiline-odo-h10",
        "jumo-tecline-cl2",
        "reiss-m3c",
    ):
        profile = get_profile(profile_id)
        topics = set(configs(build(profile_id)))
        for point in profile.points_in(PollGroup.PROCESS):
            assert f"{S10_NODE}/{point.name}/config" in topics, (profile_id, point.name)


def test_s10_status_bits_become_binary_sensors() -> None:
    messages = build("jumo-digiline-odo-s10")
    bits = {
        topic: payload
        for topic, payload in configs(messages).items()
        if topic.startswith("homeassistant/binary_sensor/")
    }
    flags = dict(get_profile("jumo-digiline-odo-s10").point("status").format.bits).values()
    assert set(bits) == {f"{S10_BITS}/status_{flag}/config" for flag in flags}
    cap = bits[f"{S10_BITS}/status_cap_missing/config"]
    assert cap["state_topic"] == "gateway/aeration_oxygen/status/cap_missing"
    assert cap["payload_on"] == "true"
    assert cap["payload_off"] == "false"
    assert cap["device_class"] == "problem"
    assert cap["name"] == "Cap missing"
    assert cap["unique_id"] == "gateway-pi_aeration_oxygen_status_cap_missing"
    assert cap["default_entity_id"] == "binary_sensor.aeration_oxygen_cap_missing"
    assert "entity_category" not in cap
    assert len(cap["availability"]) == 2
    for flag in flags:  # every named S10 status bit is a fault or a warning
        assert bits[f"{S10_BITS}/status_{flag}/config"]["device_class"] == "problem", flag


def test_h10_error_and_measurement_status_bits() -> None:
    bits = {
        topic.removeprefix(f"{S10_BITS}/").removesuffix("/config"): payload
        for topic, payload in configs(build("jumo-digiline-odo-h10")).items()
        if topic.startswith(S10_BITS)
    }
    for key in (
        "error_register_reference_channel_overflow",
        "error_register_temperature_too_high",
        "error_register_amplitude_too_low",
        "error_register_reference_amplitude_out_of_limits",
        "error_register_memory_write_error",
        "error_register_pme_timeout",
        "status_cap_missing",
        "status_measurement_count_exceeded",
        "status_temperature_too_high_for_measurement",
    ):
        assert bits[key]["device_class"] == "problem", key
    for key in (
        "status_new_values",
        "measurement_status_measuring",
        "measurement_status_continuous_measurement",
        "measurement_status_single_measurement_trigger",
    ):
        assert "device_class" not in bits[key], key
        assert bits[key]["entity_category"] == "diagnostic"
    assert bits["error_register_pme_timeout"]["name"] == "PME timeout"
    assert (
        bits["measurement_status_measuring"]["state_topic"]
        == "gateway/aeration_oxygen/status/measuring"
    )


@pytest.mark.parametrize(
    ("flag", "problem"),
    [
        ("oxygen_invalid", True),
        ("cap_replacement_recommended", True),
        ("temperature_out_of_range", True),
        ("signal_channel_overflow", True),
        ("new_values", False),
        ("measuring", False),
        ("continuous_measurement", False),
        ("single_measurement_trigger", False),
        ("errorless", False),  # whole words only
    ],
)
def test_is_problem(flag: str, *, problem: bool) -> None:
    assert is_problem(flag) is problem


def test_entity_name() -> None:
    assert entity_name("cell_current") == "Cell current"
    assert entity_name("sip_cycles_since_calibration") == "SIP cycles since calibration"


@pytest.mark.parametrize("profile_id", ["jumo-digiline-odo-s10", "jumo-digiline-odo-h10"])
def test_payloads_and_topics_are_valid(profile_id: str) -> None:
    messages = build(profile_id, gateway_id="gateway/pi+#1")
    assert messages
    unique_ids = []
    for message in messages:
        assert message.retain
        assert message.qos == 1
        levels = message.topic.split("/")
        assert len(levels) == 5
        assert levels[0] == "homeassistant"
        assert levels[1] in {"sensor", "binary_sensor"}
        assert levels[-1] == "config"
        assert all(SEGMENT.fullmatch(level) for level in levels), message.topic
        assert re.fullmatch(r"[a-zA-Z0-9_-]+", levels[2])
        assert re.fullmatch(r"[a-zA-Z0-9_-]+", levels[3])
        payload = json.loads(message.payload)
        unique_ids.append(payload["unique_id"])
        assert payload["device"]["identifiers"] == ["gateway_pi__1_aeration_oxygen"]
        for topic in [payload["state_topic"], *(a["topic"] for a in payload["availability"])]:
            assert all(SEGMENT.fullmatch(level) for level in topic.split("/")), topic
    assert len(unique_ids) == len(set(unique_ids))
    assert len({m.topic for m in messages}) == len(messages)


def test_identity_in_the_device_block() -> None:
    messages = build(
        "jumo-digiline-odo-s10",
        identity={
            "serial_number": " 00012345 ",
            "software_version": "306.01.02",
            "device_name": "O-DO S10",
        },
    )
    for payload in configs(messages).values():
        assert payload["device"] == {
            "identifiers": ["gateway-pi_aeration_oxygen"],
            "name": "aeration_oxygen",
            "model": "JUMO digiLine O-DO S10",
            "manufacturer": "JUMO",
            "serial_number": "00012345",
            "sw_version": "306.01.02",
        }
        assert payload["origin"]["name"] == "rs485-sensor-gateway"


def test_unknown_identity_is_left_out() -> None:
    device = json.loads(
        build("jumo-digiline-odo-s10", identity={"serial_number": None, "software_version": ""})[
            0
        ].payload
    )["device"]
    assert "serial_number" not in device
    assert "sw_version" not in device
    assert device["identifiers"] == ["gateway-pi_aeration_oxygen"]


@pytest.mark.parametrize("profile_id", ["jumo-digiline-odo-s10", "jumo-digiline-odo-h10"])
def test_removal_clears_the_same_topics(profile_id: str) -> None:
    profile = get_profile(profile_id)
    removal = removal_messages(
        prefix="homeassistant",
        gateway_id=GATEWAY_ID,
        device="aeration_oxygen",
        profile=profile,
        points=polled(profile),
    )
    assert [m.topic for m in removal] == [m.topic for m in build(profile_id)]
    assert all(m.payload == b"" and m.retain for m in removal)


@pytest.mark.parametrize("profile_id", ["jumo-digiline-odo-s10", "jumo-digiline-odo-h10"])
def test_identical_inputs_give_identical_bytes(profile_id: str) -> None:
    first = build(profile_id)
    again = build(profile_id)
    assert first == again
    profile = get_profile(profile_id)
    shuffled = discovery_messages(
        prefix="homeassistant",
        base_topic=BASE,
        gateway_id=GATEWAY_ID,
        device="aeration_oxygen",
        profile=profile,
        points=reversed(polled(profile)),
        identity={"software_version": "306.01.02", "serial_number": "00012345"},
        units={"oxygen": "mg/l"},
    )
    assert shuffled == first
    payload = first[0].payload.decode()
    assert payload == json.dumps(
        json.loads(payload), sort_keys=True, separators=(",", ":"), ensure_ascii=False
    )


def test_only_polled_points_and_qos() -> None:
    profile = get_profile("jumo-digiline-odo-s10")
    messages = discovery_messages(
        base_topic="plant/gw",
        gateway_id=GATEWAY_ID,
        device="tank1",
        profile=profile,
        points=["oxygen", "status"],
        identity={},
        units={"oxygen": "mg/l"},
        qos=0,
    )
    topics = [m.topic for m in messages]
    assert topics[0] == "homeassistant/sensor/gateway-pi_tank1/oxygen/config"
    assert len(topics) == 1 + len(profile.point("status").format.bits)
    assert all(m.qos == 0 for m in messages)
    assert json.loads(messages[0].payload)["state_topic"] == "plant/gw/tank1/oxygen"


def test_unknown_point_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="no point 'oxygn'"):
        build_points(["oxygn"])


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"base_topic": "gate/#"}, "mqtt.base_topic"),
        ({"prefix": "home//assistant"}, "mqtt.discovery.prefix"),
        ({"device": "tank/1"}, "devices"),
        ({"gateway_id": "///"}, "mqtt.client_id"),
    ],
)
def test_invalid_topics_are_config_errors(kwargs: dict[str, str], key: str) -> None:
    with pytest.raises(ConfigError) as caught:
        build_points(["oxygen"], **kwargs)
    assert caught.value.key == key


def build_points(points: list[str], **kwargs: str) -> list[Message]:
    arguments: dict[str, Any] = {
        "prefix": "homeassistant",
        "base_topic": BASE,
        "gateway_id": GATEWAY_ID,
        "device": "aeration_oxygen",
    } | kwargs
    return discovery_messages(
        **arguments,
        profile=get_profile("jumo-digiline-odo-s10"),
        points=points,
        identity={},
        units={},
    )
