"""The suite's guard against asyncio exceptions nobody retrieved.

A task or future that ends with an exception nobody awaits is only reported when it is
garbage-collected, by asyncio's logger at ERROR ("Task exception was never retrieved"),
often long after the test that caused it, and never as a failure. The unplug of a serial
port did that for months. So every test collects garbage at its end and fails on such a
report (:func:`guard`), and the tests that run the gateway as its own process fail on
such a line in its output (:func:`reported_in`).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import re
import warnings
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Iterator

# asyncio's own wording (base_futures/futures.py and tasks.py: Future.__del__).
UNRETRIEVED: Final = re.compile(r"(?:Task|Future) exception was never retrieved")

_ACTIVE: list[Catcher] = []  # nested guards: the innermost one takes a report


class UnretrievedExceptionError(AssertionError):
    """An asyncio task or future ended with an exception that nobody retrieved."""


class Catcher(logging.Handler):
    """Keeps the unretrieved-exception reports asyncio's logger emits (each with its trace)."""

    def __init__(self) -> None:
        """Catch from ERROR up, where asyncio reports them."""
        super().__init__(logging.ERROR)
        self.reports: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        """Keep a report with its exception, drop everything else asyncio says."""
        if not _ACTIVE or _ACTIVE[-1] is not self:
            return  # a guard inside this one is watching (a test of the guard itself)
        message = record.getMessage()
        if UNRETRIEVED.search(message):
            if record.exc_info is not None:
                message += "\n" + logging.Formatter().formatException(record.exc_info)
            self.reports.append(message)


def reported_in(output: str) -> list[str]:
    """The lines of a process's output (stderr, a log file) that report one."""
    return [line for line in output.splitlines() if UNRETRIEVED.search(line)]


def check(catcher: Catcher, *, collect: bool = True, other_warnings: bool = True) -> None:
    """Collect garbage (that is when asyncio reports), then fail on any report caught.

    A full collection costs tens of milliseconds in the test process: ``collect=False``
    is for code that ran no event loop, where only a report already made can come.
    ``other_warnings=False`` silences the ResourceWarnings a collection may set off in
    objects that are not the tests' (at the session's end: a directory iterator pytest
    itself left open, which the error filter made a failure after every test passed).
    """
    if collect:
        with warnings.catch_warnings():
            if not other_warnings:
                warnings.simplefilter("ignore", ResourceWarning)
            gc.collect()
    if catcher.reports:
        reports = "\n\n".join(catcher.reports)
        raise UnretrievedExceptionError(f"asyncio reported unretrieved exceptions:\n{reports}")


@contextlib.contextmanager
def guard(*, collect: bool = True, other_warnings: bool = True) -> Iterator[Catcher]:
    """Watch asyncio's logger for the block; fail at its end if a report came."""
    catcher = Catcher()
    logger = logging.getLogger("asyncio")
    logger.addHandler(catcher)
    _ACTIVE.append(catcher)
    try:
        yield catcher
        check(catcher, collect=collect, other_warnings=other_warnings)
    finally:
        _ACTIVE.remove(catcher)
        logger.removeHandler(catcher)
