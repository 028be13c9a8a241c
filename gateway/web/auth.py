"""Who may do what on the page: users and roles, sessions that expire, CSRF tokens, the host.

Reading is open from this machine (a loopback address) and needs a session from anywhere
else; a write or a calibration needs a session whose role allows it (an operator's or an
admin's, not a viewer's) and, on every request, the session's CSRF token in the
``X-CSRF-Token`` header. A session is a named user of the users file
(:mod:`gateway.web.users`) with their role, or, for a plant that wants no accounts, the
one shared password of the config's ``web`` section (``GATEWAY_WEB__PASSWORD``, or its
SHA-256 in old configs): such a session is the user :data:`SHARED_PASSWORD`, an operator,
with the name typed at sign-in kept as its detail. The shared password is kept in memory
only as a scrypt hash made at start with a random salt (of its SHA-256, so both ways of
configuring it are one secret), and every password is compared as a scrypt hash with
:func:`hmac.compare_digest`: neither the length nor the content of a guess shows in the
time an answer takes. A scrypt check takes tens of milliseconds, so the page runs it in a
thread (:meth:`Sessions.authenticate` is thread-safe) while the loop goes on polling.

A session's :class:`~gateway.records.actor.Actor` (:meth:`Session.actor`) is what the
records name: the user, the page, the client's address, the reason given and whether the
password was given again for the act (Part 11 §11.200's signature).

Guesses are throttled (:class:`SignInThrottle`): one at a time per client address and one
at a time overall, each wrong one costing :data:`WRONG_DELAY_S`, and an address that
guesses wrong :data:`MAX_FAILURES` times is locked out for a while, so parallel requests
buy no speed. A ``Host`` header the page does not answer to (:func:`host_allowed`) is a
DNS-rebinding attempt: a page of another site that resolved its name to this gateway.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import ipaddress
import logging
import secrets
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING, Final

from gateway.records.actor import SHARED_PASSWORD, Actor, Via
from gateway.web.users import PasswordHash, Role

if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable, Collection

    from gateway.config import WebConfig
    from gateway.web.users import UserBook

_LOGGER = logging.getLogger(__name__)

SESSION_COOKIE: Final = "gateway_session"
CSRF_HEADER: Final = "X-CSRF-Token"
MAX_SESSIONS: Final = 64  # the oldest goes first: a page at the basin, not a web shop
MAX_NAME: Final = 40
WRONG_DELAY_S: Final = 0.5  # what each wrong password costs, per address and overall
MAX_FAILURES: Final = 5  # wrong passwords from one address within FAILURE_WINDOW_S ...
FAILURE_WINDOW_S: Final = 10 * 60.0
LOCKOUT_S: Final = 5 * 60.0  # ... lock it out this long (the right password too)
MAX_WAITING: Final = 16  # sign-ins queued at once, all addresses; more are turned away
MAX_ADDRESSES: Final = 1024  # addresses remembered; the quiet ones are forgotten first
LOCALHOST_NAMES: Final = frozenset({"localhost", "localhost.localdomain", "ip6-localhost"})


def digest(password: str) -> bytes:
    """The SHA-256 of a password: what the shared password's scrypt hash is made of."""
    return hashlib.sha256(password.encode("utf-8")).digest()


def is_loopback(remote: str | None) -> bool:
    """Whether a peer address is this machine (``None``: a Unix socket, also local)."""
    if remote is None:
        return True
    try:
        return ipaddress.ip_address(remote.split("%")[0]).is_loopback
    except ValueError:
        return False


def _typed(name: str) -> str:
    """A name typed at sign-in, as kept: spaces folded, at most :data:`MAX_NAME` long."""
    return " ".join(name.split())[:MAX_NAME]


@dataclass(frozen=True, slots=True, kw_only=True)
class Identity:
    """Who a right password showed someone to be."""

    user: str  # the users file's name, or SHARED_PASSWORD
    role: Role
    who: str  # shown and logged: the user's name, or the name typed with the shared password


@dataclass(slots=True, kw_only=True)
class Session:
    """One signed-in user: who, their role, from where, until when, and the CSRF token."""

    token: str
    csrf: str
    who: str  # the user's name, or the name typed with the shared password
    remote: str
    expires: float  # monotonic
    user: str = SHARED_PASSWORD  # the name records carry
    role: Role = Role.OPERATOR
    busy: int = 0  # calibrations of this session under way: it does not expire meanwhile

    @property
    def shared(self) -> bool:
        """Whether it was opened with the shared password, not by a named user."""
        return self.user == SHARED_PASSWORD

    def csrf_ok(self, given: str | None) -> bool:
        """Whether ``given`` is this session's CSRF token (compared in constant time)."""
        return given is not None and hmac.compare_digest(digest(given), digest(self.csrf))

    def actor(self, remote: str, *, reason: str = "", signed: bool = False) -> Actor:
        """Who acts in a request of this session, as the records name them.

        The shared password's records say :data:`SHARED_PASSWORD`, with the name typed at
        sign-in beside the address: a name nobody proved, kept as a hint, not as the user.
        """
        detail = f"{remote}, name given: {self.who}" if self.shared else remote
        return Actor(user=self.user, via=Via.PAGE, detail=detail, reason=reason, signed=signed)


class Sessions:
    """The users and the shared password, and the sessions they opened."""

    def __init__(
        self,
        *,
        shared: PasswordHash | None,
        users: UserBook | None = None,
        lifetime_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """Sessions that live ``lifetime_s`` from their last write.

        ``shared``: the scrypt hash of the shared password's SHA-256 (``None``: no shared
        password); ``users``: the users file. Neither: nobody can sign in.
        """
        self._shared = shared
        self.users = users
        self.lifetime_s = lifetime_s
        self._clock = clock
        self._sessions: dict[str, Session] = {}

    @classmethod
    def from_config(
        cls,
        config: WebConfig,
        *,
        users: UserBook | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> Sessions:
        """From the ``web`` section: the shared password (or its SHA-256), the session length."""
        if config.password is not None:
            secret: bytes | None = digest(config.password.get_secret_value())
        elif config.password_sha256 is not None:
            secret = bytes.fromhex(config.password_sha256)
        else:
            secret = None
        # Hashed once, here, with a salt of this run: what stays in memory is scrypt's.
        shared = PasswordHash.of(secret) if secret is not None else None
        return cls(shared=shared, users=users, lifetime_s=config.session_minutes * 60, clock=clock)

    @property
    def shared_password(self) -> bool:
        """Whether the shared password is configured."""
        return self._shared is not None

    @property
    def named_users(self) -> bool:
        """Whether the users file has users now."""
        return self.users is not None and bool(self.users.snapshot())

    @property
    def enabled(self) -> bool:
        """Whether anyone can sign in: a shared password, or users in the users file."""
        return self._shared is not None or self.named_users

    def authenticate(self, name: str, password: str) -> Identity | None:
        """Who ``name`` and ``password`` show someone to be, else ``None``.

        Slow (scrypt) and safe to run in a thread: it reads the users file and the shared
        password's hash, and opens no session. A named user's own password comes first;
        else the shared password, with ``name`` kept as typed.
        """
        typed = _typed(name)
        if self.users is not None:
            user = self.users.authenticate(typed, password)
            if user is not None:
                return Identity(user=user.name, role=user.role, who=user.name)
        if self._shared is not None and self._shared.matches(digest(password)):
            return Identity(user=SHARED_PASSWORD, role=Role.OPERATOR, who=typed or "operator")
        return None

    def signature_ok(self, session: Session, password: str) -> bool:
        """Whether ``password`` is the session's user's again (a signature); slow, thread-safe."""
        if session.shared:
            return self._shared is not None and self._shared.matches(digest(password))
        user = self.users.snapshot().get(session.user) if self.users is not None else None
        return user is not None and user.password.matches(password)

    def open(self, identity: Identity, remote: str) -> Session:
        """A new session for who :meth:`authenticate` found (in the loop: not thread-safe)."""
        self._expire()
        while len(self._sessions) >= MAX_SESSIONS:
            oldest = min(self._sessions.values(), key=lambda s: s.expires)
            del self._sessions[oldest.token]
        session = Session(
            token=secrets.token_urlsafe(32),
            csrf=secrets.token_urlsafe(32),
            who=identity.who,
            remote=remote,
            expires=self._clock() + self.lifetime_s,
            user=identity.user,
            role=identity.role,
        )
        self._sessions[session.token] = session
        how = "with the shared password" if session.shared else f"as {session.role.value}"
        _LOGGER.info("web: %s signed in %s from %s", session.who, how, remote)
        return session

    def refused(self, name: str, remote: str) -> None:
        """Log a refused sign-in."""
        _LOGGER.warning("web: sign-in refused for %r from %s", _typed(name), remote)

    def sign_in(self, who: str, password: str, remote: str) -> Session | None:
        """A new session for a right name and password, else ``None`` (and a warning).

        Checks in the caller's thread: the page calls :meth:`authenticate` in a thread
        and :meth:`open` in the loop instead.
        """
        identity = self.authenticate(who, password)
        if identity is None:
            self.refused(who, remote)
            return None
        return self.open(identity, remote)

    def find(self, token: str | None, *, touch: bool = False) -> Session | None:
        """The live session of a cookie's token.

        ``touch`` (a write, a calibration step) pushes its expiry back: the session ends
        ``lifetime_s`` after its last write. Reading does not, so a page left open on a
        phone does not keep its session alive. A named user removed from the users file
        has no session any more; one whose role changed has the new role.
        """
        if not token:
            return None
        self._expire()
        session = self._sessions.get(token)
        if session is not None and not session.shared and self.users is not None:
            user = self.users.snapshot().get(session.user)
            if user is None:
                _LOGGER.warning("web: %s is no longer a user: their session ended", session.who)
                del self._sessions[token]
                return None
            session.role = user.role
        if session is not None and touch:
            session.expires = self._clock() + self.lifetime_s
        return session

    def hold(self, token: str) -> None:
        """A calibration of this session began: it does not expire until :meth:`release`."""
        session = self._sessions.get(token)
        if session is not None:
            session.busy += 1

    def release(self, token: str) -> None:
        """A calibration of this session ended: its ``lifetime_s`` starts again from now."""
        session = self._sessions.get(token)
        if session is not None:
            session.busy = max(0, session.busy - 1)
            session.expires = max(session.expires, self._clock() + self.lifetime_s)

    def sign_out(self, token: str | None) -> Session | None:
        """End a session; the one that ended (``None`` if there was none)."""
        session = self._sessions.pop(token or "", None)
        if session is not None:
            _LOGGER.info("web: %s signed out", session.who)
        return session

    def _expire(self) -> None:
        now = self._clock()
        for token in [t for t, s in self._sessions.items() if s.expires <= now and not s.busy]:
            _LOGGER.info("web: the session of %s expired", self._sessions.pop(token).who)


class Verdict(StrEnum):
    """How a sign-in attempt ended (also the ``outcome`` label of its metric)."""

    OK = "ok"
    WRONG = "wrong"  # a wrong password, answered after the delay
    LOCKED_OUT = "locked_out"  # the address guessed too often: not even checked
    BUSY = "busy"  # too many sign-ins waiting at once: not even checked


@dataclass(slots=True)
class _Address:
    failures: deque[float] = field(default_factory=deque)  # monotonic, within the window
    locked_until: float = 0.0
    waiting: int = 0
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)


class SignInThrottle:
    """Password checks one at a time per address and overall; lock-out after failures.

    A wrong password holds both locks for ``delay_s``, so guesses from one address, or
    from many, come no faster than one per ``delay_s`` however many are sent at once
    (an aiohttp server answers requests concurrently: a per-request sleep alone lets 20
    parallel guesses take one delay). The right password is answered at once.
    ``counts`` (by :class:`Verdict`) and ``lockouts`` are what the metrics read.
    """

    def __init__(
        self,
        *,
        delay_s: float = WRONG_DELAY_S,
        max_failures: int = MAX_FAILURES,
        window_s: float = FAILURE_WINDOW_S,
        lockout_s: float = LOCKOUT_S,
        max_waiting: int = MAX_WAITING,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """The limits; defaults are the module's constants."""
        self.delay_s = delay_s
        self.max_failures = max_failures
        self.window_s = window_s
        self.lockout_s = lockout_s
        self.max_waiting = max_waiting
        self._clock = clock
        self._addresses: dict[str, _Address] = {}
        self._overall = asyncio.Lock()
        self._waiting = 0
        self.counts: Counter[Verdict] = Counter()
        self.lockouts = 0

    def locked_out(self) -> int:
        """How many addresses are locked out now."""
        now = self._clock()
        return sum(1 for a in self._addresses.values() if a.locked_until > now)

    def locked_until(self, remote: str) -> float:
        """Until when (monotonic) ``remote`` is or was last locked out (0: never)."""
        entry = self._addresses.get(remote)
        return entry.locked_until if entry else 0.0

    def retry_after_s(self, remote: str) -> float:
        """How long ``remote`` is still locked out (0: it is not)."""
        entry = self._addresses.get(remote)
        return max(0.0, entry.locked_until - self._clock()) if entry else 0.0

    async def attempt(self, remote: str, check: Callable[[], Awaitable[bool]]) -> Verdict:
        """Run ``check`` (the password compared) under the throttle; how it went.

        ``check`` is awaited: a scrypt comparison runs in a thread, the loop polls meanwhile.
        """
        entry = self._entry(remote)
        if entry.locked_until > self._clock():
            return self._count(Verdict.LOCKED_OUT)
        if self._waiting >= self.max_waiting:
            _LOGGER.debug("web: sign-in from %s turned away: %d waiting", remote, self._waiting)
            return self._count(Verdict.BUSY)
        self._waiting += 1
        entry.waiting += 1
        try:
            async with entry.lock, self._overall:
                now = self._clock()
                if entry.locked_until > now:
                    return self._count(Verdict.LOCKED_OUT)
                if await check():
                    entry.failures.clear()
                    return self._count(Verdict.OK)
                self._fail(remote, entry, now)
                await asyncio.sleep(self.delay_s)  # a guess costs time, here and overall
                return self._count(Verdict.WRONG)
        finally:
            self._waiting -= 1
            entry.waiting -= 1

    def _fail(self, remote: str, entry: _Address, now: float) -> None:
        entry.failures.append(now)
        while entry.failures and entry.failures[0] <= now - self.window_s:
            entry.failures.popleft()
        if len(entry.failures) >= self.max_failures:
            entry.failures.clear()
            entry.locked_until = now + self.lockout_s
            self.lockouts += 1
            _LOGGER.warning(
                "web: %s locked out for %.0f s after %d wrong passwords within %.0f s",
                remote,
                self.lockout_s,
                self.max_failures,
                self.window_s,
            )

    def _count(self, verdict: Verdict) -> Verdict:
        self.counts[verdict] += 1
        return verdict

    def _entry(self, remote: str) -> _Address:
        entry = self._addresses.get(remote)
        if entry is None:
            if len(self._addresses) >= MAX_ADDRESSES:
                self._forget()
            entry = self._addresses[remote] = _Address()
        return entry

    def _forget(self) -> None:
        """Drop the addresses neither locked out nor waiting, least recently failed first."""
        now = self._clock()
        quiet = sorted(
            (a.failures[-1] if a.failures else 0.0, k)
            for k, a in self._addresses.items()
            if a.locked_until <= now and not a.waiting
        )
        for _, key in quiet[: max(1, len(quiet) // 2)]:
            del self._addresses[key]


def _host_part(header: str) -> str:
    """The name or address of a ``Host`` header: without the port, lower case, no final dot."""
    host = header.strip().lower()
    if host.startswith("["):
        return host[1 : host.find("]")] if "]" in host else host
    if host.count(":") == 1:
        host = host.partition(":")[0]
    return host.rstrip(".")


def _address(text: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    try:
        address = ipaddress.ip_address(text.split("%", maxsplit=1)[0])
    except ValueError:
        return None
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped
    return address


def host_allowed(
    header: str | None,
    *,
    allowed: Collection[str],
    listen: str,
    local: str | None,
    remote: str | None,
) -> bool:
    """Whether the page answers a request whose ``Host`` is ``header``.

    Accepted: a name of ``allowed`` (``*.example.com`` matches its subdomains); an address
    that is the listen address (``listen``) or the one the client connected to
    (``local``), since an address cannot be rebound; and the localhost names when the
    client is this machine (``remote`` on loopback). No header at all (HTTP/1.0) comes
    from no browser and is let through.
    """
    if header is None:
        return True
    host = _host_part(header)
    if host in allowed or any(
        name.startswith("*.") and host.endswith(name[1:]) for name in allowed
    ):
        return True
    given = _address(host)
    if given is not None:
        return any(given == _address(a) for a in (listen, local) if a)
    if host == listen.lower().rstrip("."):
        return True
    return (host in LOCALHOST_NAMES or host.endswith(".localhost")) and is_loopback(remote)
