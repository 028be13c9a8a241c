"""The command line with serial device servers: ``gateway simulate --framing tcp``, ``gateway
read --port tcp://…``, and the ``tcp:`` settings checked by ``gateway check-config``."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from typing import TYPE_CHECKING

import pytest

from tests.mqtt_broker import free_port
from tests.rigs import run_gateway, stats_of
from tests.unretrieved import reported_in

if TYPE_CHECKING:
    from collections.abc import Iterator
    from pathlib import Path

SIMULATED = (
    "line: {baudrate: 19200, parity: E, stopbits: 1}\n"
    "devices:\n"
    "  - {profile: jumo-digiline-odo-s10, address: 1, animate: false,"
    " values: {temperature: 20.25, oxygen: {fault: overrange}}}\n"
    "  - {profile: reiss-m0c, address: 10, animate: false, values: {concentration: 0.168}}\n"
)


@pytest.fixture
def converter(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    """``gateway simulate --tcp 127.0.0.1:0 --framing tcp`` in its own process: its URL."""
    path, stats = tmp_path / "sim.yaml", tmp_path / "stats.json"
    path.write_text(SIMULATED, encoding="utf-8")
    command = [sys.executable, "-m", "gateway", "simulate", "--config", str(path)]
    command += ["--tcp", "127.0.0.1:0", "--framing", "tcp", "--stats", str(stats)]
    with subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    ) as sim:
        assert sim.stdout is not None
        banner = sim.stdout.readline()
        match = re.search(r"tcp://127\.0\.0\.1:(\d+)", banner)
        assert match, banner
        yield f"tcp://127.0.0.1:{match.group(1)}", stats
        sim.send_signal(signal.SIGINT)
        _, stderr = sim.communicate(timeout=10)
    assert not reported_in(stderr), stderr


def gateway(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return run_gateway(*args, cwd=cwd)


@pytest.mark.line
def test_read_through_a_modbus_tcp_converter(converter: tuple[str, Path], tmp_path: Path) -> None:
    url, stats = converter
    common = ["--port", url, "--baudrate", "19200", "--parity", "E", "--json"]
    result = gateway(
        "read", *common, "--address", "1", "--profile", "jumo-digiline-odo-s10",
        "temperature", "oxygen", cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["temperature"] == {"value": 20.25, "unit": "°C"}
    assert data["oxygen"] == {"fault": "overrange", "unit": "ppm"}
    reiss = gateway(
        "read", *common, "--address", "10", "--profile", "reiss-m0c", "concentration", cwd=tmp_path
    )
    assert reiss.returncode == 0, reiss.stderr
    assert json.loads(reiss.stdout)["concentration"]["value"] == pytest.approx(0.168, abs=1e-6)
    counters = stats_of(stats)["counters"]
    assert counters["mbap_requests"] >= 3
    assert stats_of(stats)["timing_violations"] == 0


@pytest.mark.line
def test_read_of_an_absent_device_names_the_converters_0b(
    converter: tuple[str, Path], tmp_path: Path
) -> None:
    url, _ = converter
    result = gateway(
        "read", "--port", url, "--baudrate", "19200", "--parity", "E", "--address", "7",
        "--profile", "reiss-m0c", "concentration", "--json", cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 1
    assert json.loads(result.stdout)["concentration"]["comms_error"] == "gateway_target_failed"
    assert "1 of 1 points could not be read" in result.stderr


def test_read_of_a_converter_that_is_not_there(tmp_path: Path) -> None:
    port = free_port()
    result = gateway(
        "read", "--port", f"tcp://127.0.0.1:{port}", "--address", "1",
        "--profile", "reiss-m0c", cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode != 0
    assert (
        f"error: cannot connect to tcp://127.0.0.1:{port}: connection refused (nothing listens "
        "there: check the converter's address, its port and that it is in Modbus TCP mode)"
    ) in " ".join(result.stderr.split())


@pytest.mark.line
def test_simulate_refuses_an_unknown_framing(tmp_path: Path) -> None:
    result = gateway(
        "simulate", "--device", "reiss-m0c:10", "--tcp", "127.0.0.1:0", "--framing", "mbap",
        cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode != 0
    assert "--framing 'mbap': expected rtu (RTU over TCP) or tcp (Modbus TCP)" in result.stderr


def test_check_config_refuses_tcp_settings_on_a_serial_port_and_bad_bounds(tmp_path: Path) -> None:
    config = tmp_path / "hall.yaml"
    config.write_text(
        "buses:\n"
        "  - name: hall\n"
        "    port: /dev/ttyUSB0\n"
        "    tcp: {keepalive_s: 10}\n"
        "  - name: yard\n"
        "    port: tcp://10.0.0.5:502\n"
        "    tcp:\n"
        "      user_timeout_s: -1\n"
        "      silent_requests: -1\n"
        "      keepalive_s: 5\n"
        "  - name: pump\n"
        "    port: tcp://10.0.0.6\n",
        encoding="utf-8",
    )
    result = gateway("check-config", str(config), cwd=tmp_path)
    assert result.returncode == 2
    err = " ".join(result.stderr.split())
    assert (
        "buses[0].tcp (line 4): the tcp settings apply to socket:// and tcp:// ports only, "
        "not to /dev/ttyUSB0; remove them or give the converter's URL"
    ) in err
    assert "buses[1].tcp.user_timeout_s (line 8): Input should be greater than or equal to 0" in err
    assert "buses[1].tcp.silent_requests (line 9)" in err
    assert (
        "buses[2].port (line 12): 'tcp://10.0.0.6': a tcp:// URL needs a host and a port, "
        "e.g. tcp://10.0.0.5:502"
    ) in err


def test_check_config_accepts_tcp_settings_on_network_ports(tmp_path: Path) -> None:
    config = tmp_path / "hall.yaml"
    config.write_text(
        "buses:\n"
        "  - {name: hall, port: 'tcp://10.0.0.5:502', baudrate: 19200, parity: E,\n"
        "     tcp: {keepalive_s: 5, user_timeout_s: 15, connect_pause_s: 0.5}}\n"
        "  - {name: yard, port: 'socket://10.0.0.6:4001', tcp: {silent_requests: 0}}\n"
        "devices:\n"
        "  - {name: tank, bus: hall, address: 10, profile: reiss-m0c}\n",
        encoding="utf-8",
    )
    result = gateway("check-config", str(config), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "OK" in result.stdout


@pytest.mark.line
def test_write_with_a_config_whose_bus_is_a_modbus_tcp_converter(
    converter: tuple[str, Path], tmp_path: Path
) -> None:
    url, stats = converter
    config = tmp_path / "hall.yaml"
    config.write_text(
        "buses:\n"
        f"  - {{name: hall, port: '{url}', baudrate: 19200, parity: E,\n"
        "     tcp: {connect_pause_s: 0.2, request_pause_ms: 5}}\n"
        "devices:\n"
        "  - {name: tank1, bus: hall, address: 1, profile: jumo-digiline-odo-s10}\n"
        "mqtt: {enabled: false}\n"
        f"state_dir: {tmp_path / 'state'}\n",
        encoding="utf-8",
    )
    result = gateway(
        "write", "compensation_temperature", "21.5", "--config", str(config),
        "--device", "tank1", "--json", cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["value"] == 21.5, data
    writes = stats_of(stats)["devices"]["1"]["writes"]
    assert [w["points"] for w in writes] == [["compensation_temperature"]]
    assert stats_of(stats)["timing_violations"] == 0
