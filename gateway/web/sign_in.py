"""The page's sign-in: who is signed in, sign in, sign out.

A sign-in's scrypt check runs in a thread and passes the :class:`SignInThrottle` (an
address locked out after wrong passwords, a bound on checks at once); each attempt is
counted on the gateway's state for the metrics. The session lives in a cookie without
``Max-Age``: the gateway ends it after ``web.session_minutes`` without a write.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING

from aiohttp import web

from gateway.errors import CommandRejectedError
from gateway.web.auth import SESSION_COOKIE, Session, is_loopback
from gateway.web.guards import error, json_body, same_origin
from gateway.web.users import Role

if TYPE_CHECKING:
    from gateway.config import WebConfig
    from gateway.shared.state import GatewayState
    from gateway.web.auth import Sessions, SignInThrottle
    from gateway.web.calibration import Calibrations
    from gateway.web.guards import Guards


class SignInRoutes:
    """``GET /api/session``, ``POST /api/login`` and ``POST /api/logout``."""

    def __init__(
        self,
        config: WebConfig,
        state: GatewayState,
        calibrations: Calibrations,
        guards: Guards,
    ) -> None:
        """Sessions and the throttle are ``guards``'; sign-ins counted on ``state``."""
        self.config = config
        self.state = state
        self.calibrations = calibrations
        self.guards = guards

    @property
    def sessions(self) -> Sessions:
        """The page's sessions (the guards')."""
        return self.guards.sessions

    @property
    def throttle(self) -> SignInThrottle:
        """The sign-in throttle (the guards')."""
        return self.guards.throttle

    async def session_info(self, request: web.Request) -> web.StreamResponse:
        """Who is signed in, their role and CSRF token, and what this browser may do."""
        session = self.guards.session_of(request)
        return web.json_response(
            {
                "signed_in": session is not None,
                "who": session.who if session else None,
                "user": session.user if session else None,
                "role": session.role.value if session else None,
                "shared": session.shared if session else None,
                "can_write": session is not None and session.role.allows(Role.OPERATOR),
                "csrf": session.csrf if session else None,
                "can_sign_in": self.sessions.enabled,
                "can_read": session is not None or is_loopback(request.remote),
                "session_minutes": self.config.session_minutes,
                "local": is_loopback(request.remote),
            }
        )

    async def login(self, request: web.Request) -> web.StreamResponse:
        """A session (its cookie) for a name and password, through the sign-in throttle."""
        if not same_origin(request):
            return error(403, "sign in from the gateway's own page")
        try:
            body = await json_body(request)
        except CommandRejectedError as exc:
            return error(400, str(exc))
        remote = str(request.remote)
        name, password = str(body.get("name") or ""), str(body.get("password") or "")
        opened: list[Session] = []

        async def check() -> bool:
            # scrypt in a thread; the session opened back in the loop, which owns them.
            identity = await asyncio.to_thread(self.sessions.authenticate, name, password)
            if identity is None:
                self.sessions.refused(name, remote)
                return False
            opened.append(self.sessions.open(identity, remote))
            return True

        verdict = await self.throttle.attempt(remote, check)
        self.state.count_sign_in(verdict.value, remote, self.throttle.locked_until(remote))
        turned_away = self.guards.turned_away(verdict, remote)
        if turned_away is not None:
            return turned_away
        if not opened:
            if not self.sessions.enabled:
                return error(403, "no users and no password set: the page is read-only")
            wrong = "wrong name or password" if self.sessions.named_users else "wrong password"
            return error(403, wrong)
        session = opened[0]
        response = web.json_response(
            {
                "who": session.who,
                "user": session.user,
                "role": session.role.value,
                "csrf": session.csrf,
            }
        )
        # No Max-Age: the browser keeps the cookie while it runs, and the gateway ends the
        # session after web.session_minutes without a write (sliding, not fixed at sign-in).
        response.set_cookie(
            SESSION_COOKIE, session.token, httponly=True, samesite="Strict", path="/"
        )
        return response

    async def logout(self, request: web.Request) -> web.StreamResponse:
        """The session ended; its calibration waiting for an answer is told so."""
        ended = self.sessions.sign_out(request.cookies.get(SESSION_COOKIE))
        if ended is not None:
            self.calibrations.session_ended(ended.token, ended.who)
        response = web.json_response({"signed_in": False})
        response.del_cookie(SESSION_COOKIE, path="/")
        return response
