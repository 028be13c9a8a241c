"""Command topics: which topics are commands, and what they name (pure, no I/O)."""

from __future__ import annotations

import pytest

from gateway.control.command_router import COMMAND, SET, Route, parse_topic


@pytest.mark.parametrize(
    ("topic", "route"),
    [
        (
            "gw/aeration/compensation_temperature/set",
            Route(SET, "aeration", "compensation_temperature"),
        ),
        ("gw/hygienic/command/measure", Route(COMMAND, "hygienic", "measure")),
        ("gw/aeration/compensation_temperature/set/result", None),  # our own result
        ("gw/hygienic/command/measure/result", None),
        ("gw/aeration/temperature", None),  # a value topic
        ("gw/aeration/status/cap_missing", None),  # a status flag named like nothing here
        ("gw/aeration/state", None),
        ("gw/status", None),
        ("other/aeration/x/set", None),  # another base
        ("gw//x/set", None),  # an empty level
        ("gateway/aeration/x/set", None),  # a base that only starts the same
    ],
)
def test_command_topics(topic: str, route: Route | None) -> None:
    assert parse_topic("gw", topic) == route


def test_a_base_with_levels() -> None:
    assert parse_topic("plant/north/gw", "plant/north/gw/basin/x_span/set") == Route(
        SET, "basin", "x_span"
    )
