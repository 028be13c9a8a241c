"""The running gateway's records: the store and everything that writes to it or reads it.

:class:`AuditTrail` holds, for the whole run, the record store of ``state_dir`` and its
companions (compensation feeds counted per day, the host clock watched, the sensors'
history copied, each device's recent process values for verifications), hands each new
record to MQTT and to sensor care, and answers ``gateway verify`` through the metrics
port in the event loop. The write paths get the store from it
(:class:`~gateway.app.buses.Buses`).
"""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING, Final

from gateway.control.verification import VerificationRequest, Verifier
from gateway.errors import CommandRejectedError, GatewayError, RecordError
from gateway.records import Actor, FeedCounts, Kind, Query, RecordStore, Via, acting, records_path
from gateway.records.clock_watch import ClockWatch
from gateway.records.history import HistoryKeeper, device_refs
from gateway.records.interrupted import close_interrupted
from gateway.records.messages import head_message, record_message
from gateway.records.recent import RecentValues
from gateway.records.verification import care_verification, rule_for

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping
    from pathlib import Path

    from gateway.config import GatewayConfig
    from gateway.control.writes import SafeWriter
    from gateway.profiles import Profile
    from gateway.publish.message import Message
    from gateway.publish.mqtt import MqttSink
    from gateway.records import Record
    from gateway.records.verification import AcceptanceRule
    from gateway.shared.state import GatewayState

_LOGGER = logging.getLogger(__name__)

VERIFY_TIMEOUT_S: Final = 30.0  # gateway verify's wait for the running gateway
LOOK_EVERY_S: Final = 5.0  # the clock and the records other processes appended


class AuditTrail:
    """The records of one run, and the parts around them."""

    def __init__(
        self,
        state_dir: Path,
        state: GatewayState,
        *,
        config: Callable[[], GatewayConfig],
        mqtt: Callable[[], MqttSink | None],
        points: Mapping[str, str],
    ) -> None:
        """Open the store in ``state_dir``; ``config`` and ``mqtt``: the run's, a reload's too.

        ``points``: each device's point a verification compares (its process value).
        """
        self.state = state
        self._config = config
        self._mqtt = mqtt
        settings = config().verification
        self.store = RecordStore(
            records_path(state_dir),
            clock_synchronised=lambda: state.clock.status().synchronised,
        )
        state.storage.track(self.store.health)
        state.writes.records_head = lambda: self.store.head
        self.feeds = FeedCounts(self.store, profiles=self._profile_of)
        self.clock_watch = ClockWatch(self.store, state.clock)
        # Each entry of a sensor's own history or logbook copied once, and the whole copy
        # handed to sensor care for its trend (the sensors' rings keep 5 or 10).
        self.history = HistoryKeeper(self.store)
        state.care.keep_history(self.history.for_care(device_refs(state)))
        self.recent = RecentValues(
            points,
            window_s=settings.window_minutes * 60,
            resolution_s=settings.resolution_s,
        )
        self.verifier: Verifier | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def verify_with(self, writers: Mapping[str, SafeWriter]) -> Verifier:
        """The verifications of the devices of ``writers`` (the run's own dictionary)."""
        self.verifier = Verifier(writers, self.recent, self._rule)
        self.state.writes.verify = self.verify_from_thread
        return self.verifier

    def start(self) -> None:
        """In the event loop, before any write: close what the last run left, then listen."""
        self._loop = asyncio.get_running_loop()
        try:
            close_interrupted(self.store)  # a write the last run left without its answer
            for record in self.store.records(Query(kinds=(Kind.VERIFICATION,))):
                self._to_care(record)
        except RecordError as exc:  # polling goes on; writes are refused until it can
            _LOGGER.warning(
                "%s; a write the last run left unanswered is closed at the next start", exc
            )
        self.store.listen(self._publish)
        self.store.listen(self._to_care)
        mqtt = self._mqtt()
        if mqtt is not None:
            mqtt.outbox.enqueue(self.retained())

    def retained(self) -> list[Message]:
        """What the records keep retained on MQTT: the chain's head (for a server without it)."""
        return [head_message(self._config().mqtt.base_topic, self.store.head)]

    async def run(self) -> None:
        """Every few seconds: the host clock watched, other processes' records caught up."""
        while True:
            try:
                self.clock_watch.look()
                self.store.catch_up()
            except GatewayError as exc:  # the records' trouble never stops the polling
                _LOGGER.warning("the records' look failed: %s", exc)
            await asyncio.sleep(LOOK_EVERY_S)

    def close(self) -> None:
        """The day's compensation feeds so far recorded; the store closed."""
        try:
            self.feeds.flush()
        except GatewayError as exc:
            _LOGGER.warning("the compensation feeds' counts were not recorded: %s", exc)
        self.store.close()

    def watch(self, points: Mapping[str, str]) -> None:
        """After a reload: the verifiable points of the devices (new ones added)."""
        for device, point in points.items():
            self.recent.watch(device, point)

    def _profile_of(self, device: str) -> str:
        for configured in self._config().devices:
            if configured.name == device:
                return configured.profile
        return ""

    def _rule(self, device: str, profile: Profile) -> AcceptanceRule | None:
        return rule_for(self._config().verification, device=device, profile=profile)

    def _publish(self, record: Record) -> None:
        """A record to ``{base}/records``, and the chain's new head (retained)."""
        mqtt = self._mqtt()
        if mqtt is not None:
            base = self._config().mqtt.base_topic
            head = head_message(base, self.store.head, time=record.time)
            mqtt.outbox.enqueue([record_message(base, record), head])

    def _to_care(self, record: Record) -> None:
        """A verification's outcome to sensor care (the due date, a failed check)."""
        verification = care_verification(record)
        if verification is not None and record.device is not None:
            self.state.care.verified(record.device, verification)

    # --- gateway verify, through the metrics port ---------------------------------------

    def verify_from_thread(self, body: Mapping[str, object]) -> tuple[int, dict[str, object]]:
        """``POST /verify`` on the metrics port (its own thread): run in the event loop."""
        loop = self._loop
        if loop is None:
            return 503, {"status": "error", "reason": "the gateway is starting"}
        future = asyncio.run_coroutine_threadsafe(self._verify(body), loop)
        try:
            return future.result(timeout=VERIFY_TIMEOUT_S)
        except TimeoutError:
            future.cancel()
            return 504, {"status": "error", "reason": "no outcome in time"}

    async def _verify(self, body: Mapping[str, object]) -> tuple[int, dict[str, object]]:
        arguments = dict(body)
        device = arguments.pop("device", None)
        said = arguments.pop("actor", None)
        who = said if isinstance(said, dict) else {}
        try:
            if not isinstance(device, str) or self.verifier is None:
                raise CommandRejectedError("name the device (device)")  # noqa: TRY301
            request = VerificationRequest.from_arguments(arguments)
            # The command line's operating-system user, as it says (from this machine only).
            actor = Actor(
                user=str(who.get("user") or "unknown"),
                via=Via.CLI,
                detail=str(who.get("detail") or ""),
                reason=request.reason,
            )
            with acting(actor):
                verified = await self.verifier.verify(device, request)
        except CommandRejectedError as exc:
            _LOGGER.warning("verification refused: %s", exc)
            return 400, {"status": "refused", "reason": str(exc)}
        except GatewayError as exc:
            _LOGGER.warning("verification failed: %s", exc)
            return 500, {"status": "error", "reason": str(exc)}
        return 200, {"status": "ok", "device": device, **verified.as_dict()}
