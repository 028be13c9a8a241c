"""The page's guards: who may read, who may write, and a request's signature.

Shared by the page's routes (:mod:`gateway.web.site` and the route groups beside it): a
read from another machine needs a session; a write needs a session whose role allows it,
its CSRF token and a same-origin request; a signed act (a calibration, a verification, a
write given the password) needs the user's password again, checked through the sign-in
throttle in a thread (21 CFR Part 11 §11.200(a)(1)(i)). The session a write guard let
through is on the request under :data:`SESSION` for the handler.
"""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING, Final
from urllib.parse import urlsplit

from aiohttp import web

from gateway.errors import CommandRejectedError
from gateway.web.auth import CSRF_HEADER, SESSION_COOKIE, Session, Verdict, is_loopback
from gateway.web.users import Role

if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable, Mapping

    from gateway.web.auth import Sessions, SignInThrottle

    Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]

_LOGGER = logging.getLogger(__name__)

MAX_REASON: Final = 500  # characters of a request's reason kept for the record
SESSION: Final = web.RequestKey("session", Session)  # the session a write guard let through


def error(status: int, message: str) -> web.Response:
    """A JSON error answer: ``{"error": message}``."""
    return web.json_response({"error": message}, status=status)


def same_origin(request: web.Request) -> bool:
    """No ``Origin`` (not a browser's cross-site request), or this page's own."""
    origin = request.headers.get("Origin")
    if origin is None or origin == "null":
        return origin is None
    return urlsplit(origin).netloc == request.host


def who(request: web.Request) -> str:
    """The guarded request's user and address, as the log names them."""
    session = request[SESSION]
    return f"{session.who}@{request.remote}"


def reason(body: Mapping[str, object]) -> str:
    """The request's optional reason, as the record keeps it."""
    return " ".join(str(body.get("reason") or "").split())[:MAX_REASON]


async def json_body(request: web.Request) -> dict[str, object]:
    """The request's JSON object, or a refusal saying why it is not one."""
    try:
        body = await request.json()
    except (ValueError, UnicodeDecodeError) as exc:
        raise CommandRejectedError(f"the request is not JSON: {exc}") from None
    if not isinstance(body, dict):
        raise CommandRejectedError("the request must be a JSON object")
    return body


class Guards:
    """The read and write guards and the signature check, over the page's sessions."""

    def __init__(self, sessions: Sessions, throttle: SignInThrottle) -> None:
        """Guard with ``sessions``; signatures pass ``throttle`` as sign-ins do."""
        self.sessions = sessions
        self.throttle = throttle

    def session_of(self, request: web.Request, *, touch: bool = False) -> Session | None:
        """The request's session by its cookie, if live (``touch``: it is used now)."""
        return self.sessions.find(request.cookies.get(SESSION_COOKIE), touch=touch)

    def reader(self, handler: Handler) -> Handler:
        """Open from this machine; from elsewhere only with a session."""

        async def guarded(request: web.Request) -> web.StreamResponse:
            if not is_loopback(request.remote) and self.session_of(request) is None:
                return error(401, "sign in to read from another machine")
            return await handler(request)

        return guarded

    def writer(self, handler: Handler, *, needs: Role = Role.OPERATOR) -> Handler:
        """A session whose role allows it (``needs``), its CSRF token, a same-origin request."""

        async def guarded(request: web.Request) -> web.StreamResponse:
            session = self.session_of(request, touch=True)
            if session is None:
                _LOGGER.warning(
                    "web: %s %s refused from %s: no session",
                    request.method,
                    request.path,
                    request.remote,
                )
                return error(401, "sign in first: writes and calibrations need a session")
            if not same_origin(request) or not session.csrf_ok(request.headers.get(CSRF_HEADER)):
                _LOGGER.warning(
                    "web: %s %s by %s refused from %s: bad CSRF token or origin",
                    request.method,
                    request.path,
                    session.who,
                    request.remote,
                )
                return error(403, "bad or missing CSRF token")
            if not session.role.allows(needs):
                _LOGGER.warning(
                    "web: %s %s by %s refused from %s: the %s role is needed, %s is a %s",
                    request.method,
                    request.path,
                    session.who,
                    request.remote,
                    needs.value,
                    session.who,
                    session.role.value,
                )
                return error(
                    403,
                    f"not allowed: this needs the {needs.value} role (writes, calibrations "
                    f"and verifications do), and {session.who} is a {session.role.value}",
                )
            request[SESSION] = session
            return await handler(request)

        return guarded

    async def signature(
        self, request: web.Request, body: Mapping[str, object], *, what: str, required: bool
    ) -> bool | web.Response:
        """Whether the request is signed: the user's password again in ``password``, right.

        21 CFR Part 11 §11.200(a)(1)(i): the first signing of a session takes both
        components, name and password; the name is the session's. A refusal (a missing
        password where ``required``, a wrong one, a locked-out address) is the response
        to send. The check passes the sign-in throttle, so a session left open on a phone
        is no way to guess its user's password quickly.
        """
        session = request[SESSION]
        password = body.get("password")
        if password is None or password == "":
            if not required:
                return False
            _LOGGER.warning(
                "web: %s by %s refused: not signed (no password given again)",
                what,
                who(request),
            )
            return error(
                403,
                f"{what} is signed with your password: give it again (password) to go on",
            )
        if not isinstance(password, str):
            return error(400, "password must be text")
        remote = str(request.remote)

        async def check() -> bool:
            return await asyncio.to_thread(self.sessions.signature_ok, session, password)

        verdict = await self.throttle.attempt(remote, check)
        if verdict is Verdict.OK:
            return True
        turned_away = self.turned_away(verdict, remote)
        if turned_away is not None:
            return turned_away
        _LOGGER.warning("web: %s by %s refused: wrong password", what, who(request))
        return error(403, f"wrong password: {what} was not done")

    def turned_away(self, verdict: Verdict, remote: str) -> web.Response | None:
        """The 429 of a password not even checked (locked out, too many waiting), if so."""
        if verdict is Verdict.LOCKED_OUT:
            wait = max(1, round(self.throttle.retry_after_s(remote)))
            response = error(429, f"too many wrong passwords from {remote}: try again in {wait} s")
            response.headers["Retry-After"] = str(wait)
            return response
        if verdict is Verdict.BUSY:
            return error(429, "too many sign-ins at once: try again in a moment")
        return None
