"""Hypothesis settings and frame strategies shared by the fuzz tests (``tests/*/test_fuzz_*.py``).

Each fuzz test names the example count that keeps the whole fuzz suite within about a
minute of a normal test run. ``FUZZ_SCALE=N`` multiplies every count by ``N`` for a
longer hunt, e.g. before a release or after touching the frame or command code::

    FUZZ_SCALE=20 .venv/bin/python -m pytest -q tests/*/test_fuzz_*.py

Deadlines are off: the I/O tests spend real time on a pseudo-terminal by design, and a
slow CI machine must not turn that into a failure.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any, Final, TypeVar

import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from gateway.wire import frames

if TYPE_CHECKING:
    from collections.abc import Callable

FUZZ_SCALE_VARIABLE: Final = "FUZZ_SCALE"
TEST_TIMEOUT_S: Final = 120  # pyproject.toml [tool.pytest.ini_options] timeout
_Test = TypeVar("_Test", bound="Callable[..., Any]")


def _scale() -> int:
    raw = os.environ.get(FUZZ_SCALE_VARIABLE, "1")
    try:
        scale = int(raw)
    except ValueError:
        raise ValueError(f"{FUZZ_SCALE_VARIABLE} must be a whole number, got {raw!r}") from None
    if scale < 1:
        raise ValueError(f"{FUZZ_SCALE_VARIABLE} must be 1 or more, got {scale}")
    return scale


def fuzz(examples: int) -> Callable[[_Test], _Test]:
    """Run a fuzz test for ``examples`` examples, times ``FUZZ_SCALE``.

    The per-test timeout (120 s in ``pyproject.toml``) grows with the scale: a timeout
    inside a Hypothesis test is taken for a failure and shrunk, which never ends.
    """
    scale = _scale()
    chosen = settings(
        max_examples=examples * scale,
        deadline=None,
        # Strategies that build frames from a drawn request, and examples that wait on a
        # real line, are slow to generate and to run on purpose.
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )

    def apply(test: _Test) -> _Test:
        timed: _Test = pytest.mark.timeout(TEST_TIMEOUT_S * scale)(chosen(test))
        return timed

    return apply


# --- strategies shared by the frame and line fuzz tests -----------------------------------

FUNCTIONS: Final = (
    frames.READ_HOLDING,
    frames.READ_INPUT,
    frames.WRITE_SINGLE,
    frames.WRITE_MULTIPLE,
)
DEVICES = st.integers(1, 247)
WORDS = st.integers(0, frames.MAX_REGISTER_VALUE)


@st.composite
def requests(draw: st.DrawFn) -> frames.Request:
    """A request the master may send: a read (03/04) or a write (06/16), any size allowed."""
    device = draw(DEVICES)
    function = draw(st.sampled_from(FUNCTIONS))
    if function in frames.READ_FUNCTIONS:
        count = draw(st.integers(1, frames.MAX_READ_REGISTERS))
        address = draw(st.integers(0, frames.MAX_ADDRESS - count + 1))
        return frames.read_request(device, address, count, function=function)
    if function == frames.WRITE_SINGLE:
        return frames.write_single_request(device, draw(WORDS), draw(WORDS))
    values = draw(st.lists(WORDS, min_size=1, max_size=frames.MAX_WRITE_REGISTERS))
    address = draw(st.integers(0, frames.MAX_ADDRESS - len(values) + 1))
    return frames.write_multiple_request(device, address, values)


@st.composite
def good_answers(draw: st.DrawFn, request: frames.Request, *, quirk: bool) -> bytes:
    """A correct answer to ``request``: data (with the quirk where allowed) or an exception."""
    if draw(st.integers(0, 4)) == 0:
        return frames.exception_response(
            request.device, request.function, draw(st.integers(0, 255))
        )
    if request.function in frames.READ_FUNCTIONS:
        registers = draw(st.lists(WORDS, min_size=request.count, max_size=request.count))
        sixteen = quirk and draw(st.booleans())
        return frames.read_response(
            request.device, request.function, registers, byte_count_16bit=sixteen
        )
    if request.function == frames.WRITE_SINGLE:
        return frames.write_single_response(request.device, request.address, request.values[0])
    return frames.write_multiple_response(request.device, request.address, request.count)


MUTATIONS: Final = (
    "flip",
    "truncate",
    "extend",
    "insert",
    "delete",
    "replace",
    "device",
    "function",
    "byte_count",
)


@st.composite
def mutations(draw: st.DrawFn, frame: bytes, *, recrc: bool) -> bytes:
    """``frame`` with one to three random edits; with ``recrc`` the CRC is made valid again.

    Edits under a fresh CRC get past the checksum and test the structural checks; edits
    without it must all be caught by the CRC (or the length).
    """
    data = bytearray(frame[:-2] if recrc else frame)
    for kind in draw(st.lists(st.sampled_from(MUTATIONS), min_size=1, max_size=3)):
        size = len(data)
        if kind == "flip" and size:
            bit = draw(st.integers(0, 8 * size - 1))
            data[bit // 8] ^= 1 << (bit % 8)
        elif kind == "truncate" and size:
            del data[draw(st.integers(0, size - 1)) :]
        elif kind == "extend":
            data += draw(st.binary(min_size=1, max_size=8))
        elif kind == "insert":
            at = draw(st.integers(0, size))
            data[at:at] = draw(st.binary(min_size=1, max_size=4))
        elif kind == "delete" and size:
            at = draw(st.integers(0, size - 1))
            del data[at : draw(st.integers(at + 1, min(size, at + 4)))]
        elif kind == "replace" and size:
            data[draw(st.integers(0, size - 1))] = draw(st.integers(0, 255))
        elif kind in {"device", "function", "byte_count"}:
            index = ("device", "function", "byte_count").index(kind)
            if size > index:
                # A different byte: XOR with a non-zero mask.
                data[index] ^= draw(st.integers(1, 255))
    body = bytes(data)
    return body + frames.crc16(body) if recrc else body
