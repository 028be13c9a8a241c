"""Config: the examples load, the environment overrides, and every problem is located.

Broken configs are golden cases as data: each file in ``tests/config/configs/broken/`` states the
problems it must produce in header comments, one per problem, as

    # expect: KEY @ LINE: a fragment of the message

and the problems reported must be exactly those (key and line), each message containing
its fragment. An empty KEY stands for a problem of the file as a whole.
"""

from __future__ import annotations

import json
import re
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

from gateway.config import (
    BusConfig,
    Cadence,
    ConfigProblems,
    DeviceConfig,
    GatewayConfig,
    PointSchedule,
    Problem,
    check_config,
    load_config,
    parse_config,
)
from gateway.errors import ConfigError
from gateway.profiles import PollGroup, builtin_profiles, get_profile
from gateway.simulator import load_settings
from gateway.wire.codec import WordOrder
from gateway.wire.timing import LineFormat
from tests import paths

if TYPE_CHECKING:
    from collections.abc import Mapping

ROOT = paths.ROOT
CONFIG_DIR = ROOT / "config"
BROKEN_DIR = Path(__file__).parent / "configs" / "broken"
EXAMPLES = (
    "jumo-digiline-odo-s10.yaml",
    "jumo-digiline-odo-h10-h20.yaml",
    "jumo-tecline.yaml",
    "reiss-m0c-m3c.yaml",
    "plant.yaml",
)
NO_ENV: Mapping[str, str] = {}
EXPECT = re.compile(r"# expect: (?P<key>\S*) ?@ (?P<line>\d+): (?P<fragment>.+)")

MINIMAL = """\
buses:
  - {name: line1, port: /dev/ttyUSB0}
devices:
  - name: tank1_oxygen
    bus: line1
    address: 1
    profile: jumo-digiline-odo-s10
"""


def config_of(text: str, environ: Mapping[str, str] = NO_ENV) -> GatewayConfig:
    return parse_config(textwrap.dedent(text), environ=environ)


def problems_of(text: str, environ: Mapping[str, str] = NO_ENV) -> list[Problem]:
    with pytest.raises(ConfigProblems) as info:
        parse_config(textwrap.dedent(text), environ=environ)
    return info.value.problems


def device_with(**settings: object) -> DeviceConfig:
    fields: dict[str, object] = {
        "name": "tank1_oxygen",
        "bus": "line1",
        "address": 1,
        "profile": "jumo-digiline-odo-s10",
        **settings,
    }
    return DeviceConfig.model_validate(fields)


# --- the examples ------------------------------------------------------------------------


GATEWAY_CONFIGS = sorted(
    p.name for p in CONFIG_DIR.glob("*.yaml") if not p.name.startswith("simulator-")
)


@pytest.mark.parametrize("name", GATEWAY_CONFIGS)
def test_every_example_loads(name: str) -> None:
    config = load_config(CONFIG_DIR / name, environ=NO_ENV)
    assert config.devices
    assert check_config(CONFIG_DIR / name, environ=NO_ENV) == []


def test_one_example_per_family_and_the_plant() -> None:
    assert set(EXAMPLES) <= set(GATEWAY_CONFIGS)


@pytest.mark.parametrize("name", [n for n in EXAMPLES if n != "plant.yaml"])
def test_each_family_example_is_about_its_family(name: str) -> None:
    config = load_config(CONFIG_DIR / name, environ=NO_ENV)
    assert {device.get_profile().family for device in config.devices} == {Path(name).stem}


@pytest.mark.parametrize("name", GATEWAY_CONFIGS)
def test_examples_comment_every_key_where_it_first_appears(name: str) -> None:
    seen: set[str] = set()
    for line in (CONFIG_DIR / name).read_text(encoding="utf-8").splitlines():
        match = re.match(r"\s*(?:- )?([a-z_0-9]+):", line)
        if match is None or match[1] in seen:
            continue
        seen.add(match[1])
        assert "#" in line, f"{name}: key {match[1]!r} has no comment: {line.strip()!r}"


def test_plant_polls_the_simulated_reference_plant() -> None:
    config = load_config(CONFIG_DIR / "plant.yaml", environ=NO_ENV)
    simulated = load_settings(CONFIG_DIR / "simulator-plant.yaml")
    (bus,) = config.buses
    assert bus.port == "/tmp/ttySIM"  # noqa: S108 - the simulator's documented link
    assert bus.line == LineFormat(baudrate=9600, parity="E", stopbits=1)
    assert bus.line == LineFormat(**simulated.line.model_dump())
    assert {(d.profile, d.address) for d in config.devices} == {
        (d.profile, d.address) for d in simulated.devices
    }
    families = {device.get_profile().family for device in config.devices}
    assert families == {
        "jumo-digiline-odo-s10",
        "jumo-digiline-odo-h10-h20",
        "jumo-tecline",
        "reiss-m0c-m3c",
    }


# --- broken configs: golden cases --------------------------------------------------------


def expectations(path: Path) -> set[tuple[str, int, str]]:
    found = set()
    for line in path.read_text(encoding="utf-8").splitlines():
        if match := EXPECT.fullmatch(line):
            found.add((match["key"], int(match["line"]), match["fragment"]))
    assert found, f"{path.name} states no expected problem"
    return found


@pytest.mark.parametrize("path", sorted(BROKEN_DIR.glob("*.yaml")), ids=lambda p: p.stem)
def test_broken_config_reports_key_and_line(path: Path) -> None:
    expected = expectations(path)
    problems = check_config(path, environ=NO_ENV)
    assert {(p.key, p.line) for p in problems} == {(key, line) for key, line, _ in expected}
    for key, line, fragment in expected:
        (problem,) = [p for p in problems if (p.key, p.line) == (key, line)]
        assert fragment in problem.message, problem
    with pytest.raises(ConfigProblems) as info:
        load_config(path, environ=NO_ENV)
    assert info.value.problems == problems
    assert info.value.path == path


def test_every_problem_of_the_brief_has_a_golden_case() -> None:
    names = {p.stem for p in BROKEN_DIR.glob("*.yaml")}
    assert {
        "syntax-error",
        "unknown-profile",
        "unknown-bus",
        "duplicate-address",
        "duplicate-device-name",
        "duplicate-bus-name",
        "unknown-point",
        "device-timeout-too-long",
        "bus-timeout-too-long",
        "many-problems",
    } <= names


def test_problems_print_one_per_line_with_key_and_line() -> None:
    with pytest.raises(ConfigProblems) as info:
        load_config(BROKEN_DIR / "duplicate-address.yaml", environ=NO_ENV)
    error = info.value
    assert isinstance(error, ConfigError)
    assert str(error) == (
        "devices[1].address (line 14): address 1 is already used on bus line1 by devices[0] "
        "(tank1_oxygen)"
    )
    assert (error.key, error.line) == ("devices[1].address", 14)


def test_all_problems_are_reported_at_once_in_file_order() -> None:
    problems = check_config(BROKEN_DIR / "many-problems.yaml", environ=NO_ENV)
    assert len(problems) == 11
    lines = [p.line for p in problems]
    assert lines == sorted(line for line in lines if line is not None)
    with pytest.raises(ConfigProblems) as info:
        load_config(BROKEN_DIR / "many-problems.yaml", environ=NO_ENV)
    assert str(info.value).splitlines() == [str(p) for p in problems]
    kinds = {p.message.split(" ", 2)[0] for p in problems}
    assert {"name", "unknown", "address", "Input"} <= kinds  # field errors and cross-checks


def test_problem_text_leaves_out_what_is_unknown() -> None:
    assert str(Problem("mqtt.port", 3, "bad")) == "mqtt.port (line 3): bad"
    assert str(Problem("mqtt.port", None, "bad")) == "mqtt.port: bad"
    assert str(Problem("", 7, "bad")) == "line 7: bad"
    assert str(Problem("", None, "bad")) == "bad"


def test_a_missing_file_is_a_config_error_naming_the_path(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere.yaml"
    with pytest.raises(ConfigError, match=re.escape(str(missing))) as info:
        load_config(missing, environ=NO_ENV)
    assert not isinstance(info.value, ConfigProblems)
    (problem,) = check_config(missing, environ=NO_ENV)
    assert (problem.key, problem.line) == ("", None)
    assert str(missing) in problem.message


def test_a_file_that_is_not_utf8_is_a_problem(tmp_path: Path) -> None:
    path = tmp_path / "latin1.yaml"
    path.write_bytes("logging: {level: INFO}  # \xe9\n".encode("latin-1"))
    (problem,) = check_config(path, environ=NO_ENV)
    assert "not UTF-8" in problem.message


def test_an_empty_file_needs_a_bus(tmp_path: Path) -> None:
    path = tmp_path / "empty.yaml"
    path.write_text("# nothing yet\n", encoding="utf-8")
    (problem,) = check_config(path, environ=NO_ENV)
    assert (problem.key, problem.line, problem.message) == ("buses", None, "required, but missing")


def test_a_bus_list_cannot_be_empty() -> None:
    (problem,) = problems_of("buses: []\n")
    assert (problem.key, problem.line) == ("buses", 1)


def test_underscore_keys_are_not_taken_as_loader_options() -> None:
    (problem,) = problems_of(MINIMAL + "_env_file: /etc/secrets.env\n")
    assert (problem.key, problem.line) == ("_env_file", 8)
    assert problem.message.startswith("unknown key '_env_file'")


def test_a_password_is_never_echoed() -> None:
    (problem,) = problems_of(MINIMAL + "mqtt:\n  password: 12345678\n")
    assert (problem.key, problem.line) == ("mqtt.password", 9)
    assert "12345678" not in problem.message


def test_merged_keys_keep_their_lines_and_explicit_keys_win() -> None:
    problems = problems_of(
        """\
        buses:
          - {name: line1, port: /dev/ttyUSB0}
        devices:
          - &oxygen
            name: tank1_oxygen
            bus: line1
            address: 1
            profile: jumo-digiline-odo-s10
          - <<: *oxygen
            name: tank2_oxygen
          - <<: *oxygen
            name: tank3_oxygen
            address: 3
            timeout: 9
        """
    )
    assert {(p.key, p.line) for p in problems} == {
        ("devices[1].address", 7),  # inherited from the anchor: its line is there
        ("devices[2].timeout", 14),
    }


# --- the environment ---------------------------------------------------------------------


def test_environment_sets_the_mqtt_password() -> None:
    config = load_config(CONFIG_DIR / "plant.yaml", environ={"GATEWAY_MQTT__PASSWORD": "s3cret"})
    assert config.mqtt.password is not None
    assert config.mqtt.password.get_secret_value() == "s3cret"
    assert "s3cret" not in repr(config)
    assert config.mqtt.host == "localhost"  # the rest of mqtt still comes from the file


def test_an_empty_environment_variable_leaves_the_file_value(tmp_path: Path) -> None:
    # Compose passes an unset ${MQTT_USERNAME} on as "": that must not blank the file's user.
    text = (CONFIG_DIR / "plant.yaml").read_text()
    assert "  username: null" in text
    path = tmp_path / "plant.yaml"
    path.write_text(text.replace("  username: null", "  username: plant"))
    environ = {"GATEWAY_MQTT__USERNAME": "", "GATEWAY_MQTT__PASSWORD": ""}
    config = load_config(path, environ=environ)
    assert config.mqtt.username == "plant"
    assert config.mqtt.password is None


def test_environment_sets_the_log_level_case_insensitively() -> None:
    config = load_config(CONFIG_DIR / "plant.yaml", environ={"gateway_logging__level": "debug"})
    assert config.logging.level == "DEBUG"
    assert config.logging.format == "text"


def test_environment_sets_the_prometheus_port_over_the_file() -> None:
    path = CONFIG_DIR / "plant.yaml"
    assert load_config(path, environ=NO_ENV).prometheus.port == 9108
    config = load_config(path, environ={"GATEWAY_PROMETHEUS__PORT": "9200"})
    assert config.prometheus.port == 9200
    assert config.prometheus.host == "127.0.0.1"


def test_environment_defaults_to_os_environ(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GATEWAY_LOGGING__LEVEL", "WARNING")
    assert load_config(CONFIG_DIR / "plant.yaml").logging.level == "WARNING"
    assert load_config(CONFIG_DIR / "plant.yaml", environ=NO_ENV).logging.level == "INFO"


def test_environment_takes_json_for_a_whole_section() -> None:
    config = config_of(MINIMAL, environ={"GATEWAY_MQTT": '{"host": "broker", "port": 8883}'})
    assert (config.mqtt.host, config.mqtt.port) == ("broker", 8883)


def test_environment_can_replace_a_whole_list() -> None:
    devices = [
        {"name": "a", "bus": "line1", "address": 7, "profile": "reiss-m0c"},
        {"name": "b", "bus": "line1", "address": 7, "profile": "reiss-m3c"},
    ]
    problems = problems_of(MINIMAL, environ={"GATEWAY_DEVICES": json.dumps(devices)})
    (problem,) = problems
    assert (problem.key, problem.line) == ("devices[1].address", None)
    assert problem.message.endswith("(from GATEWAY_DEVICES)")
    devices[1]["address"] = 8
    config = config_of(MINIMAL, environ={"GATEWAY_DEVICES": json.dumps(devices)})
    assert [d.name for d in config.devices] == ["a", "b"]


def test_a_bad_environment_value_names_its_variable() -> None:
    (problem,) = problems_of(MINIMAL, environ={"GATEWAY_PROMETHEUS__PORT": "ninety"})
    assert (problem.key, problem.line) == ("prometheus.port", None)
    assert "(from GATEWAY_PROMETHEUS__PORT)" in problem.message


def test_a_misspelt_environment_key_is_refused() -> None:
    (problem,) = problems_of(MINIMAL, environ={"GATEWAY_MQTT__PASWORD": "x"})
    assert problem.key == "mqtt.pasword"
    assert "did you mean password?" in problem.message


def test_environment_problems_come_with_the_file_problems() -> None:
    problems = problems_of(
        MINIMAL.replace("address: 1", "address: 0"),
        environ={
            "GATEWAY_MQTT": "{not json",
            "GATEWAY_DEVICES__0__ADDRESS": "3",
            "GATEWAY_LOGGING__LEVEL": "LOUD",
        },
    )
    assert [(p.key, p.line) for p in problems] == [
        ("devices[0].address", 6),  # the file's problems first, in file order
        ("mqtt", None),
        ("devices", None),
        ("logging.level", None),
    ]
    messages = " | ".join(p.message for p in problems)
    assert "GATEWAY_MQTT must be JSON" in messages
    assert "GATEWAY_DEVICES__0__ADDRESS: entries of devices cannot be set one by one" in messages


def test_other_gateway_variables_are_left_alone() -> None:
    config = config_of(MINIMAL, environ={"GATEWAY_CONFIG": "/etc/gateway.yaml", "HOME": "/"})
    assert config.buses[0].name == "line1"


# --- what the bus engine asks ------------------------------------------------------------


@pytest.mark.parametrize(
    ("point", "expected"),
    [
        ("oxygen", PointSchedule.every(0.5)),  # process
        ("status", PointSchedule.every(0.5)),  # status
        ("calibration_status", PointSchedule.every(30.0)),  # diagnostics
        ("float_format", PointSchedule.every(600.0)),  # configuration
        ("serial_number", PointSchedule.ON_CONNECT),  # identity
    ],
)
def test_interval_resolution_by_poll_group(point: str, expected: PointSchedule) -> None:
    device = device_with(poll_interval=0.5, diagnostics_interval=30, configuration_interval=600)
    assert device.interval_for(point) == expected


def test_interval_defaults() -> None:
    device = device_with()
    assert device.interval_for("temperature") == PointSchedule.every(1.0)
    assert device.interval_for("operating_seconds") == PointSchedule.every(60.0)
    assert device.interval_for("oxygen_unit") == PointSchedule.every(300.0)
    assert device.interval_for("device_name") == PointSchedule.ON_CONNECT


def test_per_point_interval_wins_over_the_group() -> None:
    device = device_with(
        points={"temperature": {"interval": 5}, "serial_number": {"interval": 3600}}
    )
    assert device.interval_for("temperature") == PointSchedule.every(5.0)
    assert device.interval_for("serial_number") == PointSchedule.every(3600.0)
    assert device.interval_for("oxygen") == PointSchedule.every(1.0)


def test_per_point_disable() -> None:
    device = device_with(
        points={
            "status": {"enabled": False},
            "temperature": {"enabled": False, "interval": 5},  # kept for later, unused
            "serial_number": {"enabled": False},
        }
    )
    for name in ("status", "temperature", "serial_number"):
        schedule = device.interval_for(name)
        assert schedule == PointSchedule.NEVER
        assert schedule.cadence is Cadence.NEVER
        assert not schedule.periodic
        assert schedule.interval_s is None


def test_interval_for_takes_a_point_or_its_name() -> None:
    device = device_with(points={"temperature": {"interval": 5}})
    point = get_profile("jumo-digiline-odo-s10").point("temperature")
    assert device.interval_for(point) == device.interval_for("temperature")
    with pytest.raises(ConfigError, match="no point 'temprature'"):
        device.interval_for("temprature")


def test_every_point_of_every_profile_has_a_schedule() -> None:
    by_group = {
        PollGroup.PROCESS: Cadence.PERIODIC,
        PollGroup.STATUS: Cadence.PERIODIC,
        PollGroup.DIAGNOSTICS: Cadence.PERIODIC,
        PollGroup.CONFIGURATION: Cadence.PERIODIC,
        PollGroup.IDENTITY: Cadence.ON_CONNECT,
    }
    for profile in builtin_profiles().values():
        device = device_with(profile=profile.id)
        for point in profile.points:
            assert device.interval_for(point).cadence is by_group[point.group]


def test_schedules_are_consistent() -> None:
    assert PointSchedule.every(2.0).periodic
    assert PointSchedule.every(2.0).interval_s == 2.0
    assert not PointSchedule.ON_CONNECT.periodic
    with pytest.raises(ValueError, match="periodic"):
        PointSchedule(Cadence.PERIODIC)
    with pytest.raises(ValueError, match="periodic"):
        PointSchedule(Cadence.NEVER, 1.0)


def test_response_timeout_bus_device_and_minimum_response_time() -> None:
    bus = BusConfig(name="line1", port="/dev/ttyUSB0", timeout=0.4, retries=4)
    assert device_with().response_timeout(bus) == pytest.approx(0.4)
    assert device_with(timeout=0.2).response_timeout(bus) == pytest.approx(0.2)
    assert device_with(min_response_time_ms=50).response_timeout(bus) == pytest.approx(0.45)
    assert device_with(timeout=0.2, min_response_time_ms=500).response_timeout(
        bus
    ) == pytest.approx(0.7)
    assert device_with().retries_on(bus) == 4
    assert device_with(retries=0).retries_on(bus) == 0


def test_float_order_is_an_explicit_override_only() -> None:
    # None leaves the order to the device's format register or the profile, at run time.
    assert device_with().float_order is None
    assert device_with(float_order="ABCD").float_order is WordOrder.ABCD


def test_devices_on_a_bus_in_config_order() -> None:
    config = load_config(CONFIG_DIR / "reiss-m0c-m3c.yaml", environ=NO_ENV)
    assert [d.name for d in config.devices_on("line_m0c")] == ["basin_chlorine"]
    assert [d.name for d in config.devices_on("line_m3c")] == ["outlet_chlorine"]
    assert config.bus("line_m3c").line == LineFormat(baudrate=9600, parity="N", stopbits=2)
    with pytest.raises(ConfigError, match="unknown bus 'line9'; buses: line_m0c, line_m3c"):
        config.devices_on("line9")


def test_plant_example_resolves_as_documented() -> None:
    config = load_config(CONFIG_DIR / "plant.yaml", environ=NO_ENV)
    bus = config.bus("plant")
    oxygen, *others = config.devices_on("plant")
    assert oxygen.interval_for("temperature") == PointSchedule.every(5.0)
    assert oxygen.interval_for("oxygen") == PointSchedule.every(1.0)
    assert oxygen.response_timeout(bus) is None  # computed by the bus engine from the profile
    assert len(others) == 6
    assert others[-1].retries_on(bus) == 3


def test_defaults_of_a_minimal_config() -> None:
    config = config_of(MINIMAL)
    bus = config.buses[0]
    assert (bus.baudrate, bus.parity, bus.stopbits, bus.timeout, bus.retries) == (
        9600,
        "N",
        1,
        None,
        2,
    )
    assert bus.reconnect_max_s == 30.0
    device = config.devices[0]
    assert (device.poll_interval, device.diagnostics_interval, device.configuration_interval) == (
        1.0,
        60.0,
        300.0,
    )
    assert (device.offline_after, device.min_response_time_ms, device.inter_frame_gap_ms) == (
        3,
        0,
        0.0,
    )
    assert (config.mqtt.host, config.mqtt.port, config.mqtt.base_topic) == (
        "localhost",
        1883,
        "gateway",
    )
    assert config.mqtt.password is None
    assert (config.prometheus.host, config.prometheus.port) == ("0.0.0.0", 9108)  # noqa: S104
    assert (config.logging.level, config.logging.format) == ("INFO", "text")


@pytest.mark.parametrize(
    "port",
    [
        "/dev/ttyUSB0",
        "/dev/serial/by-id/usb-FTDI-if00",
        "COM3",
        "socket://10.0.0.5:4001",
        "rfc2217://gw.local:2217",
        "loop://",
    ],
)
def test_ports_that_pyserial_opens(port: str) -> None:
    assert BusConfig(name="line1", port=port).port == port


def test_an_unknown_echo_setting_names_the_key_line_and_choices() -> None:
    (problem,) = problems_of(
        "buses:\n"
        "  - name: line1\n"
        "    port: /dev/ttyUSB0\n"
        "    echo: sometimes\n"
        "devices:\n"
        "  - {name: tank, bus: line1, address: 1, profile: jumo-digiline-odo-s10}\n"
    )
    assert (problem.key, problem.line) == ("buses[0].echo", 4)
    assert "'off', 'on' or 'auto'" in problem.message, problem.message


@pytest.mark.parametrize(("written", "meant"), [("off", "off"), ("on", "on"), ("'off'", "off")])
def test_echo_off_and_on_unquoted_mean_the_words(written: str, meant: str) -> None:
    # YAML 1.1 reads a bare off/on as false/true.
    config = parse_config(
        f"buses:\n  - {{name: line1, port: /dev/ttyUSB0, echo: {written}}}\n"
        "devices:\n  - {name: tank, bus: line1, address: 1, profile: jumo-digiline-odo-s10}\n",
        environ=NO_ENV,
    )
    assert config.buses[0].echo == meant


def test_poll_phase_is_a_fraction_of_the_poll_interval_spread_by_default() -> None:
    assert device_with().poll_phase is None  # the gateway spreads the devices
    assert device_with(poll_phase=0).poll_phase == 0.0  # no spread
    assert device_with(poll_phase=0.25, poll_interval=2).poll_phase == 0.25
    assert device_with(poll_phase="0.75").poll_phase == 0.75
