"""Fixtures shared by the test modules: a real mosquitto broker, the guard every test runs
under against asyncio exceptions nobody retrieved, and the check of its tier's markers
(:mod:`tests.tiers`)."""

from __future__ import annotations

import gc
import inspect
import os
from typing import TYPE_CHECKING

import pytest

from gateway.shared.host_clock import TRUST_VARIABLE
from tests import tiers, unretrieved
from tests.mqtt_broker import Broker

if TYPE_CHECKING:
    from collections.abc import Generator, Iterator
    from pathlib import Path


# The test host's kernel does not hold its clock synchronised, and no test may change that;
# the gateway would refuse every date written into a simulated sensor (set-clock, the
# calibrations' stamps). The tests run as a plant without time sync that trusts its clock;
# tests/control/test_clock_trust.py and tests/app/test_clock_step.py take the override away.
os.environ.setdefault(TRUST_VARIABLE, "true")


@pytest.fixture(autouse=True, scope="session")
def no_unretrieved_exceptions_at_all() -> Iterator[None]:
    """Whatever no single test was held to (see below) fails the session at its end.

    Only asyncio's reports: a ResourceWarning that the last collection sets off there
    belongs to no test (pytest's own directory iterators among them).

    What exists before the first test (the modules, the collected tests, their
    parameters) is frozen out of the collections: they run after hundreds of tests, and
    a full one went through all of it each time (0.14 s on average, 22 s of CPU in the
    quick tier). Only what the tests make can hold an unretrieved exception.
    """
    gc.collect()
    gc.freeze()
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


# --- tiers: what a test needs, declared by its markers and checked (tests/tiers.py) --------


def pytest_configure(config: pytest.Config) -> None:
    tiers.register(config)
    tiers.install()


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> Generator[None]:  # noqa: ARG001
    """Note from the first fixture on: a fixture's broker or pty is the test's need too."""
    tiers.USAGE.start()
    return (yield)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    """A test that passed but used what its markers do not declare fails."""
    report = yield
    if call.when == "call" or (call.when == "setup" and report.outcome != "passed"):
        used = tiers.USAGE.stop()
        tiers.record(item, used)
        why = tiers.failure(item, used)
        if why is not None and report.outcome == "passed":
            report.outcome = "failed"
            report.longrepr = why
    return report
