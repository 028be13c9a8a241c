"""``gateway write`` as users run it: a real process against the simulator on a pty."""

from __future__ import annotations

import json
import subprocess
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import pytest

from tests.cli.test_cli import simulated_line
from tests.rigs import run_gateway, stats_of

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line]

__all__ = ["simulated_line"]  # the fixture, used by name


Gateway = Callable[..., subprocess.CompletedProcess[str]]


@pytest.fixture
def gateway(tmp_path: Path) -> Gateway:
    """``gateway ARGS`` in the test's folder: a write without --config keeps its records
    in ``state/`` of the folder it runs in, as for a user."""

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return run_gateway(*args, cwd=tmp_path)

    return run


def written(stats: Path, address: int) -> list[dict[str, Any]]:
    return list(stats_of(stats)["devices"][str(address)]["writes"])


def line_options(port: Path, address: int, profile: str) -> list[str]:
    return [
        "--port",
        str(port),
        "--baudrate",
        "19200",
        "--parity",
        "E",
        "--address",
        str(address),
        "--profile",
        profile,
    ]


def test_write_a_ram_point_and_read_it_back(
    simulated_line: tuple[Path, Path], gateway: Gateway
) -> None:
    port, stats = simulated_line
    result = gateway(
        "write",
        "compensation_temperature",
        "21.5",
        *line_options(port, 1, "jumo-digiline-odo-s10"),
        "--json",
    )
    assert result.returncode == 0, result.stderr
    outcome = json.loads(result.stdout)
    assert outcome == {
        "device": "address_1",
        "point": "compensation_temperature",
        "written": True,
        "value": 21.5,
        "registers": [0x0000, 0x41AC],
        "flash": False,
        "record": 1,  # the write's record in state/records.sqlite (its outcome is 2)
    }
    [record] = written(stats, 1)
    assert (record["function"], record["address"], record["values"]) == (16, 0x25B0, [0, 0x41AC])


def test_a_flash_point_needs_permission_and_counts_in_the_ledger(
    simulated_line: tuple[Path, Path], tmp_path: Path, gateway: Gateway
) -> None:
    port, stats = simulated_line
    config = tmp_path / "gateway.yaml"
    config.write_text(
        f"buses:\n  - {{name: line1, port: {port}, baudrate: 19200, parity: E}}\n"
        "devices:\n"
        "  - {name: basin, bus: line1, address: 10, profile: reiss-m0c,"
        " flash_writes: [x_span], flash_write_budget: 1}\n"
        f"state_dir: {tmp_path / 'state'}\n",
        encoding="utf-8",
    )
    refused = gateway("write", "x_zero", "1.5", "--config", str(config), "--device", "basin")
    assert refused.returncode == 2
    assert "flash-backed point not allowed for device basin" in refused.stderr
    assert written(stats, 10) == []

    ok = gateway("write", "x_span", "55.5", "--config", str(config), "--device", "basin")
    assert ok.returncode == 0, ok.stderr
    assert "x_span: written (0000 425E); the device holds 55.5" in ok.stdout
    spent = gateway("write", "x_span", "56", "--config", str(config), "--device", "basin")
    assert spent.returncode == 2
    assert "budget of 1 writes per day for basin/x_span is spent" in spent.stderr
    assert [(w["address"], w["values"]) for w in written(stats, 10)] == [(0x0208, [0, 0x425E])]
    assert (tmp_path / "state" / "flash-writes.sqlite").is_file()


def test_bad_input_writes_nothing(simulated_line: tuple[Path, Path], gateway: Gateway) -> None:
    port, stats = simulated_line
    cases = {
        ("oxygen", "8"): "the point is read-only",
        ("compensation_temperature", "warm"): "float32 needs a number",
        ("compensation_control", "{broken"): "malformed JSON",
        ("no_such_point", "1"): "no point 'no_such_point'",
        ("no[such]", "1"): "no point 'no[such]'",  # brackets are text, not rich markup
    }
    for (point, value), message in cases.items():
        result = gateway("write", point, value, *line_options(port, 1, "jumo-digiline-odo-s10"))
        assert result.returncode == 2, (point, result.stderr)
        assert message in result.stderr, (point, result.stderr)
    data = json.loads(stats.read_text(encoding="utf-8"))
    assert data["counters"].get("frames", 0) == 0  # not even a read
