"""The tier guard catches what it is there for: a need used but not declared by a marker."""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field

import pytest

from tests import tiers


@pytest.mark.parametrize(
    ("command", "needs"),
    [
        (["/usr/sbin/mosquitto", "-c", "mosquitto.conf"], ["broker"]),
        ([sys.executable, "-m", "gateway", "simulate", "--config", "sim.yaml"], ["line"]),
        (["/opt/gateway/bin/gateway", "demo", "--no-live"], ["line", "broker"]),
        ([sys.executable, "-m", "gateway", "read", "--port", "/dev/ttyUSB0"], []),
        ([sys.executable, "-m", "gateway", "run", "--config", "demo.yaml"], []),  # a file name
        ("podman build -t gateway .", ["podman"]),
        (["deploy/test-image"], ["podman"]),
        (["mount", "--bind", "/dev/pts/3", "ttyA"], ["root"]),
        (["node", "/x/playwright/driver/package/cli.js", "run-driver"], ["browser"]),
        (["mosquitto_passwd", "-b", "passwd", "plant", "secret"], []),
        ([], []),
    ],
)
def test_a_started_program_is_told_by_what_it_needs(
    command: list[str] | str, needs: list[str]
) -> None:
    assert [need for need, _ in tiers.needs_of_command(command)] == needs


@dataclass
class Marked:
    """A test item as the guard sees it: its id and its markers."""

    nodeid: str
    markers: set[str] = field(default_factory=set)

    def get_closest_marker(self, name: str) -> object | None:
        return name if name in self.markers else None


def test_a_need_used_without_its_marker_is_named_with_what_used_it() -> None:
    item = Marked("tests/x.py::test_y", {"line"})
    used = {"line": ["a pseudo-terminal"], "broker": ["mosquitto", "mosquitto"]}
    why = tiers.failure(item, used)  # type: ignore[arg-type]
    assert why == (
        "tests/x.py::test_y used what its markers do not declare; "
        "add @pytest.mark.broker (mosquitto)"
    )
    declared = Marked("tests/x.py::test_y", {"line", "broker"})
    assert tiers.failure(declared, used) is None  # type: ignore[arg-type]
    assert tiers.failure(Marked("tests/x.py::test_z"), {}) is None  # type: ignore[arg-type]


def test_a_side_by_side_test_that_is_not_timing_is_named() -> None:
    """``side_by_side`` orders a test beside others within the timing step: alone, it would
    run three at a time beside any test of the first step."""
    item = Marked("tests/x.py::test_y", {"line", "side_by_side"})
    assert tiers.failure(item, {"line": ["a pseudo-terminal"]}) == (  # type: ignore[arg-type]
        "tests/x.py::test_y is marked side_by_side but not timing: add @pytest.mark.timing"
    )
    both = Marked("tests/x.py::test_y", {"line", "side_by_side", "timing"})
    assert tiers.failure(both, {"line": ["a pseudo-terminal"]}) is None  # type: ignore[arg-type]


@pytest.mark.line
def test_a_pseudo_terminal_opened_by_a_test_is_noted_as_a_line() -> None:
    master, slave = os.openpty()
    os.close(master)
    os.close(slave)
    assert tiers.USAGE.used.get("line") == ["a pseudo-terminal"]


def test_nothing_is_noted_for_a_test_that_stays_in_python() -> None:
    assert tiers.USAGE.active
    assert tiers.USAGE.used == {}


def test_every_need_the_quick_tier_leaves_out_is_a_declared_marker(
    pytestconfig: pytest.Config,
) -> None:
    declared = {line.split(":", 1)[0] for line in pytestconfig.getini("markers")}
    assert set(tiers.NEEDS) | {"timing", "side_by_side"} <= declared
