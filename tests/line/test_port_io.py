"""A local port read and written with one system call each, with pyserial's verdicts.

:mod:`gateway.line.transports.serial_line` replaces pyserial's ``read`` and ``write`` of a local device (its
``select`` loop and timeout objects cost more than the rest of a read); the transport
above must still see what pyserial told it: no data when nothing is there, an exception
it turns into a lost port when the device is gone or the call fails.
"""

from __future__ import annotations

import contextlib
import os
import pty
from typing import TYPE_CHECKING

import pytest
import serial

from gateway.line.transports.serial_line import _direct_io

if TYPE_CHECKING:
    from collections.abc import Iterator

pytestmark = [pytest.mark.line]


@pytest.fixture
def pair() -> Iterator[tuple[int, serial.Serial]]:
    """A pseudo-terminal: its master's descriptor, and its slave as the transport opens it."""
    master, slave = pty.openpty()
    device = serial.Serial(os.ttyname(slave), timeout=0, write_timeout=0)
    os.close(slave)
    _direct_io(device)
    try:
        yield master, device
    finally:
        device.close()
        with contextlib.suppress(OSError):  # unless the test closed it
            os.close(master)


def test_reads_what_arrived_and_nothing_when_nothing_is_there(
    pair: tuple[int, serial.Serial],
) -> None:
    master, device = pair
    assert device.read(1024) == b""  # EAGAIN: no data, as pyserial says with timeout 0
    os.write(master, b"\x01\x03\x02\x00\x07\xf9\x86")
    assert device.read(1024) == b"\x01\x03\x02\x00\x07\xf9\x86"
    assert device.read(1024) == b""


def test_a_device_gone_is_a_serial_exception(pair: tuple[int, serial.Serial]) -> None:
    master, device = pair
    os.close(master)  # unplugged: the slave reads nothing (or EIO), and stays readable
    with pytest.raises(serial.SerialException, match=r"no data|read failed"):
        device.read(1024)


def test_writes_go_out_whole_and_a_failed_write_is_a_serial_exception(
    pair: tuple[int, serial.Serial],
) -> None:
    master, device = pair
    assert device.write(b"\x01\x03\x00\x00\x00\x0a\xc5\xcd") == 8
    assert os.read(master, 64) == b"\x01\x03\x00\x00\x00\x0a\xc5\xcd"
    fd = device.fd
    assert fd is not None
    os.close(fd)  # the descriptor gone under the port
    with pytest.raises(serial.SerialException, match="write failed"):
        device.write(b"\x01")
    device.fd = None  # closed already: pyserial's close must not close it again
    device.is_open = False
