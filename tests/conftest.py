"""Fixtures shared by the test modules: a real mosquitto broker, and the guard every test
runs under against asyncio exceptions nobody retrieved."""

from __future__ import annotations

import inspect
import os
from typing import TYPE_CHECKING

import pytest

from gateway.publish.host_clock import TRUST_VARIABLE
from tests import unretrieved
from tests.mqtt_broker import Broker

if TYPE_CHECKING:
    from collections.abc import Iterator
    from pathlib import Path

# The test host's kernel does not hold its clock synchronised, and no test may change that;
# the gateway would refuse every date written into a simulated sensor (set-clock, the
# calibrations' stamps). The tests run as a plant without time sync that trusts its clock;
# tests/test_clock_trust.py and tests/test_clock_step.py take the override away.
os.environ.setdefault(TRUST_VARIABLE, "true")


@pytest.fixture(autouse=True, scope="session")
def no_unretrieved_exceptions_at_all() -> Iterator[None]:
    """Whatever no single test was held to (see below) fails the session at its end.

    Only asyncio's reports: a ResourceWarning that the last collection sets off there
    belongs to no test (pytest's own directory iterators among them).
    """
    with unretrieved.guard(other_warnings=False):
        yield


@pytest.fixture(autouse=True)
def no_unretrieved_exceptions(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail the test if asyncio reports a task or future exception nobody retrieved.

    Autouse fixtures are set up before pytest-asyncio's event loop, so this one ends
    after the loop is closed: tasks that died with the loop are collected and reported
    here, against the test that left them. Garbage is collected after tests that can
    have run a loop (coroutines, and tests of modules that use asyncio, which covers
    ``asyncio.run``); a collection after each of the thousands of pure codec and plan
    cases would make the suite several times slower.
    """
    test = getattr(request.node, "obj", None)
    loop = inspect.iscoroutinefunction(test) or "asyncio" in vars(request.module)
    with unretrieved.guard(collect=loop):
        yield


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    """mosquitto on a free port, stopped after the test (tests may stop and start it)."""
    directory = tmp_path / "broker"
    directory.mkdir()
    running = Broker(directory)
    running.start()
    yield running
    running.stop()
