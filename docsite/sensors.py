"""One page per sensor family: its profiles and each profile's register map, from the data.

The profiles are the YAML files of ``gateway/profiles/data/``, loaded as the gateway loads
them (:func:`gateway.profiles.builtin_profiles`): every point with its address, type,
access, unit, poll group, storage and meaning, as ``gateway profiles show ID`` prints it.
What the families share (the codec's guarantees, the profile format) is the hand-written
``docs/sensors/index.md``.
"""

from __future__ import annotations

from itertools import groupby
from typing import TYPE_CHECKING, Final

from gateway.profiles import builtin_profiles

if TYPE_CHECKING:
    from gateway.profiles import Point, Profile

# The families in the order the manual lists them, with the title of their page.
FAMILIES: Final = {
    "jumo-digiline-odo-s10": "JUMO digiLine O-DO S10",
    "jumo-digiline-odo-h10-h20": "JUMO digiLine O-DO H10 and H20",
    "jumo-tecline": "JUMO tecLine",
    "reiss-m0c-m3c": "Reiss M0c and M3c",
}


def page_path(family: str) -> str:
    """Where a family's page is in the site."""
    return f"sensors/{family}.md"


def families() -> dict[str, list[Profile]]:
    """The built-in profiles by family: the known families first, in their order."""
    profiles = sorted(builtin_profiles().values(), key=lambda profile: profile.id)
    found: dict[str, list[Profile]] = {}
    for profile in profiles:
        found.setdefault(profile.family, []).append(profile)
    order = [*FAMILIES, *sorted(set(found) - set(FAMILIES))]
    return {family: found[family] for family in order if family in found}


def _cell(text: object) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _unit(point: Point) -> str:
    if point.unit_from:
        return f"from `{point.unit_from}`"
    return point.unit or ""


def _values(point: Point) -> str:
    data = point.as_dict()
    if "enum" in data:
        return ", ".join(f"{code} `{label}`" for code, label in data["enum"].items())
    if "bits" in data:
        return ", ".join(f"bit {bit} `{name}`" for bit, name in data["bits"].items())
    if "range" in data:
        low, high = data["range"]
        return f"{'' if low is None else low} … {'' if high is None else high}"
    return ""


def register_map(profile: Profile) -> list[str]:
    """The profile's points as a Markdown table, by address."""
    lines = [
        "| address | point | type | access | unit | group | storage | values | meaning |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for point in sorted(profile.points, key=lambda p: (p.address, p.name)):
        storage = point.storage.value if point.storage else ""
        lines.append(
            f"| `0x{point.address:04X}` ({point.address}) | `{point.name}` | "
            f"{point.dtype.value}{f' x{point.count}' if point.count > 1 else ''} | "
            f"{point.access.value} | {_cell(_unit(point))} | {point.group.value} | {storage} | "
            f"{_cell(_values(point))} | {_cell(point.description)} |"
        )
    return lines


def _same_map(profiles: list[Profile]) -> list[list[Profile]]:
    """The profiles in runs whose register maps are the same, point for point (one table)."""

    def shape(profile: Profile) -> str:
        return repr([point.as_dict() for point in profile.points])

    return [list(run) for _, run in groupby(profiles, key=shape)]


def page(family: str, profiles: list[Profile]) -> str:
    """A family's page: its profiles, then each register map."""
    title = FAMILIES.get(family, family)
    lines = [
        f"# {title}",
        "",
        (
            f"The register map{'s' if len(profiles) > 1 else ''} of the {title}, from the"
            " profile data the gateway polls with (`gateway/profiles/data/`), made when this"
            " site was built:"
        ),
        "every point with its address (0-based, as the manuals and the config write them),",
        "data type, access (`r` or `rw`), unit, poll group, the storage class of a writable",
        "register (`flash` is never written cyclically) and its meaning.",
        f"`gateway profiles show {profiles[0].id}` prints the same at the command line.",
        "",
        "| profile id | sensor | manual | points |",
        "|---|---|---|---|",
    ]
    lines.extend(
        f"| `{p.id}` | {_cell(p.title)} | `{p.spec}` | {len(p.points)} |" for p in profiles
    )
    runs = _same_map(profiles)
    for run in runs:
        names = ", ".join(f"`{p.id}`" for p in run)
        heading = "Register map" if len(runs) == 1 else f"Register map: {run[0].title}"
        lines += ["", f"## {heading}", ""]
        if len(run) > 1:
            lines += [f"The same register map for {names}, point for point.", ""]
        lines += register_map(run[0])
    return "\n".join(lines) + "\n"
