"""Our frames read the same as pymodbus reads them: an implementation we did not write.

:mod:`gateway.wire.frames` builds and reads functions 03, 04, 06 and 16 and exception
answers itself (``struct``, no pymodbus on a plain run's path). Every request it builds and
every correct answer to one is decoded here by pymodbus's own PDU decoder as well, master
side and slave side, and the two readings must agree to the register: function, address,
count, values, exception code.
"""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymodbus.pdu import DecodePDU

from gateway.errors import DeviceExceptionError
from gateway.wire import frames
from tests.fuzzing import fuzz, good_answers, requests

SERVER = DecodePDU(is_server=True)  # reads requests, as a slave does
CLIENT = DecodePDU(is_server=False)  # reads answers, as a master does


def _pdu(frame: bytes) -> bytes:
    """The PDU of an RTU frame: no address, no CRC (Modbus over serial line 2.1)."""
    return frame[1:-2]


@fuzz(400)
@given(requests())
def test_every_request_we_build_reads_the_same_in_pymodbus(request: frames.Request) -> None:
    theirs = SERVER.decode(_pdu(request.frame))
    assert theirs is not None
    assert theirs.function_code == request.function
    assert theirs.address == request.address
    if request.function in frames.READ_FUNCTIONS:
        assert theirs.count == request.count
    else:
        assert tuple(theirs.registers) == request.values
    ours = frames.parse_request(request.frame)
    assert (ours.device, ours.function, ours.address, ours.count, ours.values) == (
        request.device,
        request.function,
        request.address,
        request.count,
        request.values,
    )


@fuzz(400)
@given(st.data())
def test_every_correct_answer_reads_the_same_in_pymodbus(data: st.DataObject) -> None:
    request = data.draw(requests())
    answer = data.draw(good_answers(request, quirk=False))
    theirs = CLIENT.decode(_pdu(answer))
    assert theirs is not None
    if answer[1] & 0x80:  # an exception answer
        assert theirs.exception_code == answer[2]
        with pytest.raises(DeviceExceptionError) as raised:
            frames.parse_response(request, answer)
        assert raised.value.code == theirs.exception_code
        return
    ours = frames.parse_response(request, answer)
    assert ours.function == theirs.function_code == request.function
    if request.function in frames.READ_FUNCTIONS:
        assert ours.registers == tuple(theirs.registers)
    elif request.function == frames.WRITE_SINGLE:  # the echo: checked against the request
        assert (ours.address, request.values) == (theirs.address, tuple(theirs.registers))
    else:
        assert (ours.address, ours.count) == (theirs.address, theirs.count)
