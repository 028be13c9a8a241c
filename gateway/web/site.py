"""The page's HTTP server: aiohttp in the gateway's own event loop, one named task.

Routes (JSON unless said; ``R`` read: loopback or a session; ``W`` write: a session and
its CSRF token in ``X-CSRF-Token``, and a same-origin ``Origin`` if the browser sends one)::

    GET  /                                  the page (static: index.html, app.js, style.css)
    GET  /api/session                       who is signed in, their role, the CSRF token
    POST /api/login  {name, password}       a session (cookie), or 403
    POST /api/logout
    GET  /api/state                      R  lines and devices with live values, bus health
    GET  /api/events                     R  the same, as server-sent events, every second
    GET  /api/care                       R  sensor care: every device's document, most urgent
                                            first, with the calibration it asks for
    GET  /api/devices/{device}           R  identity, register map, procedures
    POST /api/devices/{device}/points/{point}  W  {value, reason?, password?}: a write
                                            through SafeWriter (signed if password is given)
    POST /api/devices/{device}/read      W* every point read now (queued ahead of polls)
    POST /api/calibrations               W  {device, procedure, inputs, password, reason?}:
                                            a guided run, signed with the password again
    GET  /api/calibrations?device=NAME   R  the runs under way (of a device)
    GET  /api/calibrations/{id}          R  its steps, question, outcome
    POST /api/calibrations/{id}/answer   W  {confirm: bool}: only from the run's session
    POST /api/calibrations/{id}/take-over W  the run becomes this session's
    POST /api/calibrations/{id}/cancel   W
    POST /api/lines/{bus}/scan           W  a scan of the line, its polling paused
    GET  /api/lines/{bus}/scan           R  the scan's progress and report
    GET  /api/records?device=&kind=&since=&until=&limit=
                                         R  the records chosen, newest first (500 unless
                                            limit says), the chain's head and verdict
    GET  /api/devices/{device}/verification  R  what the verification form starts from
    POST /api/devices/{device}/verify    W  {reference, unit?, method, instrument?,
                                            sampled_at?, reason?, password}: a grab-sample
                                            verification, signed; its outcome, or why not

``W`` needs an operator's or an admin's session: a viewer's is refused with 403 and a
message naming the role needed (``W*``: a viewer's too, it only reads). Every write and
calibration is logged with who did it (the signed-in user, or the name given with the
shared password) and from where, and runs under that user's
:class:`~gateway.records.actor.Actor` (:func:`~gateway.records.actor.acting`), which the
records name. A calibration is signed (21 CFR Part 11 §11.200: both components, name and
password, at the first signing of a session): its request carries the user's password
again, refused with 403 without it or with a wrong one; a verification likewise; a write is
signed when its request carries the password. Without a record store (``records``) the
records answer 404; without a verifier, verifications answer 503. Every request first
passes the ``Host`` check (:func:`host_allowed`): a name the page does not answer to gets
421, so a DNS-rebinding page cannot read it through a browser on this machine. Sign-ins
and signatures pass the :class:`SignInThrottle`, their scrypt checks in a thread so the
loop goes on polling.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from importlib import resources
from typing import TYPE_CHECKING, Final
from urllib.parse import urlsplit

from aiohttp import web

from gateway.control.verification import VerificationRequest, verifiable_point
from gateway.errors import CommandRejectedError, ConfigError, GatewayError, ProfileError
from gateway.line.samples import json_value
from gateway.records.actor import acting
from gateway.web.auth import (
    CSRF_HEADER,
    SESSION_COOKIE,
    Session,
    Sessions,
    SignInThrottle,
    Verdict,
    host_allowed,
    is_loopback,
)
from gateway.web.calibration import CalibrationRun, Calibrations, procedures_for
from gateway.web.care import calibration_offer, care_documents
from gateway.web.live import overview, register_map, sample_view
from gateway.web.records import RecordsRequest, head_view, read_records, verification_form
from gateway.web.users import Role

if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable, Mapping

    from gateway.config import WebConfig
    from gateway.control.verification import Verifier
    from gateway.control.writes import SafeWriter
    from gateway.records import RecordStore
    from gateway.shared.state import GatewayState
    from gateway.web.scan import LineScans
    from gateway.web.users import UserBook

    Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]

_LOGGER = logging.getLogger(__name__)

EVENT_INTERVAL_S: Final = 1.0
MAX_REASON: Final = 500  # characters of a request's reason kept for the record
MAX_REFUSED: Final = 256  # Host names remembered as refused, to warn once per name
SHUTDOWN_S: Final = 3.0
STATIC_FILES: Final = {
    "index.html": "text/html",
    "app.js": "text/javascript",
    "style.css": "text/css",
    "favicon.svg": "image/svg+xml",
}
_SESSION: Final = web.RequestKey("session", Session)  # the session a write guard let through
_SECURITY_HEADERS: Final = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "same-origin",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; "
    "style-src 'self'; script-src 'self'; connect-src 'self'; frame-ancestors 'none'",
    "Cache-Control": "no-store",
}


def _static(name: str) -> bytes:
    return resources.files("gateway.web").joinpath("static", name).read_bytes()


def _error(status: int, message: str) -> web.Response:
    return web.json_response({"error": message}, status=status)


class WebServer:
    """The page, served from the gateway's loop while :meth:`run` runs."""

    def __init__(
        self,
        config: WebConfig,
        state: GatewayState,
        writers: Mapping[str, SafeWriter],
        *,
        scans: LineScans | None = None,
        sessions: Sessions | None = None,
        calibrations: Calibrations | None = None,
        throttle: SignInThrottle | None = None,
        users: UserBook | None = None,
        records: RecordStore | None = None,
        verifier: Verifier | None = None,
        event_interval_s: float = EVENT_INTERVAL_S,
    ) -> None:
        """Serve ``state``; writes and calibrations through ``writers`` (by device name).

        ``sessions`` and ``calibrations``: a former page's, kept by a reload (a calibration
        under way goes on, its operator still signed in). ``users``: the users file
        (without it, only the shared password signs in). ``records``: the record store the
        records view reads (its head on every page); ``verifier``: the gateway's
        grab-sample verifications.
        """
        self.config = config
        self.state = state
        self.writers = writers
        self.scans = scans
        self.records = records
        self.verifier = verifier
        self.sessions = sessions or Sessions.from_config(config, users=users)
        self.throttle = throttle or SignInThrottle()
        if calibrations is None:
            calibrations = Calibrations(writers, sessions=self.sessions)
        calibrations.confirm_timeout_s = config.confirm_minutes * 60
        self.calibrations = calibrations
        self._allowed_hosts = frozenset(config.allowed_hosts)
        self._refused_hosts: set[str] = set()
        state.web.enabled = True
        self.event_interval_s = event_interval_s
        self.port: int | None = None  # the port bound, once started
        self._closing = asyncio.Event()
        self._latest: tuple[float, str] = (0.0, "")
        self._runner: web.AppRunner | None = None

    # --- running ----------------------------------------------------------------------

    def app(self) -> web.Application:
        """The aiohttp application with every route."""
        app = web.Application(middlewares=[self._headers, self._host_check])
        get, post = web.get, web.post
        app.add_routes(
            [
                get("/", self._index),
                get("/static/{name}", self._asset),
                get("/api/session", self._session_info),
                post("/api/login", self._login),
                post("/api/logout", self._logout),
                get("/api/state", self._reader(self._state)),
                get("/api/events", self._reader(self._events)),
                get("/api/care", self._reader(self._care)),
                get("/api/devices/{device}", self._reader(self._device)),
                post("/api/devices/{device}/points/{point}", self._writer(self._write)),
                post("/api/devices/{device}/read", self._writer(self._read_all, needs=Role.VIEWER)),
                post("/api/calibrations", self._writer(self._start_calibration)),
                get("/api/calibrations", self._reader(self._calibrations_under_way)),
                get("/api/calibrations/{id}", self._reader(self._calibration)),
                post("/api/calibrations/{id}/answer", self._writer(self._answer)),
                post("/api/calibrations/{id}/take-over", self._writer(self._take_over)),
                post("/api/calibrations/{id}/cancel", self._writer(self._cancel)),
                post("/api/lines/{bus}/scan", self._writer(self._start_scan)),
                get("/api/lines/{bus}/scan", self._reader(self._scan)),
                get("/api/records", self._reader(self._records)),
                get("/api/devices/{device}/verification", self._reader(self._verification)),
                post("/api/devices/{device}/verify", self._writer(self._verify)),
            ]
        )
        return app

    async def start(self) -> None:
        """Listen on the configured host and port."""
        self._runner = web.AppRunner(
            self.app(), access_log=None, shutdown_timeout=SHUTDOWN_S, handle_signals=False
        )
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.config.host, self.config.port)
        try:
            await site.start()
        except OSError as exc:
            await self._runner.cleanup()
            self._runner = None
            where = f"{self.config.host}:{self.config.port}"
            raise ConfigError(f"web: cannot listen on {where}: {exc}", key="web.port") from exc
        bound = self._runner.addresses
        self.port = int(bound[0][1]) if bound else self.config.port
        if not self.sessions.enabled:
            _LOGGER.warning(
                "web: no users (gateway users add) and no password (GATEWAY_WEB__PASSWORD): "
                "the page is read-only, from this machine only"
            )
        _LOGGER.info("web: the page is at %s", self.url)

    @property
    def url(self) -> str:
        """Where a browser on this machine finds the page."""
        host = self.config.host
        if host in {"0.0.0.0", "::"}:  # noqa: S104 - naming it, not binding it
            host = "127.0.0.1"
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port or self.config.port}/"

    async def stop(self, *, keep_calibrations: bool = False) -> None:
        """Close the event streams, let waiting calibrations decline, stop listening.

        ``keep_calibrations``: a reload rebuilds the page; its runs go on under the next.
        Stopped once: :meth:`run`'s end, after a reload's stop, changes nothing more.
        """
        if self._closing.is_set():
            return
        self._closing.set()
        if not keep_calibrations:
            await self.calibrations.close()
        if self.scans is not None:
            await self.scans.close()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    async def run(self, stop: asyncio.Event | None = None) -> None:
        """Serve (starting if need be) until cancelled or ``stop`` is set, then stop."""
        if self._runner is None:
            await self.start()
        try:
            await (stop or asyncio.Event()).wait()
        finally:
            await self.stop()

    # --- guards -----------------------------------------------------------------------

    @web.middleware
    async def _headers(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        response = await handler(request)
        if not response.prepared:
            for name, value in _SECURITY_HEADERS.items():
                response.headers.setdefault(name, value)
        return response

    @web.middleware
    async def _host_check(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """Answer only to the configured names, the listen address and localhost here."""
        sockname = request.transport.get_extra_info("sockname") if request.transport else None
        local = str(sockname[0]) if isinstance(sockname, tuple) and sockname else None
        header = request.headers.get("Host")
        if host_allowed(
            header,
            allowed=self._allowed_hosts,
            listen=self.config.host,
            local=local,
            remote=request.remote,
        ):
            return await handler(request)
        # The first request of a refused name is a warning; a page polling it, quiet.
        first = header not in self._refused_hosts and len(self._refused_hosts) < MAX_REFUSED
        self._refused_hosts.add(header or "")
        _LOGGER.log(
            logging.WARNING if first else logging.DEBUG,
            "web: %s %s from %s refused: Host %r is not a name of this gateway (web.allowed_hosts)",
            request.method,
            request.path,
            request.remote,
            header,
        )
        return web.Response(
            status=421,
            text=f"This gateway does not answer to the host name {header!r}. If that is "
            "its name, add it to web.allowed_hosts in the gateway's config.\n",
        )

    def _session(self, request: web.Request, *, touch: bool = False) -> Session | None:
        return self.sessions.find(request.cookies.get(SESSION_COOKIE), touch=touch)

    def _reader(self, handler: Handler) -> Handler:
        """Open from this machine; from elsewhere only with a session."""

        async def guarded(request: web.Request) -> web.StreamResponse:
            if not is_loopback(request.remote) and self._session(request) is None:
                return _error(401, "sign in to read from another machine")
            return await handler(request)

        return guarded

    def _writer(self, handler: Handler, *, needs: Role = Role.OPERATOR) -> Handler:
        """A session whose role allows it (``needs``), its CSRF token, a same-origin request."""

        async def guarded(request: web.Request) -> web.StreamResponse:
            session = self._session(request, touch=True)
            if session is None:
                _LOGGER.warning(
                    "web: %s %s refused from %s: no session",
                    request.method,
                    request.path,
                    request.remote,
                )
                return _error(401, "sign in first: writes and calibrations need a session")
            if not self._same_origin(request) or not session.csrf_ok(
                request.headers.get(CSRF_HEADER)
            ):
                _LOGGER.warning(
                    "web: %s %s by %s refused from %s: bad CSRF token or origin",
                    request.method,
                    request.path,
                    session.who,
                    request.remote,
                )
                return _error(403, "bad or missing CSRF token")
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
                return _error(
                    403,
                    f"not allowed: this needs the {needs.value} role (writes, calibrations "
                    f"and verifications do), and {session.who} is a {session.role.value}",
                )
            request[_SESSION] = session
            return await handler(request)

        return guarded

    @staticmethod
    def _same_origin(request: web.Request) -> bool:
        origin = request.headers.get("Origin")
        if origin is None or origin == "null":
            return origin is None
        return urlsplit(origin).netloc == request.host

    @staticmethod
    def _who(request: web.Request) -> str:
        session = request[_SESSION]
        return f"{session.who}@{request.remote}"

    async def _signature(
        self, request: web.Request, body: Mapping[str, object], *, what: str, required: bool
    ) -> bool | web.Response:
        """Whether the request is signed: the user's password again in ``password``, right.

        21 CFR Part 11 §11.200(a)(1)(i): the first signing of a session takes both
        components, name and password; the name is the session's. A refusal (a missing
        password where ``required``, a wrong one, a locked-out address) is the response
        to send. The check passes the sign-in throttle, so a session left open on a phone
        is no way to guess its user's password quickly.
        """
        session = request[_SESSION]
        password = body.get("password")
        if password is None or password == "":
            if not required:
                return False
            _LOGGER.warning(
                "web: %s by %s refused: not signed (no password given again)",
                what,
                self._who(request),
            )
            return _error(
                403,
                f"{what} is signed with your password: give it again (password) to go on",
            )
        if not isinstance(password, str):
            return _error(400, "password must be text")
        remote = str(request.remote)

        async def check() -> bool:
            return await asyncio.to_thread(self.sessions.signature_ok, session, password)

        verdict = await self.throttle.attempt(remote, check)
        if verdict is Verdict.OK:
            return True
        turned_away = self._turned_away(verdict, remote)
        if turned_away is not None:
            return turned_away
        _LOGGER.warning("web: %s by %s refused: wrong password", what, self._who(request))
        return _error(403, f"wrong password: {what} was not done")

    def _turned_away(self, verdict: Verdict, remote: str) -> web.Response | None:
        """The 429 of a password not even checked (locked out, too many waiting), if so."""
        if verdict is Verdict.LOCKED_OUT:
            wait = max(1, round(self.throttle.retry_after_s(remote)))
            response = _error(429, f"too many wrong passwords from {remote}: try again in {wait} s")
            response.headers["Retry-After"] = str(wait)
            return response
        if verdict is Verdict.BUSY:
            return _error(429, "too many sign-ins at once: try again in a moment")
        return None

    @staticmethod
    def _reason(body: Mapping[str, object]) -> str:
        """The request's optional reason, as the record keeps it."""
        return " ".join(str(body.get("reason") or "").split())[:MAX_REASON]

    @staticmethod
    async def _body(request: web.Request) -> dict[str, object]:
        try:
            body = await request.json()
        except (ValueError, UnicodeDecodeError) as exc:
            raise CommandRejectedError(f"the request is not JSON: {exc}") from None
        if not isinstance(body, dict):
            raise CommandRejectedError("the request must be a JSON object")
        return body

    # --- the page ---------------------------------------------------------------------

    async def _index(self, _request: web.Request) -> web.StreamResponse:
        return web.Response(body=_static("index.html"), content_type="text/html", charset="utf-8")

    async def _asset(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        kind = STATIC_FILES.get(name)
        if kind is None:
            raise web.HTTPNotFound
        return web.Response(body=_static(name), content_type=kind)

    async def _session_info(self, request: web.Request) -> web.StreamResponse:
        session = self._session(request)
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

    async def _login(self, request: web.Request) -> web.StreamResponse:
        if not self._same_origin(request):
            return _error(403, "sign in from the gateway's own page")
        try:
            body = await self._body(request)
        except CommandRejectedError as exc:
            return _error(400, str(exc))
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
        turned_away = self._turned_away(verdict, remote)
        if turned_away is not None:
            return turned_away
        if not opened:
            if not self.sessions.enabled:
                return _error(403, "no users and no password set: the page is read-only")
            wrong = "wrong name or password" if self.sessions.named_users else "wrong password"
            return _error(403, wrong)
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

    async def _logout(self, request: web.Request) -> web.StreamResponse:
        ended = self.sessions.sign_out(request.cookies.get(SESSION_COOKIE))
        if ended is not None:
            self.calibrations.session_ended(ended.token, ended.who)
        response = web.json_response({"signed_in": False})
        response.del_cookie(SESSION_COOKIE, path="/")
        return response

    # --- reading ----------------------------------------------------------------------

    def _overview(self) -> str:
        """The overview as JSON, made at most once per half interval for every reader."""
        now = time.monotonic()
        made, text = self._latest
        if now - made >= self.event_interval_s / 2 or not text:
            paused = self.scans.paused() if self.scans is not None else {}
            data = overview(self.state, paused)
            if self.records is not None:  # the chain's head, on every page
                head = self.records.head
                data["records"] = head_view(head.seq, head.hash)
            text = json.dumps(data, separators=(",", ":"))
            self._latest = (now, text)
        return text

    async def _state(self, _request: web.Request) -> web.StreamResponse:
        return web.Response(text=self._overview(), content_type="application/json")

    async def _events(self, request: web.Request) -> web.StreamResponse:
        response = web.StreamResponse(
            headers={
                "Content-Type": "text/event-stream",
                "Cache-Control": "no-cache",
                "X-Accel-Buffering": "no",
            }
        )
        await response.prepare(request)
        local = is_loopback(request.remote)
        with contextlib.suppress(ConnectionError):
            while not self._closing.is_set():
                if not local and self._session(request) is None:
                    break  # the session ended: reading from elsewhere needs a new one
                await response.write(f"event: state\ndata: {self._overview()}\n\n".encode())
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(self.event_interval_s):
                        await self._closing.wait()
        return response

    async def _care(self, _request: web.Request) -> web.StreamResponse:
        return web.json_response(care_documents(self.state))

    async def _device(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["device"]
        info = next((i for i in self.state.devices.values() if i.name == name), None)
        writer = self.writers.get(name)
        if info is None or writer is None:
            return _error(404, f"no device {name!r}")
        profile = writer.link.profile
        data = register_map(
            info,
            profile,
            self.state,
            writable_by_page=self.sessions.enabled,
            flash_allowed=writer.policy.allowed,
        )
        data["procedures"] = [p.as_dict() for p in procedures_for(profile)]
        return web.json_response(data)

    async def _read_all(self, request: web.Request) -> web.StreamResponse:
        """Every point of the device read now, for the register map; nothing is published.

        A session is asked for: a read of a whole map takes the line for a while.
        """
        device = request.match_info["device"]
        writer = self.writers.get(device)
        if writer is None:
            return _error(404, f"no device {device!r}")
        points = [point for point in writer.link.profile.points if not point.view]
        _LOGGER.info("web: %s reads every point of %s", self._who(request), device)
        try:
            samples = await writer.link.worker.read_points(device, points)
        except GatewayError as exc:
            return _error(502, str(exc))
        now = time.monotonic()
        return web.json_response(
            {"values": [sample_view(s, stale=False, now=now) for s in samples]}
        )

    # --- writing ----------------------------------------------------------------------

    async def _write(self, request: web.Request) -> web.StreamResponse:
        device = request.match_info["device"]
        writer = self.writers.get(device)
        if writer is None:
            return _error(404, f"no device {device!r}")
        who = self._who(request)
        try:
            body = await self._body(request)
            signed = await self._signature(request, body, what="the write", required=False)
            if isinstance(signed, web.Response):
                return signed
            actor = request[_SESSION].actor(
                str(request.remote), reason=self._reason(body), signed=signed
            )
            value = body.get("value")
            if isinstance(value, str) and value.lstrip().startswith("{"):
                value = json.loads(value)
            point = writer.point(request.match_info["point"])
            _LOGGER.info("web: %s writes %s/%s = %r", who, device, point.name, value)
            with acting(actor):  # the records of this write name the session's user
                outcome = await writer.set(point, value)
        except (CommandRejectedError, ConfigError, ProfileError, ValueError) as exc:
            _LOGGER.warning("web: write by %s to %s refused: %s", who, device, exc)
            self.state.count_write(device, "web", "rejected")
            return _error(400, str(exc))
        except GatewayError as exc:
            _LOGGER.warning("web: write by %s to %s failed: %s", who, device, exc)
            self.state.count_write(device, "web", "failed")
            return _error(502, str(exc))
        self.state.count_write(device, "web", "ok")
        _LOGGER.info(
            "web: %s wrote %s/%s: %s, the device holds %r",
            who,
            device,
            outcome.point,
            "written" if outcome.written else "unchanged",
            outcome.value,
        )
        return web.json_response(
            {
                "device": device,
                "point": outcome.point,
                "written": outcome.written,
                "value": json_value(outcome.value),  # type: ignore[arg-type]
                "registers": list(outcome.registers),
                "flash": outcome.flash,
                "note": outcome.note,
            }
        )

    async def _start_calibration(self, request: web.Request) -> web.StreamResponse:
        try:
            body = await self._body(request)
            signed = await self._signature(request, body, what="the calibration", required=True)
            if isinstance(signed, web.Response):
                return signed
            inputs = body.get("inputs") or {}
            run = self.calibrations.start(
                str(body.get("device")),
                str(body.get("procedure")),
                inputs,
                self._who(request),
                request[_SESSION].token,
                actor=request[_SESSION].actor(
                    str(request.remote), reason=self._reason(body), signed=signed
                ),
            )
        except CommandRejectedError as exc:
            return _error(400, str(exc))
        return web.json_response(self._run_view(request, run), status=201)

    def _run_view(self, request: web.Request, run: CalibrationRun) -> dict[str, object]:
        """A run as the page shows it, with whether it is the asking session's own."""
        session = request.get(_SESSION) or self._session(request)
        return {**run.as_dict(), "mine": session is not None and session.token == run.session}

    async def _calibrations_under_way(self, request: web.Request) -> web.StreamResponse:
        device = request.query.get("device")
        return web.json_response(
            {"runs": [self._run_view(request, r) for r in self.calibrations.active(device)]}
        )

    async def _calibration(self, request: web.Request) -> web.StreamResponse:
        run = self.calibrations.runs.get(request.match_info["id"])
        if run is None:
            return _error(404, "no such calibration")
        return web.json_response(self._run_view(request, run))

    async def _take_over(self, request: web.Request) -> web.StreamResponse:
        run = self.calibrations.runs.get(request.match_info["id"])
        if run is None:
            return _error(404, "no such calibration")
        try:
            self.calibrations.take_over(run, request[_SESSION].token, self._who(request))
        except CommandRejectedError as exc:
            return _error(409, str(exc))
        return web.json_response(self._run_view(request, run))

    async def _answer(self, request: web.Request) -> web.StreamResponse:
        run = self.calibrations.runs.get(request.match_info["id"])
        if run is None:
            return _error(404, "no such calibration")
        if run.session != request[_SESSION].token:
            _LOGGER.warning(
                "web: %s's answer to the %s calibration of %s refused: it is %s's",
                self._who(request),
                run.procedure.id,
                run.device,
                run.who,
            )
            return _error(
                403,
                f"this calibration belongs to {run.who}'s session: take it over to answer it",
            )
        try:
            body = await self._body(request)
            run.answer(body.get("confirm") is True, self._who(request))
        except CommandRejectedError as exc:
            return _error(409, str(exc))
        await asyncio.sleep(0)  # let the flow take the answer before the page asks again
        return web.json_response(self._run_view(request, run))

    async def _cancel(self, request: web.Request) -> web.StreamResponse:
        run = self.calibrations.runs.get(request.match_info["id"])
        if run is None:
            return _error(404, "no such calibration")
        try:
            run.cancel(self._who(request))
        except CommandRejectedError as exc:
            return _error(409, str(exc))
        return web.json_response(self._run_view(request, run))

    # --- scanning ---------------------------------------------------------------------

    async def _start_scan(self, request: web.Request) -> web.StreamResponse:
        if self.scans is None:
            return _error(404, "scans are not available")
        try:
            body = await self._body(request)
            addresses = str(body.get("addresses") or "1-247")
            job = self.scans.start(request.match_info["bus"], self._who(request), addresses)
        except CommandRejectedError as exc:
            return _error(409, str(exc))
        return web.json_response(job.as_dict(), status=201)

    async def _scan(self, request: web.Request) -> web.StreamResponse:
        job = self.scans.latest(request.match_info["bus"]) if self.scans is not None else None
        if job is None:
            return _error(404, "no scan of this line yet")
        return web.json_response(job.as_dict())

    # --- records and verifications ----------------------------------------------------

    async def _records(self, request: web.Request) -> web.StreamResponse:
        """The records chosen, newest first, with the whole chain's verdict (in a thread)."""
        if self.records is None:
            return _error(404, "the records are not available: this page has no record store")
        query = request.query
        try:
            chosen = RecordsRequest.parse(
                device=query.get("device"),
                kinds=query.getall("kind", []),
                since=query.get("since"),
                until=query.get("until"),
                limit=query.get("limit"),
            )
            answer = await asyncio.to_thread(read_records, self.records.path, chosen)
        except CommandRejectedError as exc:
            return _error(400, str(exc))
        except GatewayError as exc:
            return _error(503, str(exc))
        return web.json_response(answer)

    async def _verification(self, request: web.Request) -> web.StreamResponse:
        """What the verification form of a device starts from: point, unit, rule, offer."""
        if self.verifier is None:
            return _error(503, "verifications are not available: this page has no verifier")
        device = request.match_info["device"]
        writer = self.writers.get(device)
        if writer is None:
            return _error(404, f"no device {device!r}")
        profile = writer.link.profile
        try:
            point = verifiable_point(profile)
        except CommandRejectedError as exc:
            return _error(404, str(exc))
        info = next((i for i in self.state.devices.values() if i.name == device), None)
        latest = None if info is None else self.state.last_good.get((info.bus, device, point.name))
        return web.json_response(
            verification_form(
                device,
                profile.id,
                point,
                unit=latest.unit if latest is not None else None,
                rule=self.verifier.rules(device, profile),
            )
        )

    async def _verify(self, request: web.Request) -> web.StreamResponse:
        """A grab-sample verification, signed with the password again; nothing is written."""
        if self.verifier is None:
            return _error(503, "verifications are not available: this page has no verifier")
        device = request.match_info["device"]
        if device not in self.writers:
            return _error(404, f"no device {device!r}")
        who = self._who(request)
        try:
            body = await self._body(request)
            signed = await self._signature(request, body, what="the verification", required=True)
            if isinstance(signed, web.Response):
                return signed
            asked = VerificationRequest.from_arguments(
                {key: value for key, value in body.items() if key != "password"}
            )
            actor = request[_SESSION].actor(
                str(request.remote), reason=asked.reason[:MAX_REASON], signed=signed
            )
            _LOGGER.info("web: %s verifies %s against %s", who, device, asked.reference)
            with acting(actor):  # the verification's record names the session's user, signed
                verified = await self.verifier.verify(device, asked)
        except CommandRejectedError as exc:
            _LOGGER.warning("web: verification of %s by %s refused: %s", device, who, exc)
            return _error(400, str(exc))
        except GatewayError as exc:
            _LOGGER.warning("web: verification of %s by %s failed: %s", device, who, exc)
            return _error(502, str(exc))
        answer = {"device": device, **verified.as_dict()}
        if not verified.judgement.passed:  # the page offers the calibration care asks for
            answer["calibration"] = calibration_offer(self.writers[device].link.profile.id)
        return web.json_response(answer)
