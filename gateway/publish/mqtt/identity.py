"""One identity, one gateway: a retained owner marker that a copied config cannot share.

A plant copies a cabinet's config to the next cabinet and forgets to change the base topic
or the client id. Two gateways with one client id take each other's session over, each
reconnect throwing the other off, for ever; two with one base topic write over each
other's retained values. Neither says so. This claim makes the second one see it and stand
down within seconds, with the first one untouched.

Each run of the gateway has a random start id. At every connection it subscribes to
``{base}/owner`` and publishes its claim there (retained, QoS 1): start id, client id,
host, process id and the wall time it started. What it then reads there decides:

- its own claim: nothing to do;
- another claim, retained, before this run's claim has once stood: the previous holder (a
  dead run of this gateway, or a live other one); this claim replaces it, and a live
  holder will answer;
- another claim, live, or retained once this run's claim has stood (someone claimed while
  this one was away): this gateway held the identity first: it *defends*, publishing its
  claim again, naming the other's start id as ``contested_by``, and says ``online`` again;
- a claim that names this run's start id as ``contested_by``: another gateway held the
  identity first. This one *stands down*: it logs why, ``/healthz`` says so, and it does
  not connect again until its config is fixed (a reload or a restart). Two that claimed
  at the same instant each defend; the larger start id stands down.

Until its claim has once *stood* a run publishes nothing but ``online`` and its claim, at
every connection: the claim must come back from the broker (a round trip) and, if the
marker named another run (a live holder, or this gateway's own last run),
:data:`CLAIM_ANSWER_S` more must pass. A live holder's answer reaches it within that, and
the newcomer stands down having written over none of the holder's retained messages (its
backlog, availability, values and records head). Every connection, not only the first: a
newcomer with the holder's client id is thrown off by the holder's return before its wait
ends, and reads the defence only at its next connection. A broker without a marker (a new
one) costs no wait. Once the claim has stood the run never yields, and nothing waits. The
identity's messages (a defence, ``online`` again) go at once, never behind a backlog, so
that a holder draining an outage's queue answers in time.

A defence also sends again what the newcomer may have written over in the moment before
it stood down (the retained availability, discovery configs and records head: the
connection's ``for_a_new_server``), at most once in :data:`RESEND_AFTER_DEFENCE_S`: each
claim is answered, but a client flooding the marker gets no copy of every discovery config
for each. And the holder watches its own ``{base}/status``: an ``offline`` said there
while it is connected is another client's last will (a newcomer that stood down and whose
connection closed uncleanly, seen with mosquitto 2.0.11, or a copied config's session
taken over), and would show every entity of this gateway as unavailable in Home
Assistant: the holder says ``online`` again.

The marker is plain MQTT, read by any broker: no broker feature (MQTT 5's "session taken
over" reason) is needed, and the take-over loop of a shared client id ends with the
second connection of the newcomer.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import uuid
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import Final

from gateway.publish.message import Message

_LOGGER = logging.getLogger(__name__)

OWNER_LEVEL: Final = "owner"  # {base}/owner
# A live holder's time to answer a claim once it has come back from the broker: its event
# loop's turn and one message through the broker (a few milliseconds on a LAN; a loaded
# 2-core machine has shown tens). Waited until the run's claim has once stood.
CLAIM_ANSWER_S: Final = 1.0
# After a defence the retained state is sent again at most this often (the connection's
# clock): a newcomer's claim is answered at once, a flood of claims only claim by claim.
RESEND_AFTER_DEFENCE_S: Final = 10.0


class IdentityTakenError(Exception):
    """Another gateway held this identity first: this one stands down."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Claim:
    """What ``{base}/owner`` holds: who publishes under this base topic."""

    start_id: str
    client_id: str
    host: str
    pid: int
    since: str  # the wall time the run started (for people: runs are told apart by start_id)
    contested_by: str | None = None

    def payload(self) -> bytes:
        """The marker's JSON."""
        data = {
            "start_id": self.start_id,
            "client_id": self.client_id,
            "host": self.host,
            "pid": self.pid,
            "since": self.since,
        }
        if self.contested_by is not None:
            data["contested_by"] = self.contested_by
        return json.dumps(data).encode()

    @classmethod
    def parse(cls, payload: bytes) -> Claim | None:
        """A claim, or None for what is not one (an empty payload clears the marker)."""
        try:
            data = json.loads(payload)
        except ValueError:
            return None
        if not isinstance(data, dict) or not isinstance(data.get("start_id"), str):
            return None
        contested = data.get("contested_by")
        pid = data.get("pid")
        return cls(
            start_id=data["start_id"],
            client_id=str(data.get("client_id", "")),
            host=str(data.get("host", "")),
            pid=pid if isinstance(pid, int) else 0,
            since=str(data.get("since", "")),
            contested_by=contested if isinstance(contested, str) else None,
        )

    def who(self) -> str:
        """The claimant as a person reads it."""
        return f"client id {self.client_id} on {self.host} (pid {self.pid}, since {self.since})"


class IdentityGuard:
    """This run's claim on ``{base}/owner`` and the verdict on what is read there."""

    def __init__(self, base: str, client_id: str, *, start_id: str | None = None) -> None:
        """Claim ``base`` as ``client_id``; a random start id unless one is given (tests)."""
        self.base = base
        self.topic = f"{base}/{OWNER_LEVEL}"
        self.status_topic = f"{base}/status"
        self.mine = Claim(
            start_id=start_id or uuid.uuid4().hex,
            client_id=client_id,
            host=socket.gethostname(),
            pid=os.getpid(),
            since=datetime.now(UTC).isoformat(timespec="seconds"),
        )
        self.echoed = False  # this session's claim read back from the broker
        self.held_before = False  # another run's claim read retained in this session
        self.stood = False  # a session's wait ended with the claim unanswered: never yields now
        self.contested: set[str] = set()  # start ids this run defended against

    def claim(self) -> Message:
        """The claim published at every connection (retained, QoS 1)."""
        self.echoed = False
        self.held_before = False
        return Message(topic=self.topic, payload=self.mine.payload(), qos=1, retain=True)

    def judge(self, payload: bytes, *, retained: bool) -> list[Message]:
        """What to publish in answer to a marker read; raises if this run must stand down."""
        other = Claim.parse(payload)
        if other is not None and other.start_id == self.mine.start_id:
            self.echoed = True
        if other is None or other.start_id == self.mine.start_id:
            return []
        if other.contested_by == self.mine.start_id:
            stand_down = other.start_id not in self.contested or self.mine.start_id > other.start_id
            if stand_down:
                raise IdentityTakenError(
                    f"another gateway publishes under base topic {self.base!r}: "
                    f"{other.who()}; it was here first. This gateway ({self.mine.who()}) "
                    "stopped publishing: give it its own mqtt.base_topic and mqtt.client_id "
                    "(and sparkplug.edge_node_id), then reload"
                )
            return []  # both defended at once: the larger start id stands down, not this one
        if retained and not self.stood:
            self.held_before = True
            return []  # the previous holder, maybe a dead run: a live one will answer
        return self._defend(other)

    @property
    def newcomer(self) -> bool:
        """This run's claim has not yet stood: a live holder may yet answer it.

        Once it has stood (:meth:`has_stood`) this run held the identity first: a claim
        read then is defended, never yielded to, so nothing need wait.
        """
        return not self.stood

    @property
    def answer_awaited(self) -> bool:
        """Before the claim has stood the marker named another run: it may answer.

        Read once this session's claim is back (:attr:`echoed`): a retained marker reaches
        a subscriber before anything published after the subscription.
        """
        return self.newcomer and self.held_before

    def has_stood(self) -> None:
        """A session's wait ended and no holder answered: the identity is this run's."""
        self.stood = True

    def answer_status(self, payload: bytes, *, retained: bool) -> list[Message]:
        """What to publish in answer to ``{base}/status`` read while connected.

        A retained ``offline`` arrives at the subscription, before this session says
        ``online``: nothing to answer. A live one is another client's last will.
        """
        if retained or payload != b"offline":
            return []
        _LOGGER.warning(
            "MQTT: 'offline' was said on %s while this gateway is connected (another "
            "client's last will: a copied config's gateway that stood down?): said online again",
            self.status_topic,
        )
        return [self._online()]

    def _online(self) -> Message:
        return Message.text(self.status_topic, "online", qos=1, retain=True)

    def _defend(self, other: Claim) -> list[Message]:
        self.contested.add(other.start_id)
        _LOGGER.error(
            "MQTT: another gateway claims base topic %r, %s; this one has held it since %s "
            "and told it to stand down: give one of them its own identity",
            self.base,
            other.who(),
            self.mine.since,
        )
        defence = replace(self.mine, contested_by=other.start_id)
        return [
            Message(topic=self.topic, payload=defence.payload(), qos=1, retain=True),
            self._online(),
        ]
