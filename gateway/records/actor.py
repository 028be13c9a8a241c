"""Who asked for a change, where from and why: the actor every record names.

21 CFR Part 11 §11.10(e) and EU GMP Annex 11 §9 ask of an audit trail who did it, when,
what, and why. The "who" is known only where a request comes in (the page's session, the
command line's operating-system user, the MQTT connection, the shared bus's client), and
the write it causes happens floors below, sometimes in a task started for it (a
calibration run). So the actor travels in a context variable: each way in says who is
acting (:func:`acting`), every write under it is recorded with that actor, and a task
started under it inherits it, as asyncio tasks copy the context they are created in. A
write under no actor at all is recorded as :data:`UNATTRIBUTED`, never dropped.
"""

from __future__ import annotations

import contextlib
import contextvars
import getpass
import os
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Iterator, Mapping

# The user a record names for the page's one password (a plant that wants no accounts).
SHARED_PASSWORD: Final = "shared password"  # noqa: S105 - a name, not a password


class Via(StrEnum):
    """The way a request came in."""

    PAGE = "page"
    CLI = "cli"
    MQTT = "mqtt"
    SPARKPLUG = "sparkplug"
    SHARED_BUS = "shared-bus"
    GATEWAY = "gateway"  # the gateway itself: a reload, the host clock, a sensor's own history
    UNKNOWN = "unknown"


@dataclass(frozen=True, slots=True, kw_only=True)
class Actor:
    """A person or a named system, the way it came in, and the reason it gave.

    ``user`` is a signed-in user's name on the page (:data:`SHARED_PASSWORD` for the
    page's one password), the operating-system user on the command line, the broker
    username of an MQTT or Sparkplug connection, a shared-bus client's address. ``detail``
    says more of where from (the page's client address, ``sudo`` by whom, the MQTT client
    id and topic). ``signed`` is true when the user gave the password again for this act
    (Part 11 §11.200's signature at a calibration or a verification).
    """

    user: str
    via: Via
    detail: str = ""
    reason: str = ""
    signed: bool = False

    def because(self, reason: str) -> Actor:
        """The same actor, with the reason a request gave (an empty one keeps the old)."""
        return replace(self, reason=reason) if reason else self

    def as_dict(self) -> dict[str, object]:
        """The fields as a record stores them."""
        return {
            "user": self.user,
            "via": str(self.via),
            "detail": self.detail,
            "reason": self.reason,
            "signed": self.signed,
        }


UNATTRIBUTED: Final = Actor(user="unattributed", via=Via.UNKNOWN)
GATEWAY: Final = Actor(user="gateway", via=Via.GATEWAY)

_CURRENT: contextvars.ContextVar[Actor] = contextvars.ContextVar(
    "gateway_actor", default=UNATTRIBUTED
)


def current() -> Actor:
    """The actor of the request being served (:data:`UNATTRIBUTED` outside any)."""
    return _CURRENT.get()


@contextlib.contextmanager
def acting(actor: Actor) -> Iterator[Actor]:
    """Everything inside (and every task started inside) acts for ``actor``."""
    token = _CURRENT.set(actor)
    try:
        yield actor
    finally:
        _CURRENT.reset(token)


def command_line_actor(reason: str = "", environ: Mapping[str, str] | None = None) -> Actor:
    """The operating-system user of this command, and who ran it through ``sudo``.

    ``sudo`` sets ``SUDO_USER`` to the user who called it: a record of ``root`` alone would
    name no person, so both are kept (``root``, "sudo by alice").
    """
    env = os.environ if environ is None else environ
    try:
        user = getpass.getuser()
    except (KeyError, OSError):  # no name for this uid (a bare container)
        user = f"uid {os.getuid()}"
    sudo_user = env.get("SUDO_USER", "")
    detail = f"sudo by {sudo_user}" if sudo_user and sudo_user != user else ""
    return Actor(user=user, via=Via.CLI, detail=detail, reason=reason)
