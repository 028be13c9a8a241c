"""Load the YAML profile files into validated :class:`Profile` values.

A family file may extend a base file and defines variants; each variant becomes a
profile id. Merging happens on plain data (base, then family, then variant), repeated
structures are expanded into points, and only then is every point validated, so an
error names the file, the point and the problem whatever layer introduced it.
"""

from __future__ import annotations

import copy
import functools
import itertools
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from gateway.errors import ConfigError, ProfileError
from gateway.profiles.model import (
    Access,
    FloatOrderRegister,
    Limits,
    Point,
    Profile,
    Quirks,
    SerialSettings,
    Slope,
    Timing,
    WaitRule,
)
from gateway.profiles.schema import (
    MAX_ADDRESS,
    RawEnumEntry,
    RawPoint,
    RawProfile,
    RawRepeat,
    RawTiming,
)
from gateway.wire.codec import (
    BITFIELD_TYPES,
    ENUM_TYPES,
    NUMERIC_TYPES,
    REGISTER_COUNT,
    DataType,
    Format,
)

DATA_DIR = Path(__file__).parent / "data"
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_SOURCE = "_source"  # key added to raw point dicts: the file that last defined them
_BIT_WIDTH = {DataType.BITFIELD: 16, DataType.BITFIELD32: 32}

# Keys a variant may set in addition to the family keys it may override.
_VARIANT_ONLY = {"id", "identify", "unit_availability", "overrides", "remove"}
_MERGED_MAPPINGS = {"timing", "limits", "quirks", "exceptions", "serial"}


def _describe(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(part) for part in err["loc"])
        parts.append(f"{loc}: {err['msg']}" if loc else err["msg"])
    return "; ".join(parts)


# libyaml's parser when PyYAML was built with it (its wheels are): the same safe subset,
# a tenth of the time. The profiles are read at every start of the gateway and of each
# command that names a sensor, where the pure-Python parser took a quarter of a second.
_SAFE_LOADER = yaml.CSafeLoader if yaml.__with_libyaml__ else yaml.SafeLoader


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=_SAFE_LOADER)  # noqa: S506 - a safe loader
    except yaml.YAMLError as exc:
        raise ProfileError(f"not valid YAML: {exc}", source=path.name) from exc
    if not isinstance(data, dict):
        raise ProfileError("the file must be a mapping of profile keys", source=path.name)
    if data.get("family") != path.stem:
        raise ProfileError(
            f"family {data.get('family')!r} must equal the file name {path.stem!r}",
            source=path.name,
        )
    return data


def _expand_repeats(layer: Mapping[str, Any], source: str) -> list[dict[str, Any]]:
    """Points of a layer, with its repeated structures expanded and tagged by source."""
    points = [{**p, _SOURCE: source} for p in layer.get("points", []) or []]
    for raw in layer.get("repeats", []) or []:
        try:
            repeat = RawRepeat.model_validate(raw)
        except ValidationError as exc:
            name = raw.get("name", "?") if isinstance(raw, dict) else "?"
            raise ProfileError(f"repeat {name!r}: {_describe(exc)}", source=source) from exc
        for n in range(repeat.count):
            index = repeat.first_index + n
            for member in repeat.points:
                entry = dict(member)
                if "offset" not in entry:
                    raise ProfileError(
                        f"repeat {repeat.name!r} member needs an 'offset'",
                        source=source,
                        point=str(entry.get("name", "?")),
                    )
                offset = entry.pop("offset")
                entry["name"] = f"{repeat.name}_{index}_{entry.get('name', '?')}"
                entry["address"] = repeat.base + n * repeat.stride + int(offset)
                entry.setdefault("group", repeat.group)
                text = entry.get("description", "")
                entry["description"] = f"{repeat.description} {index}: {text}".strip(": ")
                entry["repeat"] = repeat.name
                entry["index"] = index
                entry[_SOURCE] = source
                points.append(entry)
    return points


def _merge(base: dict[str, Any], layer: Mapping[str, Any], source: str) -> dict[str, Any]:
    """Apply one layer (family or variant) on top of merged data."""
    merged = copy.deepcopy(base)
    points: list[dict[str, Any]] = merged.pop("points", [])
    by_name = {p.get("name"): p for p in points}
    for point in _expand_repeats(layer, source):
        name = point.get("name")
        if name in by_name:
            raise ProfileError(
                "defined twice (to change an inherited point, use overrides)",
                source=source,
                point=str(name),
            )
        by_name[name] = point
        points.append(point)
    for name, changes in (layer.get("overrides") or {}).items():
        if name not in by_name:
            raise ProfileError("overrides a point that does not exist", source=source, point=name)
        by_name[name].update(changes)
        by_name[name][_SOURCE] = source
    for name in layer.get("remove") or []:
        if name not in by_name:
            raise ProfileError("removes a point that does not exist", source=source, point=name)
        points.remove(by_name.pop(name))
    merged["points"] = points
    merged["enums"] = {**merged.get("enums", {}), **(layer.get("enums") or {})}
    merged["readable"] = [*merged.get("readable", []), *(layer.get("readable") or [])]
    for key, value in layer.items():
        if key in {"points", "repeats", "overrides", "remove", "enums", "readable", "variants"}:
            continue
        if key in _MERGED_MAPPINGS and isinstance(value, dict):
            merged[key] = {**(merged.get(key) or {}), **value}
        else:
            merged[key] = value
    return merged


def _resolve_family(
    family: str, raws: Mapping[str, dict[str, Any]], chain: tuple[str, ...] = ()
) -> dict[str, Any]:
    """Merged data of a family and its bases, without variants."""
    if family in chain:
        raise ProfileError(f"extends itself through {' -> '.join(chain)}", source=family)
    if family not in raws:
        parent = chain[-1] if chain else family
        raise ProfileError(f"extends unknown family {family!r}", source=f"{parent}.yaml")
    raw = raws[family]
    base: dict[str, Any] = {}
    if extends := raw.get("extends"):
        base = _resolve_family(str(extends), raws, (*chain, family))
        base.pop("abstract", None)
    layer = {k: v for k, v in raw.items() if k != "extends"}
    return _merge(base, layer, f"{family}.yaml")


def _enum_table(
    raw: str | Mapping[int, Any] | None,
    enums: Mapping[str, Mapping[int, Any]],
    source: str,
    name: str,
) -> tuple[dict[int, str], dict[int, str]]:
    if raw is None:
        raise ProfileError("an enum type needs 'enum'", source=source, point=name)
    if isinstance(raw, str):
        if raw not in enums:
            raise ProfileError(f"unknown enum {raw!r}", source=source, point=name)
        raw = enums[raw]
    labels: dict[int, str] = {}
    units: dict[int, str] = {}
    for code, entry in raw.items():
        if isinstance(entry, RawEnumEntry):
            labels[code] = entry.label
            if entry.unit is not None:
                units[code] = entry.unit
        elif isinstance(entry, Mapping):
            labels[code] = str(entry["label"])
            if entry.get("unit") is not None:
                units[code] = str(entry["unit"])
        else:
            labels[code] = str(entry)
    if len(set(labels.values())) != len(labels):
        raise ProfileError("enum labels must be unique", source=source, point=name)
    return labels, units


def _build_point(raw: dict[str, Any], profile: RawProfile, timing: Timing) -> Point:
    source = str(raw.get(_SOURCE, "?"))
    name = str(raw.get("name", "?"))
    fields = {k: v for k, v in raw.items() if k != _SOURCE}
    dtype_name = fields.get("type")
    if dtype_name not in {t.value for t in DataType}:
        known = ", ".join(t.value for t in DataType)
        raise ProfileError(
            f"unknown type {dtype_name!r} (known: {known})", source=source, point=name
        )
    try:
        rp = RawPoint.model_validate(fields)
    except ValidationError as exc:
        raise ProfileError(_describe(exc), source=source, point=name) from exc
    if not _NAME.match(rp.name):
        raise ProfileError("names must be snake_case", source=source, point=name)

    dtype = rp.type
    count = rp.count
    expected = REGISTER_COUNT.get(dtype)
    if expected is None and count is None:
        raise ProfileError("a string needs 'count' (bytes / 2)", source=source, point=name)
    if expected is not None and count not in {None, expected}:
        raise ProfileError(
            f"{dtype} takes {expected} registers, not {count}", source=source, point=name
        )
    count = count or expected or 0
    if rp.address + count - 1 > MAX_ADDRESS:
        raise ProfileError("runs past address 0xFFFF", source=source, point=name)

    labels: dict[int, str] = {}
    units: dict[int, str] = {}
    if dtype in ENUM_TYPES:
        labels, units = _enum_table(rp.enum, profile.enums, source, name)
    elif rp.enum is not None:
        raise ProfileError(
            f"'enum' needs type enum or enum32, not {dtype}", source=source, point=name
        )
    bits = _bits_table(rp, source)
    _check_unit_and_access(rp, source)
    minimum, maximum = rp.range if rp.range is not None else (None, None)
    fmt = Format(
        dtype=dtype,
        count=count,
        encoding=rp.encoding or "ascii",
        enum=labels,
        bits=bits,
        minimum=minimum,
        maximum=maximum,
        tz_signed_byte=rp.tz == "int8",
        float_faults=profile.float_faults and dtype is DataType.FLOAT32,
    )
    wait = rp.post_write_wait_s
    if wait is None:
        wait = timing.wait_after_write(rp.address, count) if rp.access is Access.READ_WRITE else 0.0
    return Point(
        name=rp.name,
        address=rp.address,
        format=fmt,
        access=rp.access,
        unit=rp.unit if rp.unit_from is None else None,
        unit_from=rp.unit_from,
        enum_units=units,
        storage=rp.storage,
        post_write_wait_s=wait,
        group=rp.group,
        description=rp.description,
        view=rp.view,
        repeat=rp.repeat,
        index=rp.index,
    )


def _bits_table(rp: RawPoint, source: str) -> dict[int, str]:
    if rp.type not in BITFIELD_TYPES:
        if rp.bits is not None:
            raise ProfileError(
                f"'bits' needs a bit field type, not {rp.type}", source=source, point=rp.name
            )
        return {}
    if not rp.bits:
        raise ProfileError("a bit field needs named 'bits'", source=source, point=rp.name)
    width = _BIT_WIDTH[rp.type]
    for bit, bit_name in rp.bits.items():
        if not 0 <= bit < width:
            raise ProfileError(f"bit {bit} outside 0..{width - 1}", source=source, point=rp.name)
        if not _NAME.match(bit_name):
            raise ProfileError(
                f"bit name {bit_name!r} must be snake_case", source=source, point=rp.name
            )
    if len(set(rp.bits.values())) != len(rp.bits):
        raise ProfileError("bit names must be unique", source=source, point=rp.name)
    return dict(rp.bits)


def _check_unit_and_access(rp: RawPoint, source: str) -> None:
    name = rp.name
    if rp.type in NUMERIC_TYPES and "unit" not in rp.model_fields_set and rp.unit_from is None:
        raise ProfileError(
            "missing unit (give 'unit', \"\" for none, or 'unit_from')", source=source, point=name
        )
    if rp.unit_from is not None and "unit" in rp.model_fields_set:
        raise ProfileError("give either 'unit' or 'unit_from'", source=source, point=name)
    if rp.type is DataType.STRING and rp.encoding is None:
        raise ProfileError("a string needs 'encoding'", source=source, point=name)
    if rp.range is not None and rp.range[0] > rp.range[1]:
        raise ProfileError(f"range {list(rp.range)} is empty", source=source, point=name)
    if rp.access is Access.READ_WRITE:
        if rp.storage is None:
            raise ProfileError("a writable point needs 'storage'", source=source, point=name)
        if rp.type in NUMERIC_TYPES and rp.range is None:
            raise ProfileError("a writable number needs a 'range'", source=source, point=name)
    elif rp.storage is not None or rp.range is not None:
        raise ProfileError(
            "'storage' and 'range' apply to writable points only", source=source, point=name
        )


def _timing(raw: RawTiming) -> Timing:
    return Timing(
        min_gap_s=raw.min_gap_s,
        processing_time_s=raw.processing_time_s,
        min_response_time_point=raw.min_response_time_point,
        post_write_wait_s=raw.post_write_wait_s,
        post_write_waits=tuple(
            WaitRule(first=r.first, last=r.last, wait_s=r.wait_s) for r in raw.post_write_waits
        ),
    )


def _checked_runs(raw: RawProfile, source: str) -> list[tuple[int, int]]:
    """The readable runs as a sorted union: overlapping or adjacent runs join.

    Layers add runs (a variant may extend its family's), and two documented runs that
    touch are one run a read may cross.
    """
    runs: list[tuple[int, int]] = []
    for first, last in sorted(raw.readable):
        if not 0 <= first <= last <= MAX_ADDRESS:
            raise ProfileError(
                f"readable run [{first:#06x}, {last:#06x}] is not a range", source=source
            )
        if runs and first <= runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], max(runs[-1][1], last))
        else:
            runs.append((first, last))
    return runs


def _check_map(
    points: list[Point], raw: RawProfile, source: str, origins: Mapping[str, str]
) -> list[tuple[int, int]]:
    """Cross-point checks: overlaps, readable runs, references; returns the joined runs."""
    runs = _checked_runs(raw, source)
    solid = sorted((p for p in points if not p.view), key=lambda p: p.address)
    for a, b in itertools.pairwise(solid):
        if b.address <= a.last:
            raise ProfileError(
                f"overlaps {a.name!r} ({a.address:#06x}..{a.last:#06x}) at {b.address:#06x}; "
                f"in profile {raw.id}; declare one of them a view if that is intended",
                source=origins.get(b.name, source),
                point=b.name,
            )
    by_name = {p.name: p for p in points}
    for p in points:
        if p.count > raw.limits.max_read:
            raise ProfileError(
                "needs more registers than one read may take",
                source=origins.get(p.name, source),
                point=p.name,
            )
        if not any(first <= p.address and p.last <= last for first, last in runs):
            raise ProfileError(
                f"{p.address:#06x}..{p.last:#06x} lies outside every readable run "
                f"of profile {raw.id}",
                source=origins.get(p.name, source),
                point=p.name,
            )
        if p.unit_from is not None:
            ref = by_name.get(p.unit_from)
            if ref is None or not ref.enum_units:
                raise ProfileError(
                    f"unit_from {p.unit_from!r} must name an enum point whose entries carry units",
                    source=origins.get(p.name, source),
                    point=p.name,
                )
    _check_references(by_name, raw, source)
    return runs


def _check_references(by_name: Mapping[str, Point], raw: RawProfile, source: str) -> None:
    references = {
        "float_order_register": raw.float_order_register.point
        if raw.float_order_register
        else None,
        "timing.min_response_time_point": raw.timing.min_response_time_point,
        **{f"identify.{name}": name for name in raw.identify},
    }
    for key, name in references.items():
        if name is not None and name not in by_name:
            raise ProfileError(f"{key} names unknown point {name!r}", source=source)
    unit_labels = {
        label for p in by_name.values() if p.enum_units for label in p.format.enum.values()
    }
    for mode, labels in raw.unit_availability.items():
        for label in labels:
            if label not in unit_labels:
                raise ProfileError(
                    f"unit_availability.{mode}: {label!r} is not a unit label", source=source
                )


def _build_profile(merged: dict[str, Any], source: str) -> Profile:
    fields = {k: v for k, v in merged.items() if k not in {"points", "abstract", "variants"}}
    try:
        raw = RawProfile.model_validate(fields)
    except ValidationError as exc:
        raise ProfileError(
            f"variant {merged.get('id')!r}: {_describe(exc)}", source=source
        ) from exc
    if raw.care == "amperometric" and raw.slope is None:
        msg = f"variant {raw.id!r}: care 'amperometric' needs 'slope' (its limit and units)"
        raise ProfileError(msg, source=source)
    timing = _timing(raw.timing)
    points = sorted(
        (_build_point(p, raw, timing) for p in merged.get("points", [])),
        key=lambda p: (p.address, p.view),
    )
    origins = {str(p.get("name")): str(p.get(_SOURCE, source)) for p in merged.get("points", [])}
    runs = _check_map(points, raw, source, origins)
    return Profile(
        id=raw.id,
        family=raw.family,
        title=raw.title,
        spec=raw.spec,
        source=source,
        points=tuple(points),
        readable=tuple(runs),
        float_order=raw.float_order,
        float_order_register=(
            FloatOrderRegister(
                point=raw.float_order_register.point, orders=dict(raw.float_order_register.orders)
            )
            if raw.float_order_register
            else None
        ),
        float_faults=raw.float_faults,
        limits=Limits(max_read=raw.limits.max_read, max_write=raw.limits.max_write),
        timing=timing,
        quirks=Quirks(string_byte_count_16bit=raw.quirks.string_byte_count_16bit),
        exceptions=dict(raw.exceptions),
        serial=SerialSettings(**raw.serial.model_dump()) if raw.serial else None,
        identify=dict(raw.identify),
        unit_availability={mode: tuple(labels) for mode, labels in raw.unit_availability.items()},
        care=raw.care,
        slope=(
            Slope(limit=raw.slope.limit, ppm_per_unit=dict(raw.slope.ppm_per_unit))
            if raw.slope
            else None
        ),
    )


def load_profiles(directory: Path | None = None) -> dict[str, Profile]:
    """Load every profile defined by the YAML files in ``directory`` (default: built-in)."""
    directory = directory or DATA_DIR
    raws = {path.stem: _read_yaml(path) for path in sorted(directory.glob("*.yaml"))}
    profiles: dict[str, Profile] = {}
    for family, raw in raws.items():
        if raw.get("abstract"):
            continue
        source = f"{family}.yaml"
        variants = raw.get("variants") or []
        if not variants:
            raise ProfileError("defines no variants (or mark it abstract)", source=source)
        merged_family = _resolve_family(family, raws)
        for variant in variants:
            if not isinstance(variant, dict) or "id" not in variant:
                raise ProfileError("every variant needs an 'id'", source=source)
            unknown = (
                set(variant)
                - _VARIANT_ONLY
                - set(RawProfile.model_fields)
                - {"points", "repeats", "enums", "readable"}
            )
            if unknown:
                raise ProfileError(
                    f"variant {variant['id']!r} has unknown keys {sorted(unknown)}", source=source
                )
            merged = _merge(merged_family, variant, source)
            merged.pop("overrides", None)
            merged.pop("remove", None)
            profile = _build_profile(merged, source)
            if profile.id in profiles:
                raise ProfileError(f"profile id {profile.id!r} is defined twice", source=source)
            profiles[profile.id] = profile
    return profiles


@functools.cache
def builtin_profiles() -> Mapping[str, Profile]:
    """The profiles shipped with the gateway, loaded once per process."""
    return load_profiles()


def get_profile(profile_id: str) -> Profile:
    """A built-in profile by id, or a :class:`ConfigError` listing the known ids."""
    profiles = builtin_profiles()
    try:
        return profiles[profile_id]
    except KeyError:
        known = ", ".join(sorted(profiles))
        raise ConfigError(
            f"unknown profile {profile_id!r}; known: {known}", key="profile"
        ) from None
