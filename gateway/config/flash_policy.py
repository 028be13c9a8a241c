"""A device's flash-write permission, as the config states it and the write guard reads it."""

from __future__ import annotations

from dataclasses import dataclass

from gateway.errors import ConfigError


@dataclass(frozen=True, slots=True, kw_only=True)
class FlashPolicy:
    """One device's permission to write flash-backed points.

    Example::

        FlashPolicy(allowed=frozenset({"x_span", "calibration_stamp"}), daily_budget=4)
    """

    allowed: frozenset[str]
    daily_budget: int

    def __post_init__(self) -> None:
        """A negative budget is a configuration mistake, not "no writes"."""
        if self.daily_budget < 0:
            raise ConfigError(
                f"the daily flash-write budget must be 0 or more, got {self.daily_budget}",
                key="flash_writes",
            )
