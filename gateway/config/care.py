"""The ``care:`` settings: calibration intervals and limits, for the plant, a profile, a device.

Every key is optional at every level; a device's own ``care:`` wins over its profile's
entry in ``care.profiles`` (by profile id, or by family for all its variants), which wins
over the top-level ``care:``, which wins over the family's default from its manual
(the manual: Sensor care, where each default and its source are listed). Example::

    care:
      due_soon_days: 2
      profiles:
        jumo-digiline-odo-h10: {calibration_interval_days: 14, cip_cycles_limit: 30}
    devices:
      - name: basin_chlorine
        care: {calibration_interval_days: 3}
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field


class CareSettings(BaseModel):
    """Care settings of one level; ``None`` (absent): the next level decides."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool | None = None
    # Days from the last calibration to the next (tecLine annex 7.3.4: "ideally weekly").
    calibration_interval_days: Annotated[float, Field(gt=0, le=3650)] | None = None
    # How many days before it is due a calibration is reported as due soon.
    due_soon_days: Annotated[float, Field(ge=0, le=365)] | None = None
    # tecLine/Reiss: the slope / nominal slope below which the sensor needs maintenance.
    slope_limit: Annotated[float, Field(gt=0, lt=1)] | None = None
    # The least r² of the slope's least-squares fit that a projection is made from.
    min_fit_r2: Annotated[float, Field(ge=0, le=1)] | None = None
    # A projected slope limit closer than this is reported as due soon.
    projection_warn_days: Annotated[float, Field(ge=0, le=3650)] | None = None
    # H10/H20: measurement counter / its maximum from which a new cap is due soon.
    cap_usage_warn: Annotated[float, Field(gt=0, le=1)] | None = None
    # H10/H20: cycles and hours since the last calibration that make a calibration due.
    cip_cycles_limit: Annotated[int, Field(ge=1)] | None = None
    sip_cycles_limit: Annotated[int, Field(ge=1)] | None = None
    hours_outside_temperature_limit: Annotated[float, Field(gt=0)] | None = None


class CareConfig(CareSettings):
    """The top-level ``care:``: the plant's settings and those of profiles or families."""

    profiles: dict[str, CareSettings] = {}
