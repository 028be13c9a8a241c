"""A fleet's metrics through an outage of the central store: no gap once it is back.

A cabinet behind a firewall pushes its gateway's metrics out (issue 39, part 4): the gateway
runs as users run it (``python -m gateway run``) polling a simulated S10 on a
pseudo-terminal; a real Prometheus (Debian's, 2.42) in agent mode scrapes it with
``deploy/prometheus/fleet/agent.yml`` and its targets file ``cabinet.yml`` (only the
interval, the file's place, the target's port and the store's URL pointed at this test) and
remote-writes to a real VictoriaMetrics (Debian's ``victoria-metrics``). The store is
stopped for a minute and started again on its data directory. Then the raw samples it holds
(``/api/v1/export``: as stored, no lookback filling a hole) must cover the whole window, the
minute of the outage included, with no gap wider than two scrape intervals, every series
with the ``site`` and ``cabinet`` of the targets file, and the sensor's value as it held it.
The store then answers the Grafana dashboard's Fleet row and its variables as Prometheus
would: VictoriaMetrics can be the fleet's data source as the dashboard stands.
"""

from __future__ import annotations

import contextlib
import json
import math
import shutil
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
import yaml

from tests import paths
from tests.deploy.test_deploy import JOB, as_promql, rows
from tests.mqtt_broker import free_port
from tests.unretrieved import reported_in
from tests.waiting import wait_until

if TYPE_CHECKING:
    from collections.abc import Iterator

FLEET = paths.ROOT / "deploy" / "prometheus" / "fleet"
PROMETHEUS = shutil.which("prometheus") or "/usr/bin/prometheus"
VICTORIA_METRICS = shutil.which("victoria-metrics") or "/usr/bin/victoria-metrics"

SCRAPE_INTERVAL_S = 1.0  # short, so that a minute's outage is sixty samples per series
OUTAGE_S = 60.0  # "a central store's outage of a minute" (issue 39)
MAX_GAP_S = 2 * SCRAPE_INTERVAL_S + 0.5  # one failed scrape at most, and a late tick
MAX_FAILED_SCRAPES = 3  # a loaded machine may hold up a scrape past its 1 s timeout
BEFORE_S = 5.0  # the store holds this much of the series before it is stopped
AFTER_S = 5.0  # ... and this much after it is back, the backlog sent
STOP_S = 20.0  # a graceful stop (VictoriaMetrics flushes its buffers to disk first)
TEMPERATURE = 20.25  # the simulated S10 holds it: every sample stored must be it
DEVICE = {"bus": "line1", "device": "tank1_oxygen", "profile": "jumo-digiline-odo-s10"}
# What every scrape writes (the scrape's own record, the gateway's, a device's, a sensor's
# value), with the labels the gateway gives each.
SERIES: dict[str, dict[str, str]] = {
    "up": {},
    "gateway_up": {},
    "gateway_device_online": DEVICE,
    "gateway_temperature_celsius": DEVICE,
}

SIMULATED = (
    "line: {baudrate: 19200, parity: E, stopbits: 1}\n"
    "devices:\n"
    "  - {profile: jumo-digiline-odo-s10, address: 1, animate: false,"
    f" values: {{temperature: {TEMPERATURE}}}}}\n"
)


def require(program: str, package: str) -> str:
    if not Path(program).is_file():
        pytest.fail(
            f"{program} is missing: scripts/setup installs the Debian package (as root) "
            f"'{package}' (apt-get install {package})"
        )
    return program


def get(url: str) -> str:
    with urllib.request.urlopen(url, timeout=5) as response:  # noqa: S310 - http://127.0.0.1
        return str(response.read().decode())


def log_tail(log: Path) -> str:
    return log.read_text(errors="replace")[-3000:] if log.exists() else ""


class Server:
    """A program of the test's, its output in a log file; started and stopped by the test."""

    def __init__(self, command: list[str], log: Path) -> None:
        self.command, self.log = command, log
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        with self.log.open("ab") as output:
            self.process = subprocess.Popen(self.command, stdout=output, stderr=subprocess.STDOUT)

    def stop(self) -> int:
        """SIGTERM, and SIGKILL if it is not gone within ``STOP_S``; its exit code (-9 then:
        an agent whose store is away waits a minute to flush before it exits)."""
        process, self.process = self.process, None
        if process is None:
            return 0
        process.terminate()
        try:
            return process.wait(timeout=STOP_S)
        except subprocess.TimeoutExpired:
            process.kill()
            return process.wait()

    @contextlib.contextmanager
    def running(self) -> Iterator[Server]:
        self.start()
        try:
            yield self
        finally:
            self.stop()


def gateway_config(directory: Path, pty: Path, metrics_port: int) -> Path:
    config = directory / "gateway.yaml"
    config.write_text(
        "buses:\n"
        f"  - {{name: line1, port: {pty}, baudrate: 19200, parity: E}}\n"
        "devices:\n"
        "  - {name: tank1_oxygen, bus: line1, address: 1, profile: jumo-digiline-odo-s10,"
        " poll_interval: 0.5}\n"
        "mqtt: {enabled: false}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics_port}}}\n"
        f"state_dir: {directory / 'state'}\n",
        encoding="utf-8",
    )
    return config


def cabinet_targets(directory: Path, metrics_port: int) -> tuple[Path, dict[str, str]]:
    """``cabinet.yml`` with the test's gateway as its target: the file and its labels."""
    (group,) = yaml.safe_load((FLEET / "cabinet.yml").read_text(encoding="utf-8"))
    labels: dict[str, str] = group["labels"]
    assert set(labels) == {"site", "cabinet"}  # target labels, not the gateway's
    group["targets"] = [f"127.0.0.1:{metrics_port}"]
    path = directory / "cabinet.yml"
    path.write_text(yaml.safe_dump([group]), encoding="utf-8")
    return path, labels


def agent_config(directory: Path, targets: Path, store: str) -> Path:
    """``agent.yml`` scraping every second, from ``targets``, into the store at ``store``."""
    config = yaml.safe_load((FLEET / "agent.yml").read_text(encoding="utf-8"))
    config["global"] |= {
        "scrape_interval": f"{SCRAPE_INTERVAL_S:g}s",
        "scrape_timeout": f"{SCRAPE_INTERVAL_S:g}s",
    }
    (job,) = config["scrape_configs"]
    assert job["job_name"] == JOB  # what the alert rules and the dashboard name
    (discovery,) = job["file_sd_configs"]
    assert discovery["files"] == ["cabinet.yml"]
    discovery["files"] = [str(targets)]
    (remote,) = config["remote_write"]
    assert urllib.parse.urlsplit(remote["url"]).path == "/api/v1/write"
    remote["url"] = f"{store}/api/v1/write"
    path = directory / "agent.yml"
    path.write_text(yaml.safe_dump(config), encoding="utf-8")
    return path


@dataclass(frozen=True, slots=True)
class Stored:
    """One series as the store holds it: its labels, its samples in time order, and how
    many staleness markers Prometheus wrote in it (a failed scrape ends a series so)."""

    labels: dict[str, str]
    timestamps_s: list[float]
    values: list[float]
    stale: int

    def gaps_s(self) -> list[float]:
        return [b - a for a, b in zip(self.timestamps_s, self.timestamps_s[1:], strict=False)]

    def within(self, start_s: float, end_s: float) -> int:
        return sum(start_s < t < end_s for t in self.timestamps_s)


def export(store: str, name: str) -> list[Stored]:
    """Every series named ``name`` of the job in the store, raw (``/api/v1/export``)."""
    query = urllib.parse.urlencode({"match[]": f'{name}{{job="{JOB}"}}', "start": "0"})
    series = []
    for line in get(f"{store}/api/v1/export?{query}").splitlines():
        if line.strip():
            data: dict[str, Any] = json.loads(line)
            pairs = sorted(zip(data["timestamps"], data["values"], strict=True))
            samples = [(t / 1000, float(v)) for t, v in pairs if not math.isnan(float(v))]
            series.append(
                Stored(
                    labels=data["metric"],
                    timestamps_s=[t for t, _ in samples],
                    values=[v for _, v in samples],
                    stale=len(pairs) - len(samples),
                )
            )
    return series


def stored_until(store: str, at_least_s: float) -> dict[str, Stored] | None:
    """Each of ``SERIES`` once the store holds it up to ``at_least_s`` (epoch), else None."""
    found = {}
    for name in SERIES:
        try:
            series = export(store, name)
        except OSError:  # not answering (yet)
            return None
        if len(series) != 1 or series[0].timestamps_s[-1] < at_least_s:
            return None
        found[name] = series[0]
    return found


@dataclass(frozen=True, slots=True)
class FleetView:
    """What the dashboard's Fleet row (by panel and query) and its variables get."""

    panels: dict[str, list[dict[str, Any]]]
    variables: dict[str, list[str]]


def fleet_view(store: str) -> FleetView:
    """Ask the store the dashboard's Fleet row and variable queries, as Grafana would."""
    panels = {}
    for row, panel in rows():
        if row == "Fleet":
            for target in panel["targets"]:
                query = urllib.parse.urlencode({"query": as_promql(target["expr"])})
                body = json.loads(get(f"{store}/api/v1/query?{query}"))
                assert body["status"] == "success", body
                panels[f"{panel['title']} {target['refId']}"] = body["data"]["result"]
    variables = {}
    for label, selector in (
        ("cabinet", f'up{{job="{JOB}"}}'),
        ("instance", f'up{{job="{JOB}",cabinet=~".*"}}'),
    ):
        query = urllib.parse.urlencode({"match[]": selector})
        variables[label] = json.loads(get(f"{store}/api/v1/label/{label}/values?{query}"))["data"]
    return FleetView(panels, variables)


@dataclass(frozen=True, slots=True)
class Cabinet:
    """A cabinet as the test runs it: its gateway, the agent, and the central store."""

    store: str  # the store's URL
    victoria: Server  # the store's process, to stop and start
    agent_port: int
    instance: str  # the gateway's /metrics, host:port
    labels: dict[str, str]  # site and cabinet, from the targets file


@contextlib.contextmanager
def cabinet(directory: Path) -> Iterator[Cabinet]:
    """The gateway polling the simulator, scraped by the agent into the store."""
    prometheus = require(PROMETHEUS, "prometheus")
    victoria_metrics = require(VICTORIA_METRICS, "victoria-metrics")
    metrics_port, agent_port, store_port = free_port(), free_port(), free_port()
    store = f"http://127.0.0.1:{store_port}"
    targets, labels = cabinet_targets(directory, metrics_port)
    simulator_log, gateway_log, agent_log, store_log = (
        directory / f"{name}.log" for name in ("simulator", "gateway", "agent", "victoria-metrics")
    )
    # The simulator as its own process (tests.rigs.simulate_process's way), stopped by
    # Server like the others even when the test fails.
    pty, simulated = directory / "ttySIM", directory / "simulator.yaml"
    simulated.write_text(SIMULATED, encoding="utf-8")
    python = [sys.executable, "-m", "gateway"]
    simulator = Server(
        [*python, "simulate", "--config", str(simulated), "--pty", str(pty)], simulator_log
    )
    config = gateway_config(directory, pty, metrics_port)
    gateway = Server([*python, "run", "--config", str(config), "--no-print"], gateway_log)
    victoria = Server(
        [
            victoria_metrics,
            f"-storageDataPath={directory / 'victoria-metrics'}",  # the same after a stop
            f"-httpListenAddr=127.0.0.1:{store_port}",
        ],
        store_log,
    )
    agent = Server(
        [
            prometheus,
            "--enable-feature=agent",
            f"--config.file={agent_config(directory, targets, store)}",
            f"--storage.agent.path={directory / 'agent'}",
            f"--web.listen-address=127.0.0.1:{agent_port}",
        ],
        agent_log,
    )
    with simulator.running():
        wait_until(pty.exists, within_s=30)
        with gateway.running(), victoria.running(), agent.running():
            try:
                yield Cabinet(
                    store=store,
                    victoria=victoria,
                    agent_port=agent_port,
                    instance=f"127.0.0.1:{metrics_port}",
                    labels=labels,
                )
            except AssertionError as exc:
                logs = "\n".join(
                    f"--- {log.name}\n{log_tail(log)}" for log in (agent_log, store_log)
                )
                raise AssertionError(f"{exc}\n{logs}") from exc
    for log in (simulator_log, gateway_log):
        output = log.read_text(errors="replace")
        assert not reported_in(output), output
        assert "Traceback" not in output, output


def assert_no_gap(rig: Cabinet, stored: dict[str, Stored], *, down: float, up: float) -> float:
    """Each series whole, from before the outage to after it: its largest gap."""
    # Every scrape leaves its record in up, 1 or 0 (a scrape that failed, which ends every
    # series of the gateway with a staleness marker): a few may fail on a loaded machine.
    failed = stored["up"].values.count(0.0)
    assert failed <= MAX_FAILED_SCRAPES, stored["up"]
    assert set(stored["up"].values) <= {0.0, 1.0}
    largest = 0.0
    for name, series in stored.items():
        # Scraped with the targets file's site and cabinet: the scraper's labels.
        assert series.labels == {
            "__name__": name,
            "job": JOB,
            "instance": rig.instance,
            **rig.labels,
            **SERIES[name],
        }
        assert series.timestamps_s[0] < down - BEFORE_S + SCRAPE_INTERVAL_S, name
        assert series.timestamps_s[-1] >= up + AFTER_S, name
        during = series.within(down, up)
        assert during >= (up - down) / SCRAPE_INTERVAL_S - 2 - failed, (name, during)
        gaps = series.gaps_s()
        assert max(gaps) <= MAX_GAP_S, (name, max(gaps), series.timestamps_s)
        assert min(gaps) > 0, name  # no sample twice: what was retried was stored once
        largest = max(largest, *gaps)
        assert series.stale <= failed, name
    # The values as the gateway served them, every one.
    assert set(stored["gateway_temperature_celsius"].values) == {TEMPERATURE}
    for name in ("gateway_up", "gateway_device_online"):
        assert set(stored[name].values) == {1.0}, name
    return largest


def assert_retried(agent_metrics: str) -> None:
    """The agent saw the outage: it retried what the store did not take."""
    retried = [
        float(line.rsplit(" ", 1)[1])
        for line in agent_metrics.splitlines()
        if line.startswith("prometheus_remote_storage_samples_retried_total")
    ]
    assert retried, agent_metrics
    assert sum(retried) > 0


def assert_fleet_row(rig: Cabinet, fleet: FleetView) -> None:
    """One cabinet, its gateway up, its bus open, its sensor online, by site and cabinet."""
    assert fleet.variables == {"cabinet": [rig.labels["cabinet"]], "instance": [rig.instance]}
    for where, result in fleet.panels.items():
        assert len(result) == 1, (where, result)
        assert result[0]["metric"] in ({}, rig.labels), (where, result)
    value = {where: float(result[0]["value"][1]) for where, result in fleet.panels.items()}
    for where in ("Gateways B", "Buses B", "Sensors B", "Cabinets A", "Cabinets C", "Cabinets E"):
        assert value[where] == 1.0, where
    for where in ("Gateways A", "Buses A", "Sensors A", "Reloads failed A", "Cabinets G"):
        assert value[where] == 0.0, where


@pytest.mark.line
@pytest.mark.timeout(OUTAGE_S + 180)
def test_a_minute_outage_of_the_central_store_leaves_no_gap(tmp_path: Path) -> None:
    with cabinet(tmp_path) as rig:
        # The series in the store for a while, then a minute without the store.
        first = wait_until(
            lambda: stored_until(rig.store, 0), within_s=60, every_s=SCRAPE_INTERVAL_S
        )
        since = max(series.timestamps_s[0] for series in first.values())
        wait_until(
            lambda: stored_until(rig.store, since + BEFORE_S),
            within_s=BEFORE_S + 30,
            every_s=SCRAPE_INTERVAL_S,
        )
        down = time.time()
        assert rig.victoria.stop() == 0
        time.sleep(OUTAGE_S)  # the outage itself: the one fixed wait
        up = time.time()
        rig.victoria.start()
        stored = wait_until(
            lambda: stored_until(rig.store, up + AFTER_S),
            within_s=AFTER_S + 60,
            every_s=SCRAPE_INTERVAL_S,
        )
        largest = assert_no_gap(rig, stored, down=down, up=up)
        assert_retried(get(f"http://127.0.0.1:{rig.agent_port}/metrics"))
        # The store answers the dashboard's Fleet row as Prometheus would.
        assert_fleet_row(rig, fleet_view(rig.store))
    scraped = stored["up"].timestamps_s
    sys.stdout.write(
        f"store down {up - down:.1f} s; {len(scraped)} scrapes over"
        f" {scraped[-1] - scraped[0]:.1f} s, {stored['up'].within(down, up)} of them during"
        f" the outage ({stored['up'].values.count(0.0)} failed);"
        f" the largest gap {largest:.3f} s\n"
    )
