"""The ``verification:`` section: grab-sample checks, their acceptance rules and their window.

A verification compares a sensor's value with a reference analysed by hand (a DPD grab
sample for chlorine, a handheld meter for oxygen). Its rule is the larger of an absolute
deviation and a share of the reference; the built-in rules are EPA Method 334.0's for the
disinfectant sensors (tecLine, Reiss: 0.1 mg/L or 15 %) and the gateway's own default for
oxygen (0.2 mg/L or 5 %, no manual gives one). A rule here, by device name, profile id or
family (the most particular wins), replaces them; ``unit`` is the unit its absolute part
is in, and a sensor reporting in another unit is refused rather than judged wrongly.

Example::

    verification:
      window_minutes: 60     # how late a sample may be entered
      rules:
        jumo-tecline-clo2: {name: plant SOP 12, absolute: 0.05, relative: 0.10, unit: mg/l}
        aeration_1: {name: plant SOP 7, absolute: 0.5, relative: 0.05, unit: "%sat"}
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class AcceptanceRuleConfig(_Model):
    """One rule: pass within the larger of ``absolute`` and ``relative`` times the reference."""

    name: Annotated[str, Field(min_length=1, max_length=80)]
    absolute: Annotated[float, Field(ge=0)]
    relative: Annotated[float, Field(ge=0, le=1)] = 0.0
    unit: Annotated[str | None, Field(min_length=1)] = None  # None: whatever the sensor's
    source: str = ""  # where the rule comes from (an SOP, a permit)


class VerificationConfig(_Model):
    """How grab-sample verifications are judged, and how late one may be entered."""

    # The sensor's value is the one it read when the sample was taken: the gateway keeps
    # this long of each sensor's process value (one value per resolution_s). Both take
    # effect at a restart; the rules at the next verification.
    window_minutes: Annotated[float, Field(gt=0, le=24 * 60)] = 60.0
    resolution_s: Annotated[float, Field(gt=0, le=600)] = 10.0
    rules: dict[str, AcceptanceRuleConfig] = {}  # by device name, profile id or family
