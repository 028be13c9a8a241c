"""The page's records view and grab-sample verifications.

The records are read by a read-only store of their own in a worker thread
(:func:`~gateway.web.records.read_records`); a verification is signed with the user's
password again and writes nothing to a sensor.
"""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING

from aiohttp import web

from gateway.control.verification import VerificationRequest, verifiable_point
from gateway.errors import CommandRejectedError, GatewayError
from gateway.records.actor import acting
from gateway.web.care import calibration_offer
from gateway.web.guards import MAX_REASON, SESSION, error, json_body, who
from gateway.web.records import RecordsRequest, read_records, verification_form

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.control.verification import Verifier
    from gateway.control.writes import SafeWriter
    from gateway.records import RecordStore
    from gateway.shared.state import GatewayState
    from gateway.web.guards import Guards

_LOGGER = logging.getLogger(__name__)


class RecordRoutes:
    """``GET /api/records``, a device's verification form and ``POST .../verify``."""

    def __init__(
        self,
        store: RecordStore | None,
        verifier: Verifier | None,
        writers: Mapping[str, SafeWriter],
        state: GatewayState,
        guards: Guards,
    ) -> None:
        """Without ``store`` the records answer 404; without ``verifier``, verifications 503."""
        self.store = store
        self.verifier = verifier
        self.writers = writers
        self.state = state
        self.guards = guards

    async def records(self, request: web.Request) -> web.StreamResponse:
        """The records chosen, newest first, with the whole chain's verdict (in a thread)."""
        if self.store is None:
            return error(404, "the records are not available: this page has no record store")
        query = request.query
        try:
            chosen = RecordsRequest.parse(
                device=query.get("device"),
                kinds=query.getall("kind", []),
                since=query.get("since"),
                until=query.get("until"),
                limit=query.get("limit"),
            )
            answer = await asyncio.to_thread(read_records, self.store.path, chosen)
        except CommandRejectedError as exc:
            return error(400, str(exc))
        except GatewayError as exc:
            return error(503, str(exc))
        return web.json_response(answer)

    async def verification(self, request: web.Request) -> web.StreamResponse:
        """What the verification form of a device starts from: point, unit, rule, offer."""
        if self.verifier is None:
            return error(503, "verifications are not available: this page has no verifier")
        device = request.match_info["device"]
        writer = self.writers.get(device)
        if writer is None:
            return error(404, f"no device {device!r}")
        profile = writer.link.profile
        try:
            point = verifiable_point(profile)
        except CommandRejectedError as exc:
            return error(404, str(exc))
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

    async def verify(self, request: web.Request) -> web.StreamResponse:
        """A grab-sample verification, signed with the password again; nothing is written."""
        if self.verifier is None:
            return error(503, "verifications are not available: this page has no verifier")
        device = request.match_info["device"]
        if device not in self.writers:
            return error(404, f"no device {device!r}")
        by = who(request)
        try:
            body = await json_body(request)
            signed = await self.guards.signature(
                request, body, what="the verification", required=True
            )
            if isinstance(signed, web.Response):
                return signed
            asked = VerificationRequest.from_arguments(
                {key: value for key, value in body.items() if key != "password"}
            )
            actor = request[SESSION].actor(
                str(request.remote), reason=asked.reason[:MAX_REASON], signed=signed
            )
            _LOGGER.info("web: %s verifies %s against %s", by, device, asked.reference)
            with acting(actor):  # the verification's record names the session's user, signed
                verified = await self.verifier.verify(device, asked)
        except CommandRejectedError as exc:
            _LOGGER.warning("web: verification of %s by %s refused: %s", device, by, exc)
            return error(400, str(exc))
        except GatewayError as exc:
            _LOGGER.warning("web: verification of %s by %s failed: %s", device, by, exc)
            return error(502, str(exc))
        answer = {"device": device, **verified.as_dict()}
        if not verified.judgement.passed:  # the page offers the calibration care asks for
            answer["calibration"] = calibration_offer(self.writers[device].link.profile.id)
        return web.json_response(answer)
