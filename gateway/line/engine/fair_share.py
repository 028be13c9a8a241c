"""Other masters' turns on a line, fair by bus time: between addresses, then their connections.

Other masters share one part of a line's bus time (``bus_share``). Served in the order they
ask, that part goes to whoever asks most, or for the longest reads: a client pipelining
reads of 120 registers (0.29 s each at 9600 baud) took nine tenths of it beside a SCADA
reading two registers at a time, and over fifteen connections it kept the SCADA out of the
queue (exception 06 for nearly every read). Here the next request is the one of the origin
that had the least of the line so far: start-time fair queueing (Goyal, Vin and Cheng,
SIGCOMM 1996) by the bus seconds each transaction took, first between source addresses,
then between the connections of one address. So every address gets the same part however
many connections it opens, and one connection of an address cannot starve another of it.

An origin that asked nothing for a while saves nothing up: its tag starts at the virtual
time, the tag of the request last sent. What one origin leaves unused goes to the others;
nothing is reserved, with one exception: a client that reads one request at a time is
between two requests for a moment after each answer, so for ``ANTICIPATION_S`` after it
the turn is kept for it if it had less. And where the queue is full, a request of an
address holding fewer takes the place of the newest of the address holding the most.

Pure: the bus seconds and the time are passed in.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final, Protocol, TypeVar

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

# A client asking back to back sends its next request within this of its answer: a LAN's
# round trip and the client's own work take a few milliseconds. Holding the line longer
# would keep it from others for a client that was done.
ANTICIPATION_S: Final = 0.05


@dataclass(frozen=True, slots=True)
class Origin:
    """Where another master's request comes from: its source address and connection.

    Example::

        Origin(address="10.0.0.7", connection="10.0.0.7:50412")
    """

    address: str = ""  # the source address: one part of the share per address
    connection: str = ""  # one connection of it ("host:port"): a part of its address's


class Queued(Protocol):
    """A request waiting for the line, as the fair share sees it."""

    @property
    def origin(self) -> Origin:
        """Where it comes from."""

    @property
    def queued_at(self) -> float:
        """When it was queued (monotonic seconds): the older goes first between equals."""


Job = TypeVar("Job", bound=Queued)


class _Tags:
    """Start-time fair queueing of one level: a virtual clock and each flow's finish tag."""

    __slots__ = ("finish", "virtual")

    def __init__(self) -> None:
        self.virtual = 0.0  # the start tag of the transaction last sent
        self.finish: dict[str, float] = {}  # only flows ahead of the clock (they had more)

    def start(self, flow: str) -> float:
        """The flow's start tag: where it left off, or the clock if that is later."""
        return max(self.virtual, self.finish.get(flow, self.virtual))

    def charge(self, flow: str, bus_s: float) -> None:
        """The flow's transaction took ``bus_s``: it went at its start tag, and moves on."""
        start = self.start(flow)
        self.virtual = start
        self.finish[flow] = start + bus_s
        # A flow the clock has reached has nothing over the others: forget it.
        for behind in [f for f, tag in self.finish.items() if tag <= start]:
            del self.finish[behind]


class FairShare:
    """Whose request goes next (:meth:`pick`, :meth:`held_until`), and who pays (:meth:`charge`)."""

    def __init__(self) -> None:
        """No origin has had anything yet."""
        self._addresses = _Tags()
        self._connections: dict[str, _Tags] = {}  # per address with a tag ahead of the clock
        self._answered: dict[Origin, float] = {}  # within ANTICIPATION_S: when

    def pick(self, jobs: Sequence[Job]) -> Job | None:
        """The request to send of ``jobs`` (those that may go now, in the order queued).

        The address with the lowest start tag, then its connection with the lowest, then
        that connection's oldest request; between equal tags the one waiting longest.
        """
        if not jobs:
            return None
        by_address = _grouped(jobs, lambda job: job.origin.address)
        address = min(
            by_address, key=lambda a: (self._addresses.start(a), by_address[a][0].queued_at)
        )
        tags = self._connections.get(address, _Tags())
        by_connection = _grouped(by_address[address], lambda job: job.origin.connection)
        connection = min(
            by_connection, key=lambda c: (tags.start(c), by_connection[c][0].queued_at)
        )
        return by_connection[connection][0]

    def held_until(self, job: Queued, now: float) -> float:
        """When ``job`` may go: ``now``, or later while the turn is kept for one that had less.

        The turn is kept for an origin answered within ``ANTICIPATION_S`` whose address
        (or, of the same address, whose connection) had less than ``job``'s.
        """
        self._forget_answered(now)
        mine = job.origin
        until = now
        for origin, at in self._answered.items():
            if origin != mine and self._behind(origin, mine):
                until = max(until, at + ANTICIPATION_S)
        return until

    def charge(self, origin: Origin, bus_s: float, now: float) -> None:
        """A request of ``origin`` took ``bus_s`` of the line (its gap included); done ``now``."""
        self._addresses.charge(origin.address, bus_s)
        self._connections.setdefault(origin.address, _Tags()).charge(origin.connection, bus_s)
        # An address the clock has reached starts level with the others, its connections
        # too: what is kept is bounded by the origins that had more than their part lately.
        for address in [a for a in self._connections if a not in self._addresses.finish]:
            del self._connections[address]
        self._answered[origin] = now
        self._forget_answered(now)

    def displaced(self, jobs: Sequence[Job], origin: Origin) -> Job | None:
        """The request to refuse so that one of ``origin`` fits a full queue; ``None``: none.

        The newest of the address holding the most, if it holds at least two more than
        ``origin``'s address (one more would only swap the two): so a client that fills
        the queue cannot keep another out of it.
        """
        held = Counter(job.origin.address for job in jobs)
        if not held:
            return None
        address, most = held.most_common(1)[0]
        if most < held[origin.address] + 2:
            return None
        return next(job for job in reversed(jobs) if job.origin.address == address)

    def _behind(self, origin: Origin, other: Origin) -> bool:
        """Whether ``origin`` had less than ``other``: by address, or by connection within one."""
        if origin.address != other.address:
            return self._addresses.start(origin.address) < self._addresses.start(other.address)
        tags = self._connections.get(origin.address, _Tags())
        return tags.start(origin.connection) < tags.start(other.connection)

    def _forget_answered(self, now: float) -> None:
        for origin in [o for o, at in self._answered.items() if at + ANTICIPATION_S <= now]:
            del self._answered[origin]


def _grouped(jobs: Sequence[Job], key: Callable[[Job], str]) -> dict[str, list[Job]]:
    """``jobs`` by ``key``, each group in queue order (dicts keep the first seen first)."""
    groups: dict[str, list[Job]] = {}
    for job in jobs:
        groups.setdefault(key(job), []).append(job)
    return groups
