"""The answer scan without I/O: echoes passed over, answers too early refused, in bytes and times.

The frames are the S10 manual's: a read of the temperature (0x2620, 20.25 as CDAB) and a
function-06 write, whose answer is a copy of its request.
"""

from __future__ import annotations

from gateway.line.transports.answer import AnswerScan
from gateway.wire import frames

READ = frames.read_request(1, 0x2620, 2)
READ_ANSWER = frames.read_response(1, 0x03, [0x0000, 0x41A2])
WRITE = frames.write_single_request(1, 0x25AF, 1)
CHAR_S = 11 / 9600  # 9600 8E1
SENT = 100.0
FLOOR = SENT + len(WRITE.frame) * CHAR_S  # the request on the wire, no turnaround


def scan(request: frames.Request, *, echo: bool = True, known: bool = False) -> AnswerScan:
    return AnswerScan(
        request,
        exceptions=frames.STANDARD_EXCEPTIONS,
        byte_count_16bit=False,
        echo=request.frame if echo else None,
        echo_known=known,
        answer_floor=FLOOR,
        character_s=CHAR_S,
    )


def test_a_reads_echo_is_passed_over_and_the_answer_after_it_taken() -> None:
    looking = scan(READ)
    buffer = bytearray(READ.frame + READ_ANSWER)
    answer = looking.feed(buffer, SENT + 1.0)
    assert answer is not None
    assert answer.registers == (0x0000, 0x41A2)
    assert looking.echo_skipped
    assert looking.consumed == len(READ.frame) + len(READ_ANSWER)
    assert not looking.garbage  # an echo is not noise


def test_half_an_echo_waits_for_the_rest() -> None:
    looking = scan(READ)
    assert looking.feed(bytearray(READ.frame[:5]), SENT + 0.001) is None
    assert not looking.echo_skipped
    assert not looking.garbage


def test_a_writes_copy_in_before_the_wire_allows_is_its_echo_not_its_answer() -> None:
    looking = scan(WRITE)
    too_soon = FLOOR + len(WRITE.frame) * CHAR_S - 0.001  # the answer could not be in yet
    assert looking.feed(bytearray(WRITE.frame), too_soon) is None
    assert looking.echo_skipped
    # The device's own copy, in time: that one is the answer.
    answer = looking.feed(bytearray(WRITE.frame * 2), SENT + 0.05)
    assert answer is not None
    assert (answer.function, answer.address) == (0x06, 0x25AF)
    assert looking.consumed == 2 * len(WRITE.frame)


def test_a_writes_copy_in_time_is_its_answer_unless_the_line_is_known_to_echo() -> None:
    in_time = SENT + 0.05
    assert scan(WRITE).feed(bytearray(WRITE.frame), in_time) is not None
    known = scan(WRITE, known=True)
    assert known.feed(bytearray(WRITE.frame), in_time) is None  # its echo: the answer follows
    assert known.echo_skipped


def test_no_answer_is_taken_before_the_wire_allows_even_without_an_echo_expected() -> None:
    # Echo read back already (``echo: on``): a copy that is complete too soon is still not
    # the answer; it is passed over for good, and the scan waits for the real one.
    looking = scan(WRITE, echo=False)
    assert looking.feed(bytearray(WRITE.frame), SENT + 0.001) is None
    assert looking.early
    assert looking.start == len(WRITE.frame)
