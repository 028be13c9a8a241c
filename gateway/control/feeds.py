"""Compensation feeds: keep a sensor's compensation values current from other instruments.

A feed takes a number from a polled point of any device (on any bus) or from an MQTT
topic and writes it to a RAM or volatile register of a sensor: the S10 RAM compensation
block (0x25AF-0x25B5) or the H10/H20 volatile compensation temperature (0x2013) and
pressure (0x2017). It writes when ``interval`` has passed since the last write, and at
once when the source moved by more than ``deadband``. It never writes to flash: the
config check refuses a flash-backed target, and :class:`gateway.control.writes.SafeWriter` would
refuse it too (feeds have no flash permission).

Which source the sensor uses is part of the job:

- the S10 uses a RAM value only while its bit in the control byte (0x25AF) is set. Before
  the first write, and again after the sensor was offline (a power cycle resets the RAM),
  the feed reads the control byte and sets its bit, keeping the others (read, modify,
  write), after writing the value, so the sensor never computes with an old RAM value;
- the H10/H20 uses 0x2013 once it is written, until 0x201F is written.

When the source goes stale (no value for ``max_age``), the feed stops writing and hands
the sensor back its own source: the S10 bit is cleared, the H10/H20 gets 0x201F written
(internal temperature) or its default pressure (0x2019) copied to 0x2017. The log says
so, and so do the metrics; the feed resumes with the next fresh value.

Writes run in tasks of their own: a feed is told of new values by the bus tasks (as a
sink), and must never make a bus task wait for a write queued on a bus.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final

from gateway.errors import GatewayError
from gateway.line.samples import Quality
from gateway.shared.state import FeedStatus
from gateway.wire import codec, encoding

if TYPE_CHECKING:
    from collections.abc import Callable, Coroutine, Mapping, Sequence

    from gateway.config import FeedConfig
    from gateway.control.writes import SafeWriter
    from gateway.line.samples import DeviceEvent, Sample
    from gateway.publish.message import Message
    from gateway.shared.state import GatewayState

_LOGGER = logging.getLogger(__name__)

CONTROL_POINT: Final = "compensation_control"  # S10 0x25AF
AUTO_TEMPERATURE_POINT: Final = "auto_temperature_compensation"  # H10/H20 0x201F
DEFAULT_PRESSURE_POINT: Final = "default_compensation_pressure"  # H10/H20 0x2019
TICK_S: Final = 1.0  # how often interval refreshes and staleness are checked


def ram_select_bit(writer: SafeWriter, point: str) -> str | None:
    """The S10 control-byte bit that makes the sensor use ``point``'s RAM value, if any."""
    profile = writer.link.profile
    if not profile.has_point(CONTROL_POINT) or not point.startswith("compensation_"):
        return None
    bit = f"{point.removeprefix('compensation_')}_from_ram"
    return bit if bit in profile.point(CONTROL_POINT).format.bits.values() else None


@dataclass(slots=True)
class _Feed:
    """One configured feed and what it last saw and wrote."""

    config: FeedConfig
    writer: SafeWriter
    status: FeedStatus
    value: float | None = None
    value_at: float = -math.inf
    written: float | None = None
    written_at: float = -math.inf
    selected: bool = False  # the sensor is known to use the fed value (S10 bit set)
    busy: bool = False
    stale_reported: bool = field(default=False)


class FeedEngine:
    """Runs every configured feed: a sink for polled sources, a listener for MQTT ones."""

    def __init__(
        self,
        feeds: Sequence[FeedConfig],
        writers: Mapping[str, SafeWriter],
        *,
        state: GatewayState | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """Prepare the feeds; :meth:`run` refreshes them, :meth:`publish` offers values."""
        self.state = state
        self._clock = clock
        self._feeds: list[_Feed] = []
        for config in feeds:
            status = FeedStatus(feed=config.name, source=config.source.describe())
            self._feeds.append(_Feed(config=config, writer=writers[config.device], status=status))
            if state is not None:
                state.writes.feeds[config.name] = status
        self._by_point: dict[tuple[str, str], list[_Feed]] = {}
        self._by_topic: dict[str, list[_Feed]] = {}
        for feed in self._feeds:
            source = feed.config.source
            if source.topic is not None:
                self._by_topic.setdefault(source.topic, []).append(feed)
            elif source.device is not None and source.point is not None:
                self._by_point.setdefault((source.device, source.point), []).append(feed)
        self._tasks: set[asyncio.Task[None]] = set()

    # --- sources --------------------------------------------------------------------------

    async def publish(self, samples: Sequence[Sample]) -> None:
        """Take polled values (a sink of every bus); a good number feeds its feeds."""
        for sample in samples:
            feeds = self._by_point.get((sample.device, sample.point))
            if not feeds or sample.quality is not Quality.GOOD:
                continue
            value = sample.value
            if isinstance(value, bool) or not isinstance(value, int | float):
                continue
            for feed in feeds:
                self._offer(feed, float(value), sample.monotonic)

    async def device_event(self, event: DeviceEvent) -> None:
        """A target that went offline may come back with its RAM reset: select again."""
        if event.online:
            return
        for feed in self._feeds:
            if feed.config.device == event.device:
                feed.selected = False
                feed.written = None  # write again as soon as it is back

    def subscriptions(self) -> list[str]:
        """The MQTT topics of the feeds that read from the broker."""
        return list(self._by_topic)

    async def handle(self, topic: str, payload: bytes, *, retained: bool = False) -> list[Message]:
        """Take a source value from MQTT: a number, or JSON with the number under ``key``.

        A retained value is taken too: it is the newest the broker has, and its age is
        unknown, so it counts as received now (``max_age`` still ends it).
        """
        del retained
        for feed in self._by_topic.get(topic, []):
            value = _number(payload, feed.config.source.key)
            if value is None:
                feed.status.errors += 1
                _LOGGER.warning(
                    "feed %s: %s carries no number (%r)", feed.config.name, topic, payload[:64]
                )
                continue
            self._offer(feed, value, self._clock())
        return []

    # --- deciding and writing ---------------------------------------------------------------

    def _offer(self, feed: _Feed, value: float, at: float) -> None:
        feed.value, feed.value_at = value, at
        feed.status.source_value, feed.status.source_at = value, at
        if feed.stale_reported:
            feed.stale_reported = feed.status.stale = False
            _LOGGER.info("feed %s: the source is back", feed.config.name)
        self._maybe_write(feed, self._clock())

    def _due(self, feed: _Feed, now: float) -> bool:
        if feed.value is None or now - feed.value_at > feed.config.max_age:
            return False
        if feed.written is None or now - feed.written_at >= feed.config.interval:
            return True
        deadband = feed.config.deadband
        return deadband is not None and abs(feed.value - feed.written) > deadband

    def _maybe_write(self, feed: _Feed, now: float) -> None:
        if feed.busy or not self._due(feed, now):
            return
        assert feed.value is not None  # noqa: S101 - _due checked it
        feed.busy = True
        self._spawn(self._write(feed, feed.value))

    def _spawn(self, work: Coroutine[object, object, None]) -> None:
        task = asyncio.get_running_loop().create_task(work)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _write(self, feed: _Feed, value: float) -> None:
        config = feed.config
        try:
            await feed.writer.set(
                feed.writer.point(config.point), value, read_back=False, feed=True
            )
            bit = ram_select_bit(feed.writer, config.point)
            if bit is not None and not feed.selected:
                await self._select(feed, bit, use_ram=True)
            feed.selected = True
            feed.status.fallback = False
            feed.written, feed.written_at = value, self._clock()
            feed.status.writes += 1
            self._count(feed, "ok")
        except GatewayError as exc:
            feed.status.errors += 1
            feed.written_at = self._clock()  # try again after the interval, not at once
            self._count(feed, "failed")
            _LOGGER.warning("feed %s: writing %g failed: %s", config.name, value, exc)
        finally:
            feed.busy = False

    async def _select(self, feed: _Feed, bit: str, *, use_ram: bool) -> None:
        """Set or clear one bit of the S10 control byte, keeping the others."""
        writer = feed.writer
        target = writer.point(CONTROL_POINT)  # looked up once, for the read and the write
        control = await writer.link.read_point(target)
        if not isinstance(control, codec.BitfieldValue):
            raise GatewayError(f"{writer.device}: the control byte reads {control!r}")
        if dict(control.flags).get(bit) == use_ram:
            return
        # Bits the profile does not name (4-7, for JUMO masters) are kept as read; the
        # raw word, not the bit's name, so the write path does not read the byte again.
        raw = encoding.with_bits(target.format, control.raw, {bit: use_ram})
        await writer.set(target, raw, read_back=False, feed=True)

    # --- refresh and staleness ------------------------------------------------------------

    async def run(self) -> None:
        """Refresh due feeds and hand stale ones back to the sensor's own source."""
        try:
            while True:
                now = self._clock()
                for feed in self._feeds:
                    if self._is_stale(feed, now):
                        self._go_stale(feed)
                    else:
                        self._maybe_write(feed, now)
                await asyncio.sleep(TICK_S)
        finally:
            for task in self._tasks:
                task.cancel()

    def _is_stale(self, feed: _Feed, now: float) -> bool:
        return feed.value is not None and now - feed.value_at > feed.config.max_age

    def _go_stale(self, feed: _Feed) -> None:
        if feed.stale_reported:
            return
        feed.stale_reported = feed.status.stale = True
        _LOGGER.warning(
            "feed %s: no value from %s for %g s; the sensor goes back to its own source",
            feed.config.name,
            feed.status.source,
            feed.config.max_age,
        )
        if feed.written is not None and not feed.busy:
            feed.busy = True
            self._spawn(self._fall_back(feed))

    async def _fall_back(self, feed: _Feed) -> None:
        writer, point = feed.writer, feed.config.point
        try:
            bit = ram_select_bit(writer, point)
            profile = writer.link.profile
            if bit is not None:
                await self._select(feed, bit, use_ram=False)
            elif point == "compensation_temperature" and profile.has_point(AUTO_TEMPERATURE_POINT):
                await writer.set(
                    writer.point(AUTO_TEMPERATURE_POINT), 1, read_back=False, feed=True
                )
            elif point == "compensation_pressure" and profile.has_point(DEFAULT_PRESSURE_POINT):
                default = await writer.link.read_value(DEFAULT_PRESSURE_POINT)
                await writer.set(writer.point(point), default, read_back=False, feed=True)
            feed.selected = False
            feed.written = None
            feed.status.fallback = True
            self._count(feed, "fallback")
        except GatewayError as exc:
            feed.status.errors += 1
            _LOGGER.warning("feed %s: handing back the sensor's own source failed: %s", point, exc)
        finally:
            feed.busy = False

    def _count(self, feed: _Feed, outcome: str) -> None:
        if self.state is not None:
            self.state.count_write(feed.config.device, "feed", outcome)

    async def close(self) -> None:
        """Cancel writes in flight (at shutdown)."""
        for task in list(self._tasks):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


def _number(payload: bytes, key: str) -> float | None:
    """A finite number from a plain or JSON payload, else ``None``."""
    try:
        data = json.loads(payload)
    except (ValueError, UnicodeDecodeError):
        return None
    if isinstance(data, dict):
        data = data.get(key)
    if isinstance(data, bool) or not isinstance(data, int | float):
        return None
    return float(data) if math.isfinite(data) else None
