"""Which metrics the edge node has, without I/O: names, aliases, types, units, deadbands.

Resolved once at start from the config's devices and their profiles. A device's metrics are
the points it polls of the poll groups the host gets (``sparkplug.groups``: process values
and status by default), named as the profile names them; a bit field is its word (UInt) and
each named bit a Boolean metric ``{point}/{bit}``; an enumeration is its code (UInt) and its
label a String metric ``{point}/label`` beside it, a tag of its own that a host shows and
historises as it is; ``Write/Result`` carries the outcome of the last DCMD. Aliases are
numbered in config order, so they stay the same from one start to the next as long as the
config does; they are unique across the edge node (Sparkplug 3.0,
``tck-id-payloads-alias-uniqueness``). The node's own metrics (``bdSeq``, ``Node
Control/Rebirth``) have none: Sparkplug 3.0 forbids one on the rebirth metric
(``tck-id-operational-behavior-data-commands-rebirth-name-aliases``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final

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


@dataclass(frozen=True, slots=True, kw_only=True)
class MetricSpec:
    """One metric of a device: what its birth says of it, and what it is made from.

    ``point`` is ``None`` for ``Write/Result``; ``bit`` names the bit of a bit field that
    a Boolean metric carries; ``label`` marks the String metric of an enumeration's label.
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

    @classmethod
    def build(
        cls,
        devices: Iterable[tuple[str, Profile, Collection[str]]],
        *,
        deadband: float = 0.0,
        deadbands: Mapping[str, Mapping[str, float]] | None = None,
        groups: Collection[str] = DEFAULT_GROUPS,
        device_groups: Mapping[str, Collection[str]] | None = None,
    ) -> Catalogue:
        """The metrics of ``(device, profile, names of the points it polls)``, in order.

        ``deadband`` applies to every Float metric without one of its own in ``deadbands``
        (device -> point -> deadband). Only points of ``groups`` (a device's own in
        ``device_groups``) are metrics.
        """
        deadbands = deadbands or {}
        device_groups = device_groups or {}
        catalogue = cls()
        alias = FIRST_DEVICE_ALIAS
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
        return catalogue
