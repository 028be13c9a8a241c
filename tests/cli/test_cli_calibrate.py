"""``gateway calibrate`` as users run it: a real process against the simulator on a pty."""

from __future__ import annotations

import json
import subprocess
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from gateway.control.calibration import catalogue
from gateway.control.flash import FlashLedger
from gateway.profiles import get_profile
from tests.rigs import run_gateway, simulate_process, stats_of

if TYPE_CHECKING:
    from collections.abc import Iterator

SIMULATED = (
    "line: {baudrate: 19200, parity: E, stopbits: 1}\n"
    "devices:\n"
    # 76.5 nA at 0.5 ppm: X_Span 153 nA/ppm, the tecLine 2.4.3 example (00 00 43 19).
    "  - {profile: jumo-tecline-cl2, address: 20, animate: false, values: {cell_current: 76.5}}\n"
    "  - {profile: jumo-digiline-odo-h10, address: 2, animate: false}\n"
)
LINE = ("--baudrate", "19200", "--parity", "E")
CL2 = ("--address", "20", "--profile", "jumo-tecline-cl2", *LINE)
H10 = ("--address", "2", "--profile", "jumo-digiline-odo-h10", *LINE)


def gateway(cwd: Path, *args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
    """Run ``gateway``; in ``cwd``, where a command without --config keeps ``state/``."""
    return run_gateway(*args, cwd=cwd, stdin=stdin)


@pytest.fixture
def line(tmp_path: Path) -> Iterator[tuple[Path, Path]]:
    with simulate_process(tmp_path, SIMULATED) as simulated:
        yield simulated


def writes_to(stats: dict[str, Any], address: int) -> list[tuple[int, int, list[int]]]:
    return [
        (w["function"], w["address"], w["values"]) for w in stats["devices"][str(address)]["writes"]
    ]


@pytest.mark.line
def test_slope_calibration_end_to_end_as_json(line: tuple[Path, Path], tmp_path: Path) -> None:
    port, stats_path = line
    result = gateway(
        tmp_path,
        "calibrate",
        "slope",
        "--port",
        str(port),
        *CL2,
        "--reference",
        "0.5",
        "--samples",
        "2",
        "--every",
        "0.2",
        "--at",
        "2019-03-08T13:10",
        "--yes",
        "--json",
    )
    assert result.returncode == 0, result.stderr
    outcome = json.loads(result.stdout)  # stdout is the JSON alone; progress went to stderr
    assert outcome["status"] == "calibrated"
    assert [(w["point"], w["registers"]) for w in outcome["writes"]] == [
        ("x_zero", [0x0000, 0x0000]),
        ("x_span", [0x0000, 0x4319]),
        ("calibration_stamp", [0x716E, 0xB75E]),
    ]
    assert outcome["values"]["cell_current_samples"] == [76.5, 76.5]
    assert outcome["values"]["stamp_number"] == 1903081310
    assert outcome["record"]["history"][0] == {
        "x_zero": 0.0,
        "x_span": 153.0,
        "stamp": "2019-03-08T13:10",
    }
    assert all(check["ok"] for check in outcome["checks"])
    assert "to write 0x0208 x_span = 153" in result.stderr
    stats = stats_of(stats_path)
    assert writes_to(stats, 20) == [
        (16, 0x0206, [0x0000, 0x0000]),
        (16, 0x0208, [0x0000, 0x4319]),
        (16, 0x020A, [0x716E, 0xB75E]),
    ]
    assert stats["timing_violations"] == 0
    ledger = FlashLedger(tmp_path / "state" / "flash-writes.sqlite")
    assert ledger.total("address_20", "x_span") == 1  # the CLI counted its flash writes
    ledger.close()


@pytest.mark.line
def test_answering_no_writes_nothing_and_exits_1(line: tuple[Path, Path], tmp_path: Path) -> None:
    port, stats_path = line
    result = gateway(tmp_path, "calibrate", "nominal", "--port", str(port), *CL2, stdin="n\n")
    assert result.returncode == 1
    assert "to write 0x0208 x_span = 22" in result.stdout  # the plan is shown before asking
    assert "[y/N]" in result.stdout
    assert "declined: nothing was written" in result.stderr
    assert writes_to(stats_of(stats_path), 20) == []


@pytest.mark.line
def test_h10_zero_point_with_mode_and_logbook(line: tuple[Path, Path], tmp_path: Path) -> None:
    port, stats_path = line
    result = gateway(
        tmp_path,
        "calibrate",
        "zero",
        "--port",
        str(port),
        *H10,
        "--mode",
        "wet",
        "--at",
        "2025-02-10T08:30:15+01:00",
        "--yes",
        "--json",
    )
    assert result.returncode == 0, result.stderr
    outcome = json.loads(result.stdout)
    assert outcome["procedure"] == "oxygen_zero"
    assert outcome["record"]["entry_type"] == "zero_point"
    assert outcome["record"]["date"] == "2025-02-10T08:30:15+01:00"
    assert "logbook entry 1 (newest) after: zero_point" in result.stderr
    stats = stats_of(stats_path)
    assert writes_to(stats, 2) == [
        (6, 0x3009, [1]),
        (16, 0x300A, [2025, 2, 10, 8, 30, 15, 60]),
        (16, 0x3003, [0, 0]),
    ]
    assert stats["timing_violations"] == 0


@pytest.mark.line
def test_a_spent_budget_from_the_config_refuses_with_exit_2(
    line: tuple[Path, Path], tmp_path: Path
) -> None:
    port, stats_path = line
    config = tmp_path / "gateway.yaml"
    config.write_text(
        f"buses:\n  - {{name: line1, port: {port}, baudrate: 19200, parity: E}}\n"
        "devices:\n"
        "  - {name: pool_chlorine, bus: line1, address: 20, profile: jumo-tecline-cl2,"
        " flash_write_budget: 0}\n"
        f"state_dir: {tmp_path / 'state'}\n"
        "mqtt: {enabled: false}\nprometheus: {enabled: false}\n",
        encoding="utf-8",
    )
    result = gateway(
        tmp_path,
        "calibrate",
        "slope",
        "--config",
        str(config),
        "--device",
        "pool_chlorine",
        "--reference",
        "0.5",
        "--samples",
        "1",
        "--yes",
    )
    assert result.returncode == 2
    assert "budget of 0 writes per day for pool_chlorine/x_zero is spent" in result.stderr
    assert "nothing was written" in result.stderr
    assert writes_to(stats_of(stats_path), 20) == []


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("calibrate", "zero", *CL2, "--mode", "wet"), "--mode is for the H10/H20"),
        (("calibrate", "zero", *H10, "--samples", "5"), "--samples is for the tecLine/Reiss"),
        (("calibrate", "slope", *H10, "--reference", "8"), "has no slope calibration"),
        (("calibrate", "end-value", *CL2, "--reference", "20"), "has no end-value calibration"),
    ],
)
@pytest.mark.line
def test_a_procedure_for_another_family_is_refused(
    line: tuple[Path, Path], tmp_path: Path, args: tuple[str, ...], message: str
) -> None:
    port, stats_path = line
    result = gateway(tmp_path, *args, "--port", str(port), "--yes")
    assert result.returncode == 2
    assert message in result.stderr
    stats = stats_of(stats_path)
    assert writes_to(stats, 2) == writes_to(stats, 20) == []


def test_a_bad_date_is_a_usage_error_before_the_port_is_opened(tmp_path: Path) -> None:
    result = gateway(
        tmp_path,
        "calibrate",
        "nominal",
        "--port",
        str(tmp_path / "ttyNONE"),
        *CL2,
        "--at",
        "8 March 2019",
    )
    assert result.returncode == 2
    assert "is not ISO 8601" in result.stderr
    assert "cannot open" not in result.stderr


@pytest.mark.line
def test_now_is_the_default_stamp(line: tuple[Path, Path], tmp_path: Path) -> None:
    port, _ = line
    before = datetime.now(UTC).astimezone().replace(tzinfo=None, second=0, microsecond=0)
    result = gateway(tmp_path, "calibrate", "nominal", "--port", str(port), *CL2, "-y", "--json")
    assert result.returncode == 0, result.stderr
    stamp = datetime.fromisoformat(json.loads(result.stdout)["values"]["stamp"])
    assert before <= stamp <= datetime.now(UTC).astimezone().replace(tzinfo=None)


@pytest.mark.line
def test_a_check_without_samples_reads_as_often_as_the_catalogue_says(
    line: tuple[Path, Path], tmp_path: Path
) -> None:
    """The command line applies the catalogue's defaults (the page's twin is in
    ``tests/control/test_calibration_catalogue.py``): one reading, as the manuals read the current."""
    port, stats_path = line
    result = gateway(
        tmp_path, "calibrate", "check", "--port", str(port), *CL2, "--reference", "0.5", "--json"
    )
    assert result.returncode == 0, result.stderr
    outcome = json.loads(result.stdout)
    assert outcome["status"] == "checked"
    readings = outcome["values"]["cell_current_samples"]
    assert readings == [76.5] * catalogue.procedure("check").defaults().integer("samples")
    assert len(readings) == 1
    assert "cell_current sample 1/1: 76.5 nA" in result.stderr
    assert writes_to(stats_of(stats_path), 20) == []


def test_the_procedures_are_listed_with_their_defaults_and_sources(tmp_path: Path) -> None:
    result = gateway(tmp_path, "calibrate", "procedures", "--profile", "jumo-tecline-cl2")
    assert result.returncode == 0, result.stderr
    text = result.stdout
    for procedure in catalogue.offered(get_profile("jumo-tecline-cl2")):
        assert f"gateway calibrate {procedure.command}" in text
    assert "--samples" in text
    assert "tecLine annex 7.3.1 steps 2-3" in text
    assert "gateway calibrate end-value" not in text
    everything = gateway(tmp_path, "calibrate", "procedures", "--json")
    listed = json.loads(everything.stdout)
    assert [p["id"] for p in listed] == [p.id for p in catalogue.PROCEDURES]
    end_value = next(p for p in listed if p["id"] == "oxygen_end_value")
    assert end_value["profiles"] == ["jumo-digiline-odo-h10", "jumo-digiline-odo-h20"]
    refused = gateway(tmp_path, "calibrate", "procedures", "--profile", "no-such-sensor")
    assert refused.returncode == 2
    assert "no-such-sensor" in refused.stderr
