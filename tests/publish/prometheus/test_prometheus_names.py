"""The names Prometheus users expect, and the series they asked for: checked by promtool.

Every value family of every built-in profile, served over HTTP and checked by the real
``promtool check metrics``; then the gateway polling the demo's six sensors (simulated on a
pseudo-terminal) with ``prometheus:`` from its config, scraped as Prometheus scrapes it:
clean by default and with every poll group, the values in base units (the simulator's nA,
hPa, mbar and hours as amperes, pascals and seconds), only the poll groups asked for, sensor
care still fed by the logbook Prometheus no longer carries, and with ``legacy_names`` the
old families beside the new ones, as the sensor sent them; every metric the Grafana
dashboard reads is in that scrape. The config keys, the migration note and the deployment
files are checked against what the code names.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
import yaml

from gateway.app import run
from gateway.cli.demo import DEMO_SENSORS, DEVICE_NAMES
from gateway.config import ConfigProblems, check_config, parse_config
from gateway.line.samples import Quality, Sample
from gateway.profiles import PollGroup, builtin_profiles
from gateway.publish.prometheus import (
    ALL_GROUPS,
    MetricsServer,
    Selection,
    legacy_naming,
    renames,
)
from gateway.publish.prometheus.naming import NUMERIC_POINT_TYPES, point_naming
from gateway.shared.state import DeviceInfo, GatewayState
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from tests import paths
from tests.deploy.test_deploy import dashboard_queries, metric_names
from tests.mqtt_broker import Broker, free_port
from tests.publish.prometheus.test_prometheus import Exposition, fetch, scrape, scrape_until

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Iterator

    from gateway.profiles import Profile

PROMTOOL = shutil.which("promtool") or "/usr/bin/promtool"
ROOT = paths.ROOT
MIGRATION_NOTE = ROOT / "docs" / "prometheus" / "migration.md"  # the manual's page
METRICS_DOC = ROOT / "docs" / "metrics.md"
DASHBOARD = ROOT / "deploy" / "grafana" / "dashboards" / "gateway.json"
ALERTS = ROOT / "deploy" / "prometheus" / "alerts.yml"
EVERY_GROUP = [g.value for g in PollGroup]
# The groups a plant gets unless it asks: only these points' families are exported.
DEFAULT = {PollGroup.PROCESS.value, PollGroup.STATUS.value}


def promtool_check(exposition: str) -> list[str]:
    """The findings of ``promtool check metrics`` on an exposition (empty: none)."""
    if not Path(PROMTOOL).is_file():
        pytest.fail(f"{PROMTOOL} is missing: the Debian package 'prometheus' (scripts/setup)")
    result = subprocess.run(
        [PROMTOOL, "check", "metrics"],
        input=exposition,
        capture_output=True,
        text=True,
        check=False,
    )
    findings = [line for line in (result.stdout + result.stderr).splitlines() if line.strip()]
    assert (result.returncode == 0) == (not findings), result
    return findings


def finding_names(findings: list[str]) -> set[str]:
    return {line.split()[0] for line in findings}


# --- every family of every profile -------------------------------------------------------


def numeric_points(profile: Profile) -> Iterator[Any]:
    return (p for p in profile.points if p.dtype in NUMERIC_POINT_TYPES)


def every_point_state() -> GatewayState:
    """One device per built-in profile, a good sample of each of its numeric points."""
    state = GatewayState()
    now = time.monotonic()
    for index, (profile_id, profile) in enumerate(sorted(builtin_profiles().items())):
        device = f"dev{index}"
        points = list(numeric_points(profile))
        state.add_device(
            DeviceInfo(
                bus="line1",
                name=device,
                profile=profile_id,
                address=index + 1,
                intervals=dict.fromkeys((p.name for p in points), 60.0),
            )
        )
        state.record(
            [
                Sample(
                    bus="line1",
                    device=device,
                    profile=profile_id,
                    point=point.name,
                    value=True if point.dtype.value == "bool" else 1,
                    fault=None,
                    unit="mg/l" if point.unit_from else point.unit,
                    quality=Quality.GOOD,
                    monotonic=now,
                    time=datetime.now(tz=UTC),
                    group=point.group.value,
                )
                for point in points
            ]
        )
    return state


def served(state: GatewayState, selection: Selection) -> Exposition:
    with MetricsServer(state, host="127.0.0.1", port=0, selection=selection) as server:
        return scrape(server)


def test_every_value_family_of_every_profile_passes_promtool() -> None:
    metrics = served(every_point_state(), Selection(groups=ALL_GROUPS))
    assert promtool_check(metrics.text) == []
    names = set(metrics.families)
    # Base units, a record's entries as a label, no log entries, no identity gauges.
    assert {
        "gateway_cell_current_amperes",
        "gateway_raw_oxygen_amplitude_volts",
        "gateway_cip_min_duration_seconds",
        "gateway_compensation_pressure_pascals",
        "gateway_time_outside_operating_temperature_seconds",
        "gateway_cip_cycles",
        "gateway_measurements",
        "gateway_sensor_constant",
    } <= names
    assert not [
        n for n in names if re.search(r"_(logbook|history)_\d+_|_(firmware|hardware)_version", n)
    ]
    constants = {labels["constant"] for labels, _ in metrics.find("gateway_sensor_constant")}
    assert constants == {"dksv1", "dksv2", "dphi1", "dphi2", "f1", "m"}
    helps = dict(re.findall(r"^# HELP (\S+) (.*)$", metrics.text, re.MULTILINE))
    assert "named in 'constant'" in helps["gateway_sensor_constant"]  # the record, not f1
    assert helps["gateway_cell_current_amperes"].endswith("(exported in amperes)")
    # Every numeric point of every profile is in its family (or is not a metric by rule).
    exported = {(labels.get("device"), name) for name, labels, _ in metrics.samples}
    for index, (_, profile) in enumerate(sorted(builtin_profiles().items())):
        for point in numeric_points(profile):
            naming = point_naming(point)
            if naming is not None:
                assert (f"dev{index}", naming.family) in exported, point.name


def test_the_legacy_names_are_the_old_families_and_only_they_draw_promtools_findings() -> None:
    state = every_point_state()
    new = served(state, Selection(groups=ALL_GROUPS))
    both = served(state, Selection(groups=ALL_GROUPS, legacy_names=True))
    old_families = set(both.families) - set(new.families)
    renamed = {r.old for r in renames()}
    # Each old family is a row of the migration table (a log's entries folded into N).
    assert {re.sub(r"^(gateway_[a-z]+)_\d+_", r"\1_N_", n) for n in old_families} == renamed
    assert set(new.families) <= set(both.families)  # the new ones stay, unchanged
    assert finding_names(promtool_check(both.text)) <= old_families
    # An old family has the value as the sensor sent it: the tecLine's nA, not amperes.
    tecline = next(i for i, p in enumerate(sorted(builtin_profiles())) if p == "jumo-tecline-cl2")
    device = f"dev{tecline}"
    assert both.value("gateway_cell_current_nanoamperes", device=device) == 1
    assert both.value("gateway_cell_current_amperes", device=device) == 1e-9
    help_line = re.search(
        r"^# HELP gateway_cell_current_nanoamperes (.*)$", both.text, re.MULTILINE
    )
    assert help_line is not None
    assert "legacy_names" in help_line[1]
    assert "gateway_cell_current_amperes" in help_line[1]


def test_no_new_family_takes_an_old_name() -> None:
    new: set[str] = set()
    old: dict[str, str] = {}
    for profile in builtin_profiles().values():
        for point in numeric_points(profile):
            naming = point_naming(point)
            legacy = legacy_naming(point.name, point.unit, unit_from=point.unit_from is not None)
            if naming is not None:
                new.add(naming.family)
            if naming is None or naming.family != legacy.family:
                old[legacy.family] = point.name
    assert {name: old[name] for name in set(old) & new} == {}


def test_the_poll_groups_chosen_per_device_are_the_ones_exported() -> None:
    state = every_point_state()
    devices = {info.name: info.profile for info in state.devices.values()}
    h10 = next(name for name, profile in devices.items() if profile == "jumo-digiline-odo-h10")
    selection = Selection(device_groups={h10: frozenset({"diagnostics"})})
    metrics = served(state, selection)
    for name, labels, _ in metrics.samples:
        if "point" in labels:  # faults, flags, enums, ages: the point's own group
            point = builtin_profiles()[labels["profile"]].point(labels["point"])
            wanted = {"diagnostics"} if labels["device"] == h10 else DEFAULT
            assert point.group.value in wanted, (name, labels)
    assert metrics.find("gateway_measurements", device=h10) != []  # H10 diagnostics
    assert metrics.find("gateway_temperature_celsius", device=h10) == []  # not its process
    assert metrics.find("gateway_temperature_celsius") != []  # the others' process values
    assert metrics.find("gateway_measurements_max") == []  # configuration: nobody's


# --- the config ------------------------------------------------------------------------------

CONFIG = """\
buses: [{name: a, port: /dev/ttyUSB0}]
devices: [{name: basin, bus: a, address: 1, profile: jumo-tecline-cl2}]
prometheus:
  groups: [process, status, diagnostics]
  device_groups: {basin: [process, identity]}
  legacy_names: true
"""


def test_the_prometheus_keys_load_and_default_to_process_and_status() -> None:
    settings = parse_config(CONFIG, environ={}).prometheus
    assert settings.groups == [PollGroup.PROCESS, PollGroup.STATUS, PollGroup.DIAGNOSTICS]
    assert settings.device_groups == {"basin": [PollGroup.PROCESS, PollGroup.IDENTITY]}
    assert settings.legacy_names is True
    selection = Selection.of(settings)
    assert selection.groups == {"process", "status", "diagnostics"}
    assert selection.device_groups == {"basin": frozenset({"process", "identity"})}
    plain = parse_config(CONFIG.split("prometheus:", maxsplit=1)[0], environ={}).prometheus
    assert (plain.groups, plain.device_groups, plain.legacy_names) == (
        [PollGroup.PROCESS, PollGroup.STATUS],
        {},
        False,
    )
    # From the environment, as every setting: JSON for a list.
    environ = {"GATEWAY_PROMETHEUS__GROUPS": '["process", "configuration"]'}
    env = parse_config(CONFIG, environ=environ).prometheus
    assert env.groups == [PollGroup.PROCESS, PollGroup.CONFIGURATION]


def test_wrong_groups_and_devices_are_named_with_key_and_line() -> None:
    bad = (
        CONFIG.replace("diagnostics]", "diagnostic]")
        .replace("[process, identity]", "[care]")
        .replace("{basin:", "{nobody: [process], basin:")
    )
    with pytest.raises(ConfigProblems) as info:
        parse_config(bad, environ={})
    found = {(p.key, p.line): p.message for p in info.value.problems}
    choices = ", ".join(EVERY_GROUP)
    assert found == {
        ("prometheus.groups[2]", 4): f"'diagnostic' is not a poll group: one of {choices}",
        ("prometheus.device_groups.basin[0]", 5): (
            "'care' is not a poll group: the care metrics (gateway_care_state, ...) are always "
            f"exported; list poll groups only: {choices}"
        ),
        ("prometheus.device_groups.nobody", 5): "no device 'nobody'; devices: basin",
    }
    empty = CONFIG.replace("[process, status, diagnostics]", "[]")
    with pytest.raises(ConfigProblems, match=r"prometheus\.groups \(line 4\)"):
        parse_config(empty, environ={})


def test_check_config_knows_every_new_key(tmp_path: Path) -> None:
    path = tmp_path / "gateway.yaml"
    path.write_text(CONFIG, encoding="utf-8")
    assert check_config(path, environ={}) == []
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "check-config", str(path)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert "OK" in result.stdout
    path.write_text(CONFIG.replace("legacy_names", "legacy_name"), encoding="utf-8")
    (problem,) = check_config(path, environ={})
    assert (problem.key, problem.line) == ("prometheus.legacy_name", 6)


# --- the demo's plant, polled and scraped ----------------------------------------------------

# Values the demo's sensors hold still, in the sensor's units, to follow them to the metrics.
HELD: dict[str, dict[str, float]] = {
    "pool_chlorine": {"cell_current": 152.5},  # nA
    "aeration_oxygen": {"compensation_pressure": 1013.25},  # S10: hPa
    "digester_oxygen": {
        "compensation_pressure": 950.0,  # H10: mbar
        "hours_outside_operating_temperature": 0.5,  # h
        "sensor_constant_m": 1.5,
    },
    "fermenter_oxygen": {"compensation_pressure": 1000.0},  # H20: mbar
}


@dataclass(frozen=True)
class Plant:
    """The demo's sensors polled by ``app.run``: its own /metrics, and two more views."""

    configured: int  # the port of /metrics as the config has it
    default: MetricsServer  # no prometheus keys: process and status
    legacy: MetricsServer  # every group, the old names beside
    simulator: SimulatorServer

    def sensor(self, device: str) -> Any:
        address = next(a for a, name in DEVICE_NAMES.items() if name == device)
        return self.simulator.bus.devices[address]


@contextlib.asynccontextmanager
async def demo_plant(tmp_path: Path, broker: Broker) -> AsyncIterator[Plant]:
    """The demo's six sensors on a pseudo-terminal, the gateway configured for every group.

    With what adds families of its own: MQTT (and its queue's files), the demo's feed and
    the shared bus, so that promtool sees every family a plant's scrape can have.
    """
    sensors = []
    for sensor in DEMO_SENSORS:
        name = DEVICE_NAMES[sensor["address"]]
        values = sensor.get("values", {}) | HELD.get(name, {})
        sensors.append(sensor | {"animate": False, "values": values})
    simulator = SimulatorServer(build_bus(parse_settings({"devices": sensors})))
    port = tmp_path / "ttySIM"
    simulator.open_pty(port)
    metrics_port = free_port()
    devices = "".join(
        f"  - {{name: {DEVICE_NAMES[s['address']]}, bus: line1, address: {s['address']}, "
        f"profile: {s['profile']}, poll_interval: 0.5}}\n"
        for s in DEMO_SENSORS
    )
    config = parse_config(
        f"buses:\n  - {{name: line1, port: {port}}}\ndevices:\n{devices}"
        f"mqtt: {{host: 127.0.0.1, port: {broker.port}, base_topic: demo}}\n"
        "feeds:\n  - {device: aeration_oxygen, point: compensation_temperature, interval: 1,"
        " source: {device: pool_chlorine, point: temperature}}\n"
        f"shared_bus: {{listen: [{{host: 127.0.0.1, port: {free_port()}}}]}}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics_port}, groups: {json.dumps(EVERY_GROUP)}}}\n"
        f"state_dir: {tmp_path / 'state'}\n",
        environ={},
    )
    state = GatewayState()
    stop = asyncio.Event()
    gateway = asyncio.create_task(run(config, [], stop=stop, state=state), name="gateway")
    views = [
        MetricsServer(state, host="127.0.0.1", port=0),
        MetricsServer(
            state,
            host="127.0.0.1",
            port=0,
            selection=Selection(groups=ALL_GROUPS, legacy_names=True),
        ),
    ]
    for view in views:
        view.start()
    try:
        yield Plant(metrics_port, views[0], views[1], simulator)
    finally:
        for view in views:
            view.stop()
        stop.set()
        await asyncio.wait_for(gateway, timeout=10)
        await simulator.close()


def scrape_port(port: int) -> Exposition:
    reply = fetch(f"http://127.0.0.1:{port}/metrics")
    assert reply.status == 200
    return Exposition.parse(reply.body)


def dashboard_families() -> set[str]:
    """The families the Grafana dashboard reads (a counter by its family's name)."""
    names = {name for query in dashboard_queries().values() for name in metric_names(query)}
    return {name.removesuffix("_total") for name in names}


def everything_read(metrics: Exposition) -> bool:
    """Every demo sensor's diagnostics and identity read, and care assessed."""
    cared = {labels["device"] for labels, _ in metrics.find("gateway_care_state")}
    return (
        cared == set(DEVICE_NAMES.values())
        and len(metrics.find("gateway_measurements")) == 2  # H10, H20: diagnostics
        and len(metrics.find("gateway_x_zero_amperes")) == 3  # tecLine, M0c, M3c
        and len(metrics.find("gateway_sensor_constant", device="digester_oxygen")) == 6
        and bool(metrics.find("gateway_cap_usage_ratio", device="digester_oxygen"))
    )


@pytest.mark.line
@pytest.mark.broker
async def test_a_real_scrape_of_the_demo_plant_passes_promtool_in_base_units(
    tmp_path: Path, broker: Broker
) -> None:
    async with demo_plant(tmp_path, broker) as plant:
        legacy = await scrape_until(plant.legacy, everything_read, timeout_s=60)
        every = await asyncio.to_thread(scrape_port, plant.configured)
        default = await asyncio.to_thread(scrape, plant.default)
        held = {
            (device, point): plant.sensor(device).get(point)
            for device, points in HELD.items()
            for point in points
        }
    assert everything_read(legacy), sorted(legacy.families)
    # The config's own /metrics (every group, new names) and the default: no finding.
    assert everything_read(every), sorted(every.families)
    assert promtool_check(every.text) == []
    assert promtool_check(default.text) == []
    for family in ("gateway_mqtt_connected", "gateway_feed_writes", "gateway_shared_bus_share"):
        assert family in every.families  # ... checked with the rest
    # Every metric the dashboard reads is one a gateway exports: none invented, none renamed.
    assert dashboard_families() - set(every.families) == set()
    assert len(dashboard_families()) > 30
    # Values in base units, from what the simulated sensors hold in theirs (held still).
    assert held == {(d, p): v for d, points in HELD.items() for p, v in points.items()}
    assert every.value("gateway_cell_current_amperes", device="pool_chlorine") == 152.5 / 10**9
    pressure = {
        labels["device"]: value
        for labels, value in every.find("gateway_compensation_pressure_pascals")
    }
    assert pressure == {  # hPa (S10) and mbar (H10, H20) in one family
        "aeration_oxygen": 101325.0,
        "digester_oxygen": 95000.0,
        "fermenter_oxygen": 100000.0,
    }
    assert (
        every.value("gateway_time_outside_operating_temperature_seconds", device="digester_oxygen")
        == 1800.0
    )
    assert every.value("gateway_sensor_constant", device="digester_oxygen", constant="m") == 1.5
    # The default: the process values and status words, nothing of the other groups.
    for name, labels, _ in default.samples:
        if "point" in labels:
            group = builtin_profiles()[labels["profile"]].point(labels["point"]).group.value
            assert group in DEFAULT, (name, labels)
    process = {"gateway_oxygen", "gateway_temperature_celsius", "gateway_concentration"}
    assert process | {"gateway_cell_current_amperes", "gateway_status_flag"} <= set(
        default.families
    )
    assert "gateway_measurements" not in default.families
    assert "gateway_sensor_constant" not in default.families
    assert len(default.samples) < len(every.samples) / 2
    # Sensor care reads the logbook and the history Prometheus no longer carries.
    assert not [n for n in every.families if re.search(r"logbook|history", n)]
    log_points = [labels for _, labels, _ in every.samples if "_" in labels.get("point", "")]
    assert not [p for p in log_points if re.match(r"(logbook|history)_\d+_", p["point"])]
    usage = default.value("gateway_cap_usage_ratio", device="digester_oxygen")
    assert usage == pytest.approx(0.9, abs=0.001)  # aged: 900,000 of 1,000,000
    assert default.find("gateway_last_calibration_timestamp_seconds", device="digester_oxygen")
    assert default.find("gateway_slope_ratio", device="pool_chlorine")
    # With legacy_names, the old families beside, the values as the sensor sent them.
    assert legacy.value("gateway_cell_current_nanoamperes", device="pool_chlorine") == 152.5
    assert legacy.value("gateway_compensation_pressure_hectopascals") == 1013.25
    assert legacy.value("gateway_compensation_pressure_millibars", device="digester_oxygen") == 950
    old_hours = "gateway_hours_outside_operating_temperature_hours"
    assert legacy.value(old_hours, device="digester_oxygen") == 0.5
    assert legacy.find("gateway_logbook_1_oxygen", device="digester_oxygen")
    assert legacy.find("gateway_firmware_version", device="pool_chlorine")
    assert set(every.families) <= set(legacy.families)
    old = set(legacy.families) - set(every.families)
    assert finding_names(promtool_check(legacy.text)) <= old


# --- the migration note and the deployment files ---------------------------------------------


def table_rows(text: str, heading: str) -> set[tuple[str, str]]:
    """The (old, new) name pairs of the table under ``heading`` (up to the next heading)."""
    start = text.index(heading)
    end = text.find("\n#", start + len(heading))
    section = text[start : end if end >= 0 else None]
    rows = set()
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 2 and cells[0].startswith("`gateway_"):
            rows.add((cells[0].strip("`"), cells[1]))
    return rows


def expected_rows() -> set[tuple[str, str]]:
    return {(r.old, f"`{r.new}`" if r.new else r.change) for r in renames()}


def test_the_manuals_migration_note_names_every_renamed_family() -> None:
    rows = table_rows(MIGRATION_NOTE.read_text(encoding="utf-8"), "# Migration: the metric names")
    assert rows == expected_rows()


def test_docs_metrics_lists_every_renamed_family() -> None:
    rows = table_rows(METRICS_DOC.read_text(encoding="utf-8"), "## Old names")
    assert rows == expected_rows()


def old_name_pattern() -> re.Pattern[str]:
    names = sorted(re.escape(r.old).replace("_N_", r"_\d+_") for r in renames())
    return re.compile(r"(?<![\w:])(" + "|".join(names) + r")(?![\w:])")


def test_the_dashboard_and_the_alerts_use_the_new_names() -> None:
    old = old_name_pattern()
    dashboard = json.loads(DASHBOARD.read_text(encoding="utf-8"))
    queries = [t["expr"] for p in dashboard["panels"] for t in p.get("targets", [])]
    alerts = yaml.safe_load(ALERTS.read_text(encoding="utf-8"))
    queries += [r["expr"] for g in alerts["groups"] for r in g["rules"]]
    assert [q for q in queries if old.search(q)] == []
    assert any("gateway_cell_current_amperes" in q for q in queries)
