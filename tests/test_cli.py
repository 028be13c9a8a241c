"""The ``gateway`` command as users run it: a real process, its output and exit code."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.test_profiles import PROFILE_IDS


def gateway(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gateway", *args],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
        env={"COLUMNS": "200", "PATH": "/usr/bin:/bin", "PYTHONIOENCODING": "utf-8"},
    )


def test_profiles_lists_every_id() -> None:
    result = gateway("profiles")
    assert result.returncode == 0, result.stderr
    for profile_id in PROFILE_IDS:
        assert profile_id in result.stdout
    assert "JUMO digiLine O-DO H20" in result.stdout


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
