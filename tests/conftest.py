"""Fixtures shared by the test modules: a real mosquitto broker."""

from __future__ import annotations

from typing import TYPE_CHECKING

import pytest

from tests.mqtt_broker import Broker

if TYPE_CHECKING:
    from collections.abc import Iterator
    from pathlib import Path


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    """mosquitto on a free port, stopped after the test (tests may stop and start it)."""
    directory = tmp_path / "broker"
    directory.mkdir()
    running = Broker(directory)
    running.start()
    yield running
    running.stop()
