"""Which broker of a server list to connect to next: one at a time, in order, then back.

aiomqtt (and paho under it) take one host; the list and its failover are the gateway's.
A lost or refused connection moves to the next server at once, and only a whole round of
failures waits the reconnect backoff, which doubles per round: a cluster's dead node costs
one failed connect, not a backoff. After ``return_to_first_s`` on another server the
session ends cleanly and the first is tried again (``None``: stay), so that a fleet moved
away by a node's restart comes home to the server a plant meant it to use.

The plain topics' connection and the Sparkplug session each keep a walk of their own.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.config.brokers import MqttServer


class ServerWalk:
    """The position in a server list, and how often it moved."""

    def __init__(self, servers: Sequence[MqttServer], *, return_to_first_s: float | None) -> None:
        """Start at the first of ``servers`` (at least one)."""
        if not servers:
            raise ValueError("a server list needs at least one server")
        self.servers = tuple(servers)
        self.return_to_first_s = return_to_first_s
        self.index = 0
        self.switches = 0  # moves to another server since the start

    @property
    def current(self) -> MqttServer:
        """The server to connect to now."""
        return self.servers[self.index]

    @property
    def several(self) -> bool:
        """Whether there is another server to move to."""
        return len(self.servers) > 1

    def next(self) -> bool:
        """Move on after a failure; whether that began a new round (every server failed)."""
        self._go((self.index + 1) % len(self.servers))
        return self.index == 0

    def first(self) -> None:
        """Back to the first server (its time away is up)."""
        self._go(0)

    def stay_for(self) -> float | None:
        """How long a session on the current server may last before going back to the first."""
        return None if self.index == 0 else self.return_to_first_s

    def _go(self, index: int) -> None:
        if index != self.index:
            self.switches += 1
        self.index = index
