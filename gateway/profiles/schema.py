"""The profile files' schema: what a merged variant must hold, as pydantic models.

The loader (:mod:`gateway.profiles.loader`) merges the YAML layers on plain data, then
validates the variant with :class:`RawProfile` and each point with :class:`RawPoint`, so
that an error names the file, the point and the problem whatever layer introduced it.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from gateway.profiles.model import (  # noqa: TC001 - pydantic resolves them at run time
    Access,
    PollGroup,
    Storage,
)
from gateway.wire.codec import DataType, WordOrder

MAX_ADDRESS = 0xFFFF


class Strict(BaseModel):
    """A model that refuses keys it does not know (a typo is an error, not ignored)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class RawEnumEntry(Strict):
    """An enumeration entry that also selects a unit (``{label: ppm, unit: "ppm"}``)."""

    label: str
    unit: str | None = None


class RawPoint(Strict):
    """One point of a merged variant, before its format is built and checked."""

    name: str
    address: Annotated[int, Field(ge=0, le=MAX_ADDRESS)]
    type: DataType
    count: Annotated[int, Field(ge=1, le=125)] | None = None
    access: Access
    unit: str | None = None
    unit_from: str | None = None
    enum: str | dict[int, str | RawEnumEntry] | None = None
    bits: dict[int, str] | None = None
    range: tuple[float, float] | None = None
    storage: Storage | None = None
    post_write_wait_s: Annotated[float, Field(ge=0)] | None = None
    group: PollGroup
    description: Annotated[str, Field(min_length=1)]
    encoding: Literal["ascii", "utf-8", "iso-8859-1"] | None = None
    tz: Literal["int8", "int16"] | None = None
    view: bool = False
    repeat: str | None = None
    index: int | None = None


class RawRepeat(Strict):
    """A repeated structure (a ring), expanded into points named ``NAME_N_FIELD``."""

    name: str
    count: Annotated[int, Field(ge=1)]
    first_index: int = 1
    base: Annotated[int, Field(ge=0, le=MAX_ADDRESS)]
    stride: Annotated[int, Field(ge=1)]
    group: PollGroup | None = None
    description: str = ""
    points: list[dict[str, Any]]


class RawWaitRule(Strict):
    """A post-write wait for the writes that touch ``first``..``last``."""

    first: int
    last: int
    wait_s: Annotated[float, Field(ge=0)]


class RawTiming(Strict):
    """The manual's timing rules."""

    min_gap_s: Annotated[float, Field(ge=0)] = 0.0
    processing_time_s: Annotated[float, Field(gt=0)] = 0.1
    min_response_time_point: str | None = None
    post_write_wait_s: Annotated[float, Field(ge=0)] = 0.0
    post_write_waits: list[RawWaitRule] = []


class RawSerial(Strict):
    """The factory serial settings."""

    address: Annotated[int, Field(ge=1, le=247)] | None = None
    baudrate: int | None = None
    parity: Literal["N", "E", "O"] | None = None
    stopbits: Literal[1, 2] | None = None


class RawLimits(Strict):
    """Registers per read and per write."""

    max_read: Annotated[int, Field(ge=1, le=125)] = 125
    max_write: Annotated[int, Field(ge=1, le=123)] | Literal[125] = 123


class RawQuirks(Strict):
    """Documented deviations from standard Modbus."""

    string_byte_count_16bit: bool = False


class RawSlope(Strict):
    """An amperometric cell's slope limit and the ppm in each concentration unit."""

    limit: Annotated[float, Field(gt=0, lt=1)]
    ppm_per_unit: dict[str, Annotated[float, Field(gt=0)]]


class RawFloatOrderRegister(Strict):
    """The register that selects the float word order."""

    point: str
    orders: dict[int, WordOrder]


class RawProfile(Strict):
    """A fully merged variant, before its points are validated one by one."""

    id: str
    family: str
    title: str
    spec: str
    float_order: WordOrder = WordOrder.CDAB
    float_order_register: RawFloatOrderRegister | None = None
    float_faults: bool = False
    limits: RawLimits = RawLimits()
    timing: RawTiming = RawTiming()
    quirks: RawQuirks = RawQuirks()
    exceptions: dict[int, str] = {}
    serial: RawSerial | None = None
    readable: list[tuple[int, int]] = []
    enums: dict[str, dict[int, str | RawEnumEntry]] = {}
    identify: dict[str, int] = {}
    unit_availability: dict[str, list[str]] = {}
    care: Literal["amperometric", "optical_hygienic", "optical"] | None = None
    slope: RawSlope | None = None
