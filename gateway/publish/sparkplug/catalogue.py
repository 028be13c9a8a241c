"""Which metrics the edge node has, without I/O: names, aliases, types, units, deadbands.

Resolved once at start from the config's devices and their profiles. A device's metrics are
the points it polls of the poll groups the host gets (``sparkplug.groups``: process values
and status by default), named as the profile names them; a bit field is its word (UInt) and
each named bit a Boolean metric ``{point}/{bit}``; an enumeration is its code (UInt) and its
label a String metric ``{point}/label`` beside it, a tag of its own that a host shows and
historises as it is; ``Write/Result`` carries the outcome of the last DCMD. With the group
``care`` (no poll group: the care report the gateway keeps of the device), the report's
metrics under ``care/`` (:data:`CARE_METRICS`), those of a figure only where the family has
it (the slope of tecLine and Reiss, the cap of the O-DO H10/H20). Aliases are
numbered in config order, so they stay the same from one start to the next as long as the
config does; they are unique across the edge node (Sparkplug 3.0,
``tck-id-payloads-alias-uniqueness``). The node's own metrics (``bdSeq``, ``Node
Control/Rebirth``) have none: Sparkplug 3.0 forbids one on the rebirth metric
(``tck-id-operational-behavior-data-commands-rebirth-name-aliases``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final

from gateway.care import CareKind, care_kind
from gateway.config.sparkplug import CARE_GROUP
from gateway.profiles.model import PollGroup
from gateway.publish.sparkplug.payloads import DATATYPE_OF, SpType
from gateway.wire import codec

if TYPE_CHECKING:
    from collections.abc import Collection, Iterable, Mapping

    from gateway.profiles.model import Point, Profile

BD_SEQ: Final = "bdSeq"
REBIRTH: Final = "Node Control/Rebirth"
WRITE_RESULT: Final = "Write/Result"
LABEL: Final = "label"  # an enumeration's label: the metric {point}/label
FIRST_DEVICE_ALIAS: Final = 16  # below: kept free for node metrics
# What a host gets unless the config says otherwise: the measured values and the status
# words, as a SCADA tag list of a sensor has them.
DEFAULT_GROUPS: Final = frozenset({PollGroup.PROCESS, PollGroup.STATUS})
CARE_FOLDER: Final = "care"  # the care report's metrics: care/state, care/due, ...


@dataclass(frozen=True, slots=True, kw_only=True)
class CareMetric:
    """One figure of the care report as a metric ``care/{name}``; ``kinds``: where it is.

    ``name`` is also what the reporter reads of the report (``reports.CARE_VALUES``).
    """

    name: str
    datatype: SpType
    description: str
    kinds: frozenset[CareKind] | None = None  # None: every family care knows


_AMPEROMETRIC: Final = frozenset({CareKind.AMPEROMETRIC})  # tecLine, Reiss: a slope
# The care report's metrics, in the order of a birth. Dates are DateTime (ms since the
# epoch), null when the report has none, as every missing figure is.
CARE_METRICS: Final = (
    CareMetric(
        name="state",
        datatype=SpType.STRING,
        description="sensor care: ok, due_soon, due, unknown or maintenance",
    ),
    CareMetric(
        name="reasons",
        datatype=SpType.STRING,
        description="sensor care: the reasons, the most urgent first, joined with '; '",
    ),
    CareMetric(
        name="last_calibration",
        datatype=SpType.DATETIME,
        description="sensor care: the last calibration",
    ),
    CareMetric(
        name="due",
        datatype=SpType.DATETIME,
        description="sensor care: when the next calibration is due",
    ),
    CareMetric(
        name="slope_ratio",
        datatype=SpType.DOUBLE,
        description="sensor care: the active slope as a fraction of the nominal slope",
        kinds=_AMPEROMETRIC,
    ),
    CareMetric(
        name="slope_limit_projected",
        datatype=SpType.DATETIME,
        description="sensor care: when the falling slope is projected to cross its limit",
        kinds=_AMPEROMETRIC,  # fitted over the calibration history of the slope
    ),
    CareMetric(
        name="cap_usage",
        datatype=SpType.DOUBLE,
        description="sensor care: the measurement counter as a fraction of its maximum (cap)",
        kinds=frozenset({CareKind.OPTICAL_HYGIENIC}),  # O-DO H10/H20
    ),
)


@dataclass(frozen=True, slots=True, kw_only=True)
class MetricSpec:
    """One metric of a device: what its birth says of it, and what it is made from.

    ``point`` is ``None`` for ``Write/Result`` and the care metrics; ``bit`` names the bit
    of a bit field that a Boolean metric carries; ``label`` marks the String metric of an
    enumeration's label; ``care`` names the figure of the care report a care metric carries.
    """

    name: str
    alias: int
    datatype: SpType
    point: Point | None
    bit: str | None = None
    unit: str | None = None
    description: str = ""
    deadband: float = 0.0
    label: bool = False
    care: str | None = None

    @property
    def writable(self) -> bool:
        """Whether a DCMD may write it (an enumeration by its code, never by its label)."""
        return self.point is not None and self.point.writable and not self.label

    @property
    def needs_unit(self) -> bool:
        """Whether its unit comes from a unit register (so its birth waits for that)."""
        return self.point is not None and self.point.unit_from is not None and not self.label


@dataclass(slots=True)
class DeviceMetrics:
    """Every metric of one device, by name, by alias and by the point it comes from."""

    device: str
    profile: str
    metrics: list[MetricSpec] = field(default_factory=list)
    by_name: dict[str, MetricSpec] = field(default_factory=dict)
    by_alias: dict[int, MetricSpec] = field(default_factory=dict)
    of_point: dict[str, MetricSpec] = field(default_factory=dict)
    bits_of: dict[str, list[MetricSpec]] = field(default_factory=dict)
    label_of: dict[str, MetricSpec] = field(default_factory=dict)
    care: list[MetricSpec] = field(default_factory=list)
    result: MetricSpec | None = None

    def add(self, spec: MetricSpec) -> None:
        """Take one metric."""
        self.metrics.append(spec)
        self.by_name[spec.name] = spec
        self.by_alias[spec.alias] = spec


@dataclass(slots=True)
class Catalogue:
    """The edge node's metrics: its devices' in config order."""

    devices: dict[str, DeviceMetrics] = field(default_factory=dict)
    # The first alias no metric of the node has had: a device a reload adds starts there.
    # Aliases of devices a reload removed are not given again while the node lives: a host
    # may still hold them (Sparkplug 3.0: an alias names one metric of the Edge Node).
    next_alias: int = FIRST_DEVICE_ALIAS

    @classmethod
    def build(
        cls,
        devices: Iterable[tuple[str, Profile, Collection[str]]],
        *,
        deadband: float = 0.0,
        deadbands: Mapping[str, Mapping[str, float]] | None = None,
        groups: Collection[str] = DEFAULT_GROUPS,
        device_groups: Mapping[str, Collection[str]] | None = None,
        first_alias: int = FIRST_DEVICE_ALIAS,
    ) -> Catalogue:
        """The metrics of ``(device, profile, names of the points it polls)``, in order.

        ``deadband`` applies to every Float metric without one of its own in ``deadbands``
        (device -> point -> deadband). Only points of ``groups`` (a device's own in
        ``device_groups``) are metrics; ``care`` among them adds the care report's.
        Aliases are numbered from ``first_alias`` (a reload's devices: after the node's).
        """
        deadbands = deadbands or {}
        device_groups = device_groups or {}
        catalogue = cls()
        alias = first_alias
        for name, profile, polled in devices:
            own = deadbands.get(name, {})
            wanted = {str(g) for g in device_groups.get(name, groups)}
            metrics = DeviceMetrics(device=name, profile=profile.id)
            for point in profile.points:
                if point.view or point.name not in polled or point.group.value not in wanted:
                    continue
                datatype = DATATYPE_OF[point.format.dtype]
                default = deadband if datatype is SpType.FLOAT else 0.0
                spec = MetricSpec(
                    name=point.name,
                    alias=alias,
                    datatype=datatype,
                    point=point,
                    unit=point.unit,
                    description=point.description,
                    deadband=own.get(point.name, default),
                )
                alias += 1
                metrics.add(spec)
                metrics.of_point[point.name] = spec
                if point.format.dtype in codec.BITFIELD_TYPES:
                    bits = []
                    for bit in point.format.bits.values():
                        bit_spec = MetricSpec(
                            name=f"{point.name}/{bit}",
                            alias=alias,
                            datatype=SpType.BOOLEAN,
                            point=point,
                            bit=bit,
                            description=f"{point.description}: bit {bit}".strip(": "),
                        )
                        alias += 1
                        metrics.add(bit_spec)
                        bits.append(bit_spec)
                    metrics.bits_of[point.name] = bits
                if point.format.dtype in codec.ENUM_TYPES:
                    label = MetricSpec(
                        name=f"{point.name}/{LABEL}",
                        alias=alias,
                        datatype=SpType.STRING,
                        point=point,
                        description=f"{point.description}: the code's label".strip(": "),
                        label=True,
                    )
                    alias += 1
                    metrics.add(label)
                    metrics.label_of[point.name] = label
            if CARE_GROUP in wanted:
                alias = _add_care(metrics, profile, alias)
            metrics.result = MetricSpec(
                name=WRITE_RESULT,
                alias=alias,
                datatype=SpType.STRING,
                point=None,
                description="the outcome of the last DCMD write, as JSON",
            )
            alias += 1
            metrics.add(metrics.result)
            catalogue.devices[name] = metrics
        catalogue.next_alias = alias
        return catalogue


def _add_care(metrics: DeviceMetrics, profile: Profile, alias: int) -> int:
    """The care report's metrics of a family care knows (none for others); the next alias."""
    kind = care_kind(profile)
    if kind is None:
        return alias
    for care in CARE_METRICS:
        if care.kinds is not None and kind not in care.kinds:
            continue
        spec = MetricSpec(
            name=f"{CARE_FOLDER}/{care.name}",
            alias=alias,
            datatype=care.datatype,
            point=None,
            description=care.description,
            care=care.name,
        )
        alias += 1
        metrics.add(spec)
        metrics.care.append(spec)
    return alias
