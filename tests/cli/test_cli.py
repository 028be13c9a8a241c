"""The ``gateway`` command as users run it: a real process, its output and exit code."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests import paths
from tests.profiles.test_profiles import PROFILE_IDS
from tests.rigs import run_gateway, simulate_process, stats_of
from tests.unretrieved import reported_in
from tests.waiting import wait_until


def gateway(*args: str) -> subprocess.CompletedProcess[str]:
    return run_gateway(*args, cwd=Path(__file__).parent)


def test_profiles_lists_every_id() -> None:
    result = gateway("profiles")
    assert result.returncode == 0, result.stderr
    for profile_id in PROFILE_IDS:
        assert profile_id in result.stdout
    assert "JUMO digiLine O-DO H20" in result.stdout


def test_profiles_lists_whole_ids_on_a_narrow_terminal() -> None:
    # `docker run --rm rs485-gateway profiles` has no terminal: rich takes 80 columns.
    result = run_gateway("profiles", cwd=Path(__file__).parent, columns=80)
    assert result.returncode == 0, result.stderr
    for profile_id in PROFILE_IDS:
        assert profile_id in result.stdout


def test_profiles_json_list() -> None:
    result = gateway("profiles", "--json")
    assert result.returncode == 0, result.stderr
    rows = json.loads(result.stdout)
    assert {row["id"] for row in rows} == PROFILE_IDS
    assert all({"id", "family", "title", "points", "spec"} <= set(row) for row in rows)


def test_show_prints_the_register_map_as_a_table() -> None:
    result = gateway("profiles", "show", "jumo-digiline-odo-s10")
    assert result.returncode == 0, result.stderr
    assert "0x2620" in result.stdout
    assert "temperature" in result.stdout
    assert "CDAB" in result.stdout


def test_show_json_has_the_contract_fields_and_the_expanded_logbook() -> None:
    result = gateway("profiles", "show", "jumo-digiline-odo-h10", "--json")
    assert result.returncode == 0, result.stderr
    points = json.loads(result.stdout)
    for point in points:
        assert {"name", "address", "type", "count", "access", "unit"} <= set(point)
        assert point["access"] in {"r", "rw"}
    entry_types = [p for p in points if p["name"].endswith("_entry_type")]
    assert [p["address"] for p in entry_types] == [0x0600 + n * 0x31 for n in range(10)]
    assert [p["index"] for p in entry_types] == list(range(1, 11))
    by_name = {p["name"]: p for p in points}
    assert by_name["oxygen_unit"]["enum"]["16"] == "percent_volume"
    assert by_name["compensation_temperature"]["storage"] == "volatile"


def test_unknown_profile_is_a_clear_error_and_non_zero_exit() -> None:
    result = gateway("profiles", "show", "jumo-digiline-odo-s11")
    assert result.returncode == 2
    assert "unknown profile 'jumo-digiline-odo-s11'" in result.stderr
    assert result.stdout == ""


def test_version_and_module_entry_point() -> None:
    result = gateway("--version")
    assert result.returncode == 0
    assert result.stdout.strip() == "0.1.0"


# --- gateway read and gateway run against a simulated line ------------------------------


@pytest.fixture
def simulated_line(tmp_path: Path) -> Iterator[tuple[Path, Path]]:
    with simulate_process(
        tmp_path,
        "line: {baudrate: 19200, parity: E, stopbits: 1}\n"
        "devices:\n"
        "  - {profile: jumo-digiline-odo-s10, address: 1, animate: false,"
        " values: {temperature: 20.25, oxygen: {fault: overrange}}}\n"
        "  - {profile: reiss-m0c, address: 10, animate: false, values: {concentration: 0.168}}\n",
    ) as line:
        yield line


def frames_received(stats: Path) -> int:
    return int(stats_of(stats)["counters"].get("frames", 0))


@pytest.mark.line
def test_read_prints_values_and_faults_as_json(simulated_line: tuple[Path, Path]) -> None:
    port, stats = simulated_line
    result = gateway(
        "read",
        "--port",
        str(port),
        "--baudrate",
        "19200",
        "--parity",
        "E",
        "--address",
        "1",
        "--profile",
        "jumo-digiline-odo-s10",
        "temperature",
        "oxygen",
        "status",
        "--json",
    )
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["temperature"] == {"value": 20.25, "unit": "°C"}
    assert data["oxygen"] == {"fault": "overrange", "unit": "ppm"}  # never 2e37
    assert data["status"]["value"]["cap_missing"] is False
    assert frames_received(stats) >= 2
    reiss = gateway(
        "read",
        "--port",
        str(port),
        "--baudrate",
        "19200",
        "--parity",
        "E",
        "--address",
        "10",
        "--profile",
        "reiss-m0c",
        "concentration",
        "sensor_type",
    )
    assert reiss.returncode == 0, reiss.stderr
    assert "0.168" in reiss.stdout
    assert "CP4.0N-M0" in reiss.stdout


@pytest.mark.line
def test_read_of_a_silent_address_fails_clearly(simulated_line: tuple[Path, Path]) -> None:
    port, _ = simulated_line
    result = gateway(
        "read",
        "--port",
        str(port),
        "--baudrate",
        "19200",
        "--parity",
        "E",
        "--address",
        "7",
        "--profile",
        "reiss-m0c",
        "concentration",
        "--json",
    )
    assert result.returncode == 1
    assert json.loads(result.stdout)["concentration"]["comms_error"] == "timeout"
    assert "1 of 1 points could not be read" in result.stderr


# An S10 clock block (6.9: year, month ... second, time-zone offset) dated month 13.
MONTH_13 = (2025, 13, 1, 12, 0, 0, 0)
MONTH_13_HEX = ["0x07E9", "0x000D", "0x0001", "0x000C", "0x0000", "0x0000", "0x0000"]


@pytest.mark.line
def test_read_reports_an_undecodable_value_as_a_fault_of_the_value(tmp_path: Path) -> None:
    """The line worked and the S10 answered: the date it sent is not a date. That is a
    fault of the value, with its registers, not a failed read: exit status 0."""
    clock = {0x2840 + offset: word for offset, word in enumerate(MONTH_13)}
    with simulate_process(
        tmp_path,
        "devices:\n"
        "  - {profile: jumo-digiline-odo-s10, address: 1, animate: false,"
        f" values: {{temperature: 20.25}}, registers: {json.dumps(clock)}}}\n",
    ) as (port, _):
        options = ["--port", str(port), "--address", "1", "--profile", "jumo-digiline-odo-s10"]
        result = gateway("read", *options, "clock", "temperature", "--json")
        table = gateway("read", *options, "clock", "temperature")
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert data["clock"] == {"fault": "undecodable", "raw": MONTH_13_HEX, "unit": None}
    assert data["temperature"] == {"value": 20.25, "unit": "°C"}
    assert "month must be in 1..12" in result.stderr  # why, said once
    assert "could not be read" not in result.stderr
    assert table.returncode == 0, table.stderr
    assert "!undecodable" in table.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--profile", "reiss-m9c", "concentration"], "unknown profile 'reiss-m9c'"),
        (["--profile", "reiss-m0c", "concentrationn"], "has no point 'concentrationn'"),
        (["--profile", "reiss-m0c", "--parity", "X"], "--parity must be N, E or O"),
        (["--profile", "reiss-m0c", "--float-order", "ACBD"], "--float-order 'ACBD'"),
    ],
)
@pytest.mark.line
def test_read_bad_input_sends_nothing(
    simulated_line: tuple[Path, Path], args: list[str], message: str
) -> None:
    port, stats = simulated_line
    result = gateway("read", "--port", str(port), "--address", "10", *args)
    assert result.returncode == 2
    assert message in result.stderr
    assert frames_received(stats) == 0


def test_read_of_a_port_that_does_not_exist(tmp_path: Path) -> None:
    result = gateway(
        "read", "--port", str(tmp_path / "ttyUSB9"), "--address", "1", "--profile", "reiss-m0c"
    )
    assert result.returncode == 2
    assert "cannot open" in result.stderr


@pytest.mark.line
def test_run_polls_until_ctrl_c(simulated_line: tuple[Path, Path], tmp_path: Path) -> None:
    port, stats = simulated_line
    config = tmp_path / "gateway.yaml"
    config.write_text(
        f"buses:\n  - {{name: line1, port: {port}, baudrate: 19200, parity: E}}\n"
        "devices:\n"
        "  - {name: basin_oxygen, bus: line1, address: 1, profile: jumo-digiline-odo-s10,"
        " poll_interval: 0.5}\n"
        "  - {name: basin_chlorine, bus: line1, address: 10, profile: reiss-m0c,"
        " poll_interval: 0.5}\n"
        "mqtt: {enabled: false}\n"
        "prometheus: {enabled: false}\n",
        encoding="utf-8",
    )
    with subprocess.Popen(
        [sys.executable, "-m", "gateway", "run", "--config", str(config), "--print"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    ) as process:
        # Polled a few times over: each sensor's identity, then its values again and again.
        wait_until(
            lambda: all(d["requests"] >= 6 for d in stats_of(stats)["devices"].values()),
            within_s=20,
        )
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=10)
    assert process.returncode == 0, err
    assert not reported_in(err), err
    assert "line1/basin_oxygen online" in out
    assert "temperature=20.25 °C" in out
    assert "oxygen=!overrange" in out
    assert "concentration=0.168 ppm" in out
    assert json.loads(stats.read_text(encoding="utf-8"))["timing_violations"] == 0


def test_run_refuses_a_broken_config(tmp_path: Path) -> None:
    config = tmp_path / "broken.yaml"
    config.write_text(
        "buses:\n  - {name: line1, port: /dev/ttyUSB0}\n"
        "devices:\n"
        "  - {name: a, bus: line1, address: 1, profile: reiss-m0c}\n"
        "  - {name: b, bus: line1, address: 1, profile: jumo-tecline-xx}\n",
        encoding="utf-8",
    )
    result = gateway("run", "--config", str(config))
    assert result.returncode == 2
    assert "devices[1].address (line 5)" in result.stderr
    assert "devices[1].profile (line 5)" in result.stderr


def test_check_config_reports_every_problem_with_key_and_line(tmp_path: Path) -> None:
    config = tmp_path / "broken.yaml"
    config.write_text(
        "buses:\n"
        "  - {name: line1, port: /dev/ttyUSB0}\n"
        "devices:\n"
        "  - {name: tank, bus: line1, address: 1, profile: reiss-m0c, poll_interval: 0.2, timeout: 0.5}\n"
        "  - {name: tank, bus: line1, address: 1, profile: reiss-m0x}\n"
        "  - {name: pool, bus: line2, address: 3, profile: jumo-tecline-cl2,"
        " points: {concentrationn: {interval: 5}}}\n",
        encoding="utf-8",
    )
    result = gateway("check-config", str(config))
    assert result.returncode == 2
    err = result.stderr
    assert "devices[0].timeout (line 4)" in err  # longer than the poll interval
    assert "devices[1].name (line 5)" in err  # two devices with one name
    assert "devices[1].address (line 5)" in err  # duplicate address on the bus
    assert "devices[1].profile (line 5)" in err  # unknown profile
    assert "devices[2].bus (line 6)" in err  # unknown bus
    assert "devices[2].points.concentrationn (line 6)" in err  # unknown point
    assert "problems" in err


def test_check_config_accepts_the_examples() -> None:
    examples = paths.ROOT / "config"
    for example in ["plant.yaml", "jumo-tecline.yaml", "reiss-m0c-m3c.yaml"]:
        result = gateway("check-config", str(examples / example))
        assert result.returncode == 0, result.stderr
        assert "OK" in result.stdout


@pytest.mark.line
def test_sigterm_stops_cleanly_and_sighup_does_not_kill(
    simulated_line: tuple[Path, Path], tmp_path: Path
) -> None:
    port, stats = simulated_line
    config = tmp_path / "gateway.yaml"
    config.write_text(
        f"buses:\n  - {{name: line1, port: {port}, baudrate: 19200, parity: E}}\n"
        "devices:\n  - {name: basin, bus: line1, address: 10, profile: reiss-m0c, poll_interval: 0.2}\n"
        "mqtt: {enabled: false}\nprometheus: {enabled: false}\n",
        encoding="utf-8",
    )
    with subprocess.Popen(
        [sys.executable, "-m", "gateway", "run", "--config", str(config), "--print"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    ) as process:
        # Signals go once the service polls (its first printed cycle): on a loaded machine
        # the imports alone can take longer than any fixed sleep, and SIGHUP before the
        # handlers are in place ends the process as its default action says.
        assert process.stdout is not None
        assert process.stdout.readline(), "the service printed no poll cycle"
        process.send_signal(signal.SIGHUP)
        time.sleep(0.5)
        assert process.poll() is None, "SIGHUP must not stop the service"
        started = time.monotonic()
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=10)
    assert process.returncode == 0, err
    assert not reported_in(err), err
    assert time.monotonic() - started < 5
    assert "applied in" in err, err  # SIGHUP reloads the unchanged file: nothing to change
    assert "nothing changed" in err, err
    assert "basin concentration=0.168 ppm" in out
    assert json.loads(stats.read_text(encoding="utf-8"))["timing_violations"] == 0


def test_gateway_run_does_not_import_what_only_other_commands_need(tmp_path: Path) -> None:
    # What `gateway run` holds in memory for as long as it runs: the simulator, the bus
    # scan and the calibrations belong to other commands (imported there, when asked for).
    script = (
        "import atexit, json, sys\n"
        "atexit.register(lambda: print(json.dumps(sorted(sys.modules))))\n"
        "from gateway.cli import main\n"
        f"sys.argv = ['gateway', 'run', '--config', {str(tmp_path / 'none.yaml')!r}]\n"
        "main()\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 2, result.stderr  # the config file does not exist
    modules = set(json.loads(result.stdout.splitlines()[-1]))
    assert "gateway.app" in modules
    unwanted = (
        "gateway.simulator",
        "gateway.line.scan",
        "gateway.control.calibration",
        "gateway.web",  # the page, and aiohttp with it, only when web.enabled
        "aiohttp",
        "rich.progress",
        "rich.live",
    )
    assert not {m for m in modules if m.startswith(unwanted)}
