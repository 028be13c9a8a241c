"""The page's calibrations: start one, follow it, answer it, take it over, cancel it.

The runs themselves are :mod:`gateway.web.calibration`'s; these are their routes. A run's
answer is taken only from the session that owns it; another signed-in session may take the
run over or cancel it.
"""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING

from aiohttp import web

from gateway.errors import CommandRejectedError
from gateway.web.guards import SESSION, error, json_body, reason, who

if TYPE_CHECKING:
    from gateway.web.calibration import CalibrationRun, Calibrations
    from gateway.web.guards import Guards

_LOGGER = logging.getLogger(__name__)


class CalibrationRoutes:
    """``/api/calibrations`` and each run's answer, take-over and cancel."""

    def __init__(self, calibrations: Calibrations, guards: Guards) -> None:
        """Route to ``calibrations``; sessions and signatures by ``guards``."""
        self.calibrations = calibrations
        self.guards = guards

    async def start(self, request: web.Request) -> web.StreamResponse:
        """A guided run of a procedure, signed with the user's password again."""
        try:
            body = await json_body(request)
            signed = await self.guards.signature(
                request, body, what="the calibration", required=True
            )
            if isinstance(signed, web.Response):
                return signed
            inputs = body.get("inputs") or {}
            run = self.calibrations.start(
                str(body.get("device")),
                str(body.get("procedure")),
                inputs,
                who(request),
                request[SESSION].token,
                actor=request[SESSION].actor(
                    str(request.remote), reason=reason(body), signed=signed
                ),
            )
        except CommandRejectedError as exc:
            return error(400, str(exc))
        return web.json_response(self.view(request, run), status=201)

    def view(self, request: web.Request, run: CalibrationRun) -> dict[str, object]:
        """A run as the page shows it, with whether it is the asking session's own."""
        session = request.get(SESSION) or self.guards.session_of(request)
        return {**run.as_dict(), "mine": session is not None and session.token == run.session}

    async def under_way(self, request: web.Request) -> web.StreamResponse:
        """The runs under way, of one device if ``device`` says."""
        device = request.query.get("device")
        return web.json_response(
            {"runs": [self.view(request, r) for r in self.calibrations.active(device)]}
        )

    async def one(self, request: web.Request) -> web.StreamResponse:
        """One run: its steps, its question, its outcome."""
        run = self.calibrations.runs.get(request.match_info["id"])
        if run is None:
            return error(404, "no such calibration")
        return web.json_response(self.view(request, run))

    async def take_over(self, request: web.Request) -> web.StreamResponse:
        """The run becomes the asking session's (its operator left, a phone died)."""
        run = self.calibrations.runs.get(request.match_info["id"])
        if run is None:
            return error(404, "no such calibration")
        try:
            self.calibrations.take_over(run, request[SESSION].token, who(request))
        except CommandRejectedError as exc:
            return error(409, str(exc))
        return web.json_response(self.view(request, run))

    async def answer(self, request: web.Request) -> web.StreamResponse:
        """The run's question answered, only from the run's own session."""
        run = self.calibrations.runs.get(request.match_info["id"])
        if run is None:
            return error(404, "no such calibration")
        if run.session != request[SESSION].token:
            _LOGGER.warning(
                "web: %s's answer to the %s calibration of %s refused: it is %s's",
                who(request),
                run.procedure.id,
                run.device,
                run.who,
            )
            return error(
                403,
                f"this calibration belongs to {run.who}'s session: take it over to answer it",
            )
        try:
            body = await json_body(request)
            run.answer(body.get("confirm") is True, who(request))
        except CommandRejectedError as exc:
            return error(409, str(exc))
        await asyncio.sleep(0)  # let the flow take the answer before the page asks again
        return web.json_response(self.view(request, run))

    async def cancel(self, request: web.Request) -> web.StreamResponse:
        """The run cancelled, before its writes."""
        run = self.calibrations.runs.get(request.match_info["id"])
        if run is None:
            return error(404, "no such calibration")
        try:
            run.cancel(who(request))
        except CommandRejectedError as exc:
            return error(409, str(exc))
        return web.json_response(self.view(request, run))
