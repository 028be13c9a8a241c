"""The shared bus without I/O: framing, request checks, answers, client policy, config.

The fuzz tests throw random and mutated bytes at the socket framers and the request
parser; whatever they accept must frame anew into a request a Modbus slave parses to the
same function, address and count (so nothing malformed reaches the line).
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.config import ConfigProblems, parse_config
from gateway.control.shared_bus.framing import FramingError, RtuFramer, TcpFramer
from gateway.control.shared_bus.pdu import (
    ClientRequest,
    RequestRefusedError,
    answer_pdu,
    line_request,
    parse_request,
)
from gateway.control.shared_bus.policy import client_for, client_policies, origin_of
from gateway.control.shared_bus.throttle import Throttle
from gateway.wire import frames
from tests.fuzzing import fuzz

# --- requests ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("pdu", "code"),
    [
        ("", 0x01),
        ("08 0000 0000", 0x01),  # diagnostics: no family documents it
        ("2B 0E 01 00", 0x01),  # device identification: neither
        ("03 0000 0000", 0x03),  # a read of no register
        ("03 0000 007E", 0x03),  # 126 registers: more than any family answers
        ("03 0000", 0x03),  # cut short
        ("03 FFFF 0002", 0x02),  # past the end of the map
        ("06 0206", 0x03),
        ("10 0206 0002 03 000000", 0x03),  # byte count is not twice the count
        ("10 0206 0002 04 0000", 0x03),  # fewer bytes than the byte count
        ("10 0206 007C F8" + "00" * 248, 0x03),  # 124 registers: over the write limit
    ],
)
def test_a_request_the_gateway_cannot_pass_on_gets_the_exception_modbus_names(
    pdu: str, code: int
) -> None:
    with pytest.raises(RequestRefusedError) as refused:
        parse_request(bytes.fromhex(pdu))
    assert refused.value.code == code


def test_requests_are_framed_for_the_line_as_the_manuals_print_them() -> None:
    # S10 manual 2.4.1 example: read 2 words at 0x2600 of device 8.
    read = parse_request(bytes.fromhex("03 2600 0002"))
    assert line_request(read, 8).frame == bytes.fromhex("08 03 26 00 00 02 CF DA")
    # tecLine manual 2.4.3 example: write 153.0 (CDAB) to 0x0208 of device 1.
    write = parse_request(bytes.fromhex("10 0208 0002 04 0000 4319"))
    assert write == ClientRequest(function=16, address=0x0208, count=2, values=(0, 0x4319))
    assert line_request(write, 1).frame == bytes.fromhex("01 10 02 08 00 02 04 00 00 43 19 1B 93")
    # H10/H20 manual 2.4.2 example: write 1 to 0x3009 of device 1 (function 06).
    single = parse_request(bytes.fromhex("06 3009 0001"))
    assert line_request(single, 1).frame == bytes.fromhex("01 06 30 09 00 01 97 08")


def test_the_answer_is_the_devices_pdu_byte_for_byte() -> None:
    # S10 manual 2.4.1: the answer 08 03 04 BD C2 7D 70 C6 17, parsed, then passed on.
    read = parse_request(bytes.fromhex("03 2600 0002"))
    line = line_request(read, 8)
    answer = bytes.fromhex("08 03 04 BD C2 7D 70 C6 17")
    assert answer_pdu(read, frames.parse_response(line, answer)) == answer[1:-2]
    # A digiLine string with the two-byte byte count: passed on as the device sent it.
    name = parse_request(bytes.fromhex("03 0100 0002"))
    line = line_request(name, 1)
    quirky = frames.read_response(1, 3, [0x4142, 0x0000], byte_count_16bit=True)
    response = frames.parse_response(line, quirky, byte_count_16bit=True)
    assert answer_pdu(name, response) == quirky[1:-2]
    assert quirky[1:4] == bytes.fromhex("03 00 04")


# --- framing -----------------------------------------------------------------------------


def test_modbus_tcp_frames_are_cut_where_their_header_says() -> None:
    framer = TcpFramer()
    one = struct.pack(">HHHB", 7, 0, 6, 20) + bytes.fromhex("0300000006")
    two = struct.pack(">HHHB", 8, 0, 6, 2) + bytes.fromhex("0300100002")
    assert framer.decode(one[:9]) is None  # more bytes needed
    cut = framer.decode(one + two)
    assert cut is not None
    assert (cut.used, cut.unit, cut.transaction, cut.pdu) == (12, 20, 7, one[7:])
    assert framer.encode(bytes.fromhex("8306"), 20, 7) == bytes.fromhex("0007 0000 0003 14 8306")


@pytest.mark.parametrize(
    "header",
    [
        "0001 0001 0006 14",  # protocol id 1: not Modbus
        "0001 0000 0001 14",  # length 1: a unit id and no function
        "0001 0000 00FF 14",  # 255: longer than any PDU can be
    ],
)
def test_a_modbus_tcp_header_that_cannot_be_one_ends_the_connection(header: str) -> None:
    with pytest.raises(FramingError):
        TcpFramer().decode(bytes.fromhex(header) + bytes(12))


def test_rtu_frames_need_their_crc() -> None:
    framer = RtuFramer()
    good = frames.read_request(20, 0, 6).frame
    cut = framer.decode(good + b"\x01")
    assert cut is not None
    assert (cut.used, cut.unit, cut.pdu) == (8, 20, good[1:-2])
    assert framer.decode(good[:5]) is None
    # Bytes that fail the CRC at their function's length may be a frame of another
    # length: the silence after them says where it ends, and then the CRC decides.
    bad = good[:-1] + bytes([good[-1] ^ 0xFF])
    assert framer.decode(bad) is None
    with pytest.raises(FramingError):
        framer.decode(bad, silent=True)
    assert framer.encode(bytes.fromhex("8306"), 20, 0) == frames.exception_response(20, 3, 6)


def _rtu(body: str) -> bytes:
    data = bytes.fromhex(body)
    return data + frames.crc16(data)


@pytest.mark.parametrize(
    ("frame", "length"),
    [
        ("14 11", 4),  # report server id (Modbus application protocol 6.13)
        ("14 07", 4),  # read exception status
        ("14 2B 0E 01 00", 7),  # read device identification, basic (6.21)
        ("14 08 0000 1234", 8),  # diagnostics, return query data
        ("14 16 0004 00F2 0025", 10),  # mask write register
        ("14 18 04DE", 6),  # read FIFO queue
        ("14 0F 0013 000A 02 CD01", 11),  # write multiple coils: its byte count
        ("14 17 0003 0006 000E 0003 06 00FF 00FF 00FF", 19),  # read/write registers
    ],
)
def test_rtu_frames_of_other_functions_are_cut_at_their_length(frame: str, length: int) -> None:
    data = _rtu(frame)
    assert len(data) == length
    following = frames.read_request(20, 0, 2).frame  # a client that does not wait
    first = RtuFramer().decode(data + following)
    assert first is not None
    assert (first.used, first.unit, first.pdu) == (length, 0x14, data[1:-2])
    second = RtuFramer().decode((data + following)[first.used :])
    assert second is not None
    assert second.pdu == following[1:-2]


def test_an_rtu_frame_of_unknown_length_ends_at_the_silence() -> None:
    framer = RtuFramer()
    private = _rtu("14 41 00 01 02 03 04 05 06 07 08")  # a function no standard knows
    assert framer.decode(private) is None  # more may come, until a silence
    cut = framer.decode(private, silent=True)
    assert cut is not None
    assert (cut.used, cut.pdu) == (len(private), private[1:-2])
    # A read cut short, its CRC over what came: a frame of the wrong length (exception 03).
    short = _rtu("14 03 00 00 02")
    assert framer.decode(short) is None
    cut = framer.decode(short, silent=True)
    assert cut is not None
    assert parse_request_code(cut.pdu) == 0x03
    with pytest.raises(FramingError):
        framer.decode(bytes(2 * 256 + 1))  # no frame in twice the longest: given up


def parse_request_code(pdu: bytes) -> int:
    try:
        parse_request(pdu)
    except RequestRefusedError as refused:
        return refused.code
    return 0


@fuzz(400)
@given(st.binary(max_size=300))
def test_any_bytes_on_a_modbus_tcp_socket_give_a_frame_a_wait_or_a_clean_close(
    data: bytes,
) -> None:
    _check_cut(TcpFramer(), data)


@fuzz(400)
@given(st.binary(max_size=300))
def test_any_bytes_on_an_rtu_socket_give_a_frame_a_wait_or_a_clean_close(data: bytes) -> None:
    _check_cut(RtuFramer(), data)
    # After a silence: a frame or a close, never a wait.
    try:
        cut = RtuFramer().decode(data, silent=True)
    except FramingError:
        return
    assert cut is not None
    assert 0 < cut.used <= len(data)


def _check_cut(framer: TcpFramer | RtuFramer, data: bytes) -> None:
    try:
        cut = framer.decode(data)
    except FramingError:
        return
    if cut is None:
        return
    assert 0 < cut.used <= len(data)
    _check_request(cut.pdu)


@fuzz(600)
@given(
    st.one_of(
        st.binary(max_size=260),
        st.tuples(st.sampled_from([3, 4, 6, 16]), st.integers(0, 0xFFFF), st.integers(0, 130)).map(
            lambda t: bytes([t[0]]) + struct.pack(">HH", t[1], t[2])
        ),
        st.tuples(st.integers(0, 0xFFFF), st.integers(0, 130), st.binary(max_size=260)).map(
            lambda t: bytes([16]) + struct.pack(">HHB", t[0], t[1], len(t[2]) % 256) + t[2]
        ),
    )
)
def test_whatever_a_client_sends_the_line_gets_a_well_formed_request_or_nothing(
    pdu: bytes,
) -> None:
    _check_request(pdu)


def _check_request(pdu: bytes) -> None:
    try:
        request = parse_request(pdu)
    except RequestRefusedError as refused:
        code = refused.code
    else:
        code = 0
    assert code in {0, 0x01, 0x02, 0x03}
    if code:
        return
    line = line_request(request, 20)
    slave = frames.parse_request(line.frame)  # the simulator's own parser: CRC, lengths
    assert (slave.function, slave.address, slave.count) == (
        request.function,
        request.address,
        request.count,
    )
    assert slave.values == request.values
    assert line.frame[1:-2] == pdu  # the request as the client sent it, nothing added


# --- who may do what ---------------------------------------------------------------------


def _config(shared_bus: str, devices: str = "") -> str:
    return (
        "buses: [{name: a, port: /dev/ttyUSB0}, {name: b, port: /dev/ttyUSB1}]\n"
        "devices:\n"
        "  - {name: cl2, bus: a, address: 20, profile: jumo-tecline-cl2}\n"
        "  - {name: oxygen, bus: b, address: 20, profile: jumo-digiline-odo-h10"
        f"{devices}}}\n"
        f"{shared_bus}"
    )


def test_clients_are_told_apart_by_where_they_connect_from() -> None:
    config = parse_config(
        _config(
            "shared_bus:\n"
            "  listen: [{port: 1502}]\n"
            "  clients:\n"
            "    - {name: scada, networks: [10.0.0.0/24], cache_max_age: 2}\n"
            "    - name: service\n"
            "      networks: ['10.0.1.7', '::1']\n"
            "      writes: [{device: cl2, registers: ['0x0206-0x020B']}]\n",
            ", unit_id: 21",
        ),
        environ={},
    )
    policies = client_policies(config.shared_bus.clients)
    assert client_for(policies, "10.0.0.99").name == "scada"
    assert client_for(policies, "::ffff:10.0.0.5").name == "scada"  # IPv4 on a v6 socket
    assert client_for(policies, "10.0.1.7").name == "service"
    assert client_for(policies, "::1").name == "service"
    assert client_for(policies, "192.168.1.1").name == "other"
    service = client_for(policies, "10.0.1.7")
    service.check_write("cl2", ClientRequest(function=16, address=0x0206, count=6))
    with pytest.raises(RequestRefusedError) as outside:
        service.check_write("cl2", ClientRequest(function=16, address=0x020A, count=3))
    assert (outside.value.code, outside.value.label) == (0x02, "register_not_allowed")
    with pytest.raises(RequestRefusedError) as elsewhere:
        service.check_write("oxygen", ClientRequest(function=6, address=0x2013, count=1))
    assert (elsewhere.value.code, elsewhere.value.label) == (0x01, "write_not_allowed")
    with pytest.raises(RequestRefusedError):
        client_for(policies, "10.0.0.1").check_write(
            "cl2", ClientRequest(function=6, address=0x0206, count=1)
        )


def test_a_connection_takes_turns_as_its_address_then_as_itself() -> None:
    # One machine is one address for the fair share, over IPv4 or IPv6-mapped IPv4.
    v4, mapped = origin_of(("10.0.0.5", 4000)), origin_of(("::ffff:10.0.0.5", 4001))
    assert (v4.address, v4.connection) == ("10.0.0.5", "10.0.0.5:4000")
    assert (mapped.address, mapped.connection) == ("10.0.0.5", "::ffff:10.0.0.5:4001")
    assert origin_of(("fe80::1", 4002)).address == "fe80::1"


def test_two_buses_with_the_same_address_need_a_unit_id_for_the_shared_bus() -> None:
    parse_config(_config(""), environ={})  # no shared bus: the addresses may repeat
    with pytest.raises(ConfigProblems) as problems:
        parse_config(_config("shared_bus: {listen: [{port: 1502}]}\n"), environ={})
    text = str(problems.value)
    assert "devices[1].address (line 4)" in text
    assert "give one of them a unit_id" in text


@pytest.mark.parametrize(
    ("section", "where"),
    [
        ("{listen: [{port: 1502}], clients: [{name: x, networks: [10.0.0.0/33]}]}", "networks"),
        (
            (
                "{listen: [{port: 1502}], clients: [{name: x, networks: [10.0.0.1],"
                " writes: [{device: nosuch}]}]}"
            ),
            "unknown device 'nosuch'",
        ),
        (
            (
                "{listen: [{port: 1502}], clients: [{name: x, networks: [10.0.0.1],"
                " writes: [{device: cl2, registers: ['0x020B-0x0206']}]}]}"
            ),
            "first <= last",
        ),
        ("{listen: [{port: 1502}], bus_share: 1.0}", "bus_share"),
    ],
)
def test_a_broken_shared_bus_section_is_named(section: str, where: str) -> None:
    with pytest.raises(ConfigProblems) as problems:
        parse_config(_config(f"shared_bus: {section}\n", ", unit_id: 21"), environ={})
    assert where in str(problems.value)
    assert "shared_bus" in str(problems.value)


# --- the rate limit ----------------------------------------------------------------------


def test_the_rate_limit_lets_a_burst_through_then_spaces_requests_and_sheds_past_max_wait() -> None:
    throttle = Throttle(max_wait_s=1.0)
    # 2 a second: a second's worth (2) at once, then one every 0.5 s, promised in order
    # (connections of one address take turns); a turn later than 1 s away is refused and
    # takes no token.
    waits = [throttle.reserve("10.0.0.5", 2.0, 0.0) for _ in range(5)]
    assert waits == [0.0, 0.0, 0.5, 1.0, None]
    assert throttle.reserve("10.0.0.6", 2.0, 0.0) == 0.0  # another address: its own bucket
    assert throttle.reserve("10.0.0.5", 2.0, 1.0) == 0.5  # two refilled, two promised
    assert throttle.reserve("10.0.0.5", 2.0, 10.0) == 0.0  # idle: full again, no more
    assert throttle.reserve("10.0.0.5", 2.0, 10.0) == 0.0
    assert throttle.reserve("10.0.0.5", 2.0, 10.0) == 0.5
