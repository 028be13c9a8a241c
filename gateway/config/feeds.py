"""The ``feeds:`` section: compensation values kept current from another instrument."""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

from gateway.config.fields import Seconds  # noqa: TC001 - pydantic resolves it at run time


class _Model(BaseModel):
    # The same as config.model's: declared here, on BaseModel, so ruff still sees pydantic
    # models, whose list defaults are copied per instance.
    model_config = ConfigDict(extra="forbid", frozen=True)


def _feed_topic(value: str) -> str:
    if not value or {"+", "#"} & set(value):
        raise ValueError(f"{value!r} is not a topic to read a value from: no wildcards (+, #)")
    return value


class FeedSource(_Model):
    """Where a feed's value comes from: a polled point of any device, or an MQTT topic.

    An MQTT payload is a plain number or JSON: a number, or an object whose ``value``
    (or the configured ``key``) is one.
    """

    device: str | None = None
    point: str | None = None
    topic: Annotated[str, AfterValidator(_feed_topic)] | None = None
    key: Annotated[str, Field(min_length=1)] = "value"

    @model_validator(mode="after")
    def _one_kind(self) -> FeedSource:
        by_point = self.device is not None or self.point is not None
        if by_point and self.topic is not None:
            raise ValueError("give either device and point, or topic, not both")
        if not by_point and self.topic is None:
            raise ValueError("give device and point of a polled value, or an MQTT topic")
        if by_point and (self.device is None or self.point is None):
            raise ValueError("a point source needs both device and point")
        return self

    def describe(self) -> str:
        """The source as text for logs and metrics: ``device/point`` or ``mqtt:topic``."""
        return f"mqtt:{self.topic}" if self.topic is not None else f"{self.device}/{self.point}"


class FeedConfig(_Model):
    """Keep a compensation value of a sensor current from another instrument.

    Written every ``interval`` seconds while the source is fresh, and at once when the
    source moves by more than ``deadband`` since the last write. A source older than
    ``max_age`` is not written (the log and the metrics say so). Feeds only write RAM or
    volatile registers; a flash-backed target is a config error.
    """

    device: str
    point: str
    source: FeedSource
    interval: Seconds = 60.0
    deadband: Annotated[float, Field(ge=0)] | None = None
    max_age: Seconds = 300.0

    @property
    def name(self) -> str:
        """The feed as ``device/point``, its label in logs and metrics."""
        return f"{self.device}/{self.point}"
