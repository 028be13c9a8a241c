"""Who may do what on the page: the password, sessions that expire, CSRF tokens.

Reading is open from this machine (a loopback address) and needs a session from anywhere
else; a write or a calibration needs a session and, on every request, the session's CSRF
token in the ``X-CSRF-Token`` header. The password comes from the config's ``web``
section (meant to be ``GATEWAY_WEB__PASSWORD`` in the environment) or as its SHA-256;
the gateway keeps only the digest, and compares digests with :func:`hmac.compare_digest`,
so neither the length nor the content of a guess shows in the time an answer takes.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import logging
import secrets
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.config import WebConfig

_LOGGER = logging.getLogger(__name__)

SESSION_COOKIE: Final = "gateway_session"
CSRF_HEADER: Final = "X-CSRF-Token"
MAX_SESSIONS: Final = 64  # the oldest goes first: a page at the basin, not a web shop
MAX_NAME: Final = 40


def digest(password: str) -> bytes:
    """The SHA-256 of a password, as the gateway keeps and compares it."""
    return hashlib.sha256(password.encode("utf-8")).digest()


def is_loopback(remote: str | None) -> bool:
    """Whether a peer address is this machine (``None``: a Unix socket, also local)."""
    if remote is None:
        return True
    try:
        return ipaddress.ip_address(remote.split("%")[0]).is_loopback
    except ValueError:
        return False


@dataclass(slots=True, kw_only=True)
class Session:
    """One signed-in operator: who, from where, until when, and the CSRF token."""

    token: str
    csrf: str
    who: str
    remote: str
    expires: float  # monotonic

    def csrf_ok(self, given: str | None) -> bool:
        """Whether ``given`` is this session's CSRF token (compared in constant time)."""
        return given is not None and hmac.compare_digest(digest(given), digest(self.csrf))


class Sessions:
    """The password's digest and the sessions it opened."""

    def __init__(
        self,
        *,
        password_digest: bytes | None,
        lifetime_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """Sessions that live ``lifetime_s`` from their last write; no password: none at all."""
        self._digest = password_digest
        self.lifetime_s = lifetime_s
        self._clock = clock
        self._sessions: dict[str, Session] = {}

    @classmethod
    def from_config(cls, config: WebConfig) -> Sessions:
        """From the ``web`` section: the password (or its SHA-256) and the session length."""
        if config.password is not None:
            password_digest: bytes | None = digest(config.password.get_secret_value())
        elif config.password_sha256 is not None:
            password_digest = bytes.fromhex(config.password_sha256)
        else:
            password_digest = None
        return cls(password_digest=password_digest, lifetime_s=config.session_minutes * 60)

    @property
    def enabled(self) -> bool:
        """Whether anyone can sign in (a password is configured)."""
        return self._digest is not None

    def sign_in(self, who: str, password: str, remote: str) -> Session | None:
        """A new session for the right password, else ``None`` (and a warning in the log)."""
        who = " ".join(who.split())[:MAX_NAME] or "operator"
        if self._digest is None or not hmac.compare_digest(digest(password), self._digest):
            _LOGGER.warning("web: sign-in refused for %r from %s", who, remote)
            return None
        self._expire()
        while len(self._sessions) >= MAX_SESSIONS:
            oldest = min(self._sessions.values(), key=lambda s: s.expires)
            del self._sessions[oldest.token]
        session = Session(
            token=secrets.token_urlsafe(32),
            csrf=secrets.token_urlsafe(32),
            who=who,
            remote=remote,
            expires=self._clock() + self.lifetime_s,
        )
        self._sessions[session.token] = session
        _LOGGER.info("web: %s signed in from %s", who, remote)
        return session

    def find(self, token: str | None, *, touch: bool = False) -> Session | None:
        """The live session of a cookie's token.

        ``touch`` (a write, a calibration step) pushes its expiry back; reading does not,
        so a page left open on a phone does not keep its session alive.
        """
        if not token:
            return None
        self._expire()
        session = self._sessions.get(token)
        if session is not None and touch:
            session.expires = self._clock() + self.lifetime_s
        return session

    def sign_out(self, token: str | None) -> None:
        """End a session (nothing if there is none)."""
        session = self._sessions.pop(token or "", None)
        if session is not None:
            _LOGGER.info("web: %s signed out", session.who)

    def _expire(self) -> None:
        now = self._clock()
        for token in [t for t, s in self._sessions.items() if s.expires <= now]:
            _LOGGER.info("web: the session of %s expired", self._sessions.pop(token).who)
