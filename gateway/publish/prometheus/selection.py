"""What Prometheus gets: the poll groups whose points are series, and the old names or not.

Every point is polled whatever is exported; the groups choose only which become series,
as ``sparkplug.groups`` chooses a host's metrics. By default the process values and the
status words (``prometheus.groups``), what a dashboard and an alert of a sensor need; the
gateway's own health, sensor care and ``gateway_device_info`` always. Diagnostics,
configuration and identity points add some 170 series per O-DO H10 and change slowly, if
at all: they are exported when a plant asks for them, plant-wide or per device
(``prometheus.device_groups``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final

from gateway.profiles.model import PollGroup

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping

    from gateway.config.prometheus import PrometheusConfig
    from gateway.line.samples import Sample

DEFAULT_GROUPS: Final = frozenset({PollGroup.PROCESS.value, PollGroup.STATUS.value})
ALL_GROUPS: Final = frozenset(group.value for group in PollGroup)


def _names(groups: Iterable[str]) -> frozenset[str]:
    return frozenset(str(group) for group in groups)


@dataclass(frozen=True, slots=True, kw_only=True)
class Selection:
    """The poll groups exported, plant-wide and per device, and whether old names are too.

    Example::

        Selection()  # process values and status, new names only
        Selection(groups=ALL_GROUPS, legacy_names=True)  # everything, old names beside
        Selection.of(config.prometheus)
    """

    groups: frozenset[str] = DEFAULT_GROUPS
    device_groups: Mapping[str, frozenset[str]] = field(default_factory=dict)
    legacy_names: bool = False

    @classmethod
    def of(cls, settings: PrometheusConfig) -> Selection:
        """The selection a config's ``prometheus:`` section makes."""
        return cls(
            groups=_names(settings.groups),
            device_groups={
                device: _names(groups) for device, groups in settings.device_groups.items()
            },
            legacy_names=settings.legacy_names,
        )

    def exports(self, sample: Sample) -> bool:
        """Whether the sample's point is exported (its poll group is selected for its device)."""
        return sample.group in self.device_groups.get(sample.device, self.groups)
