"""What ``gateway run`` holds in memory: the libraries of what its config switches on, no more.

The gateway runs as a user runs it, as its own process on a simulated line with a real
broker, polls, is scraped once and is stopped; at its exit it writes the names of every
module it imported. A plain config (MQTT and Prometheus) must not have imported the web
page (aiohttp), Sparkplug (protobuf), the shared bus, the feeds or any other command's
module, nor the command line's libraries (typer, rich) or pymodbus; a config that switches
them on must have (so that the check sees what it claims to: a rename or a lazy import
that never happens fails here too).

A plain ``gateway run`` is read without typer (``gateway/cli/run.py``); every command line
that reader takes must be read by typer the same way, whatever the options' order and
spelling, and every other one left to typer.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import urllib.request
from typing import TYPE_CHECKING

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.cli import root
from gateway.cli.run import plain_run
from tests.fuzzing import fuzz
from tests.mqtt_broker import free_port
from tests.rigs import simulate_process
from tests.unretrieved import reported_in

if TYPE_CHECKING:
    from collections.abc import Iterator
    from pathlib import Path

    from tests.mqtt_broker import Broker

# `gateway run` through the command line's entry point; the modules written at exit
# (SIGTERM stops it cleanly, so exit handlers run).
RUN = """
import atexit, json, sys
modules_file, config = sys.argv[1], sys.argv[2]
def dump():
    with open(modules_file, "w", encoding="utf-8") as out:
        json.dump(sorted(sys.modules), out)
atexit.register(dump)
sys.argv = ["gateway", "run", "--config", config, "--print"]
from gateway.cli import main
main()
"""

# Never in `gateway run`, whatever its config: other commands' modules and libraries.
OTHER_COMMANDS = (
    "gateway.simulator",  # `gateway simulate`, the demo
    "gateway.cli.demo",
    "gateway.cli.write",
    "gateway.cli.calibrate",
    "gateway.cli.operations",
    "rich.live",  # the demo's live table
    "rich.progress",  # the scan's progress bar
    "rich.table",  # the tables of `profiles`, `read`, `scan`
    "amqtt",  # the demo's embedded broker
    "pymodbus.server",  # pymodbus's servers and clients: the gateway has its own
    "pymodbus.client",
)

# Never in a plain run: the command line's libraries, there only to read `run --config`
# (cli/run reads it); pymodbus, which only the shared bus and the simulator use; the MQTT
# operations, until one is asked for; the network lines, unless a port names one; difflib,
# which only hints at a config's mistakes.
NOT_IN_A_PLAIN_RUN = (
    "typer",
    "rich",
    "click",
    "shellingham",
    "pymodbus",
    "gateway.control.operations",
    "gateway.line.transports.modbus_tcp",
    "gateway.line.transports.rtu_over_tcp",
    "gateway.line.transports.tcp_session",
    "difflib",
)

# Each optional feature's modules: imported if and only if it is configured.
OPTIONAL = {
    "web": ("gateway.web", "aiohttp", "gateway.line.scan", "gateway.control.calibration"),
    "sparkplug": (
        "gateway.publish.sparkplug",
        "gateway.control.sparkplug_commands",
        "google.protobuf",
    ),
    "shared_bus": ("gateway.control.shared_bus",),
    "feeds": ("gateway.control.feeds",),
}

SIMULATED = (
    "line: {baudrate: 19200, parity: E, stopbits: 1}\n"
    "devices:\n"
    "  - {profile: jumo-digiline-odo-s10, address: 1, animate: false}\n"
    "  - {profile: reiss-m0c, address: 10, animate: false, values: {temperature: 17.5}}\n"
)


@pytest.fixture
def line(tmp_path: Path) -> Iterator[Path]:
    with simulate_process(tmp_path, SIMULATED) as (port, _):
        yield port


def plant(port: Path, broker: int, metrics: int, directory: Path, extra: str = "") -> str:
    return (
        f"buses:\n  - {{name: line1, port: {port}, baudrate: 19200, parity: E}}\n"
        "devices:\n"
        "  - {name: aeration, bus: line1, address: 1, profile: jumo-digiline-odo-s10,"
        " poll_interval: 0.5}\n"
        "  - {name: basin, bus: line1, address: 10, profile: reiss-m0c, poll_interval: 0.5}\n"
        f"mqtt: {{host: 127.0.0.1, port: {broker}, base_topic: gw}}\n"
        f"prometheus: {{host: 127.0.0.1, port: {metrics}}}\n"
        f"state_dir: {directory / 'state'}\n"
        f"{extra}"
    )


def modules_of_run(config_text: str, directory: Path, metrics: int) -> set[str]:
    """Run the gateway on ``config_text`` until it polled and was scraped; its modules."""
    config, modules_file = directory / "gateway.yaml", directory / "modules.json"
    config.write_text(config_text, encoding="utf-8")
    with subprocess.Popen(
        [sys.executable, "-c", RUN, str(modules_file), str(config)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    ) as process:
        assert process.stdout is not None
        assert process.stdout.readline(), "the gateway printed no poll cycle"
        # A scrape, so that whatever /metrics imports when asked is imported too.
        url = f"http://127.0.0.1:{metrics}/metrics"
        with urllib.request.urlopen(url, timeout=10) as response:
            assert b"gateway_" in response.read()
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=20)
    assert process.returncode == 0, err
    assert not reported_in(err), err
    return set(json.loads(modules_file.read_text(encoding="utf-8")))


def loaded(modules: set[str], prefixes: tuple[str, ...]) -> set[str]:
    """The modules that are one of ``prefixes`` or inside one of them."""
    return {m for m in modules if any(m == p or m.startswith(f"{p}.") for p in prefixes)}


@pytest.mark.line
@pytest.mark.broker
def test_a_plain_config_imports_no_optional_feature(
    line: Path, broker: Broker, tmp_path: Path
) -> None:
    metrics = free_port()
    modules = modules_of_run(plant(line, broker.port, metrics, tmp_path), tmp_path, metrics)
    # It ran what it should: the bus, MQTT and Prometheus.
    assert {"gateway.app", "gateway.line.engine.worker", "aiomqtt", "prometheus_client"} <= modules
    optional = tuple(name for names in OPTIONAL.values() for name in names)
    assert loaded(modules, optional) == set()
    assert loaded(modules, OTHER_COMMANDS) == set()
    assert loaded(modules, NOT_IN_A_PLAIN_RUN) == set()


@pytest.mark.line
@pytest.mark.broker
def test_each_configured_feature_imports_its_own(
    line: Path, broker: Broker, tmp_path: Path
) -> None:
    metrics = free_port()
    features = (
        f"web: {{enabled: true, port: {free_port()}}}\n"
        "sparkplug: {enabled: true, group_id: water, edge_node_id: plant-gw}\n"
        "shared_bus: {listen: [{host: 127.0.0.1, port: 0}]}\n"
        "feeds:\n"
        "  - {device: aeration, point: compensation_temperature, interval: 60,"
        " source: {device: basin, point: temperature}}\n"
    )
    config = plant(line, broker.port, metrics, tmp_path, features)
    modules = modules_of_run(config, tmp_path, metrics)
    for feature, names in OPTIONAL.items():
        for name in names:
            assert name in modules, f"{feature}: {name} not imported"
    assert loaded(modules, OTHER_COMMANDS) == set()


# --- a plain run's command line, read without typer -----------------------------------------

# The options of `run` in every spelling, their values, and what a plain run is not.
TOKENS = (
    *("run", "--config", "-c", "a.yaml", "b c.yaml", "--config=d.yaml", "--config="),
    *("--print", "--no-print", "--help", "--version", "-x", "--", "", "-", "--conf", "scan"),
)


def typer_reads(args: list[str]) -> tuple[Path, bool | None] | None:
    """What typer hands the run command for ``args``; ``None`` if it runs no gateway."""
    handed: list[tuple[Path, bool | None]] = []

    def record(config: Path, *, show: bool | None) -> None:
        handed.append((config, show))

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(root, "run_command", record)
        try:
            root.app(args, prog_name="gateway", standalone_mode=False)
        except Exception:  # noqa: BLE001 - a usage error, help, a missing file: no run
            return None
    return handed[0] if handed else None


@pytest.mark.parametrize(
    "args",
    [
        ["run", "--config", "a.yaml"],
        ["run", "-c", "a.yaml", "--print"],
        ["run", "--no-print", "--config=d.yaml"],
        ["run", "--config", "a.yaml", "--print", "-c", "b c.yaml", "--no-print"],
    ],
)
def test_the_usual_plain_runs_are_read_without_typer_as_typer_reads_them(args: list[str]) -> None:
    assert plain_run(args, {}) is not None
    assert plain_run(args, {}) == typer_reads(args)


@pytest.mark.parametrize(
    "args",
    [
        ["run", "--config", "a.yaml", "--help"],
        ["run", "--print"],
        ["run", "--config", "-x"],
        ["run", "--config="],
        ["--version", "run", "--config", "a.yaml"],
        ["scan", "--config", "a.yaml"],
    ],
)
def test_help_mistakes_and_other_commands_are_left_to_typer(args: list[str]) -> None:
    assert plain_run(args, {}) is None


def test_a_shell_asking_for_completions_is_left_to_typer() -> None:
    args = ["run", "--config", "a.yaml"]
    assert plain_run(args, {"_GATEWAY_COMPLETE": "bash_complete"}) is None


@fuzz(400)
@given(st.lists(st.sampled_from(TOKENS), max_size=7))
def test_every_command_line_read_without_typer_is_read_so_by_typer(tail: list[str]) -> None:
    args = ["run", *tail]
    plain = plain_run(args, {})
    if plain is not None:
        assert plain == typer_reads(args)
