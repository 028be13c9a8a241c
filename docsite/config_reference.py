"""The configuration reference: every key of the config's models, its type and default.

Walks :class:`gateway.config.GatewayConfig` and the models under it. A key's description is
its field's ``description`` where it has one, else the comment the model's source puts on
the field's line or on the lines just above it (the config's models are documented that
way), else its model's docstring's first line.
"""

from __future__ import annotations

import enum
import functools
import inspect
import io
import re
import tokenize
import types
import typing
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final, Literal, get_args, get_origin

from pydantic import BaseModel, SecretStr
from pydantic_core import PydanticUndefined

from gateway.config.model import ENV_NESTED_DELIMITER, ENV_PREFIX, GatewayConfig

if TYPE_CHECKING:
    from collections.abc import Iterator

    from pydantic.fields import FieldInfo

PAGE: Final = "reference/configuration.md"


@dataclass(frozen=True)
class Key:
    """One key of the config: its dotted path, type, default and description."""

    path: str
    type: str
    default: str
    description: str


def _models(annotation: object) -> list[type[BaseModel]]:
    """The models an annotation holds (in a list, a dict, an optional)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [model for arg in get_args(annotation) for model in _models(arg)]


def _container(annotation: object) -> str:
    """``[]`` for a list of models, ``.NAME`` for a dict of them, else nothing."""
    origin = get_origin(annotation)
    if origin in {typing.Union, types.UnionType, typing.Annotated}:
        for arg in get_args(annotation):
            found = _container(arg)
            if found:
                return found
        return ""
    if origin in {list, tuple, set, frozenset} and any(
        _models(arg) for arg in get_args(annotation)
    ):
        return "[]"
    if origin is dict and _models(get_args(annotation)[-1]):
        return ".NAME"
    return ""


def type_name(annotation: object) -> str:  # noqa: PLR0911 - one answer per kind of type
    """A reader's name for a field's type."""
    origin = get_origin(annotation)
    args = get_args(annotation)
    if origin is typing.Annotated:
        return type_name(args[0])
    if origin in {typing.Union, types.UnionType}:
        names = [type_name(arg) for arg in args if arg is not type(None)]
        text = " or ".join(dict.fromkeys(names))
        return f"{text} or null" if type(None) in args else text
    if origin is Literal:
        return " | ".join(repr(arg) if isinstance(arg, str) else str(arg) for arg in args)
    if origin in {list, tuple, set, frozenset}:
        return f"list of {type_name(args[0])}" if args else "list"
    if origin is dict:
        return f"map of {type_name(args[0])} to {type_name(args[-1])}" if args else "map"
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return " | ".join(repr(member.value) for member in annotation)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return "object"
    if annotation is SecretStr:
        return "secret string"
    return getattr(annotation, "__name__", str(annotation))


def _default(field: FieldInfo) -> str:
    if field.is_required():
        return "required"
    value = field.default
    if value is PydanticUndefined and field.default_factory is not None:
        try:
            value = field.default_factory()  # type: ignore[call-arg]
        except TypeError:
            return "computed"
    return _shown(value)


def _shown(value: object) -> str:
    """A default as the config file writes it."""
    if isinstance(value, enum.Enum):
        value = value.value
    special = {BaseModel: "(its keys' defaults)", SecretStr: "(secret)"}
    for kind, text in special.items():
        if isinstance(value, kind):
            return text
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (list, tuple, dict)) and not value:
        return "{}" if isinstance(value, dict) else "[]"
    return repr(value) if isinstance(value, str) else str(value)


_BODY_INDENT: Final = 4  # a class body's fields, as the formatter writes them


def _comment_text(token: tokenize.TokenInfo) -> str:
    return re.sub(r"\s*noqa\b.*|\s*type:\s*ignore.*", "", token.string.lstrip("# "))


@functools.cache
def _comments(model: type[BaseModel]) -> dict[str, str]:
    """Each field's comment in the model's source: on its line, or the lines above it."""
    try:
        source = inspect.getsource(model)
    except (OSError, TypeError):
        return {}
    return _source_comments(source)


def _source_comments(source: str) -> dict[str, str]:
    """Each field's comment in a class's source text."""
    above: dict[str, list[str]] = {}  # the comment lines just above each field
    pending: list[str] = []
    field_lines: dict[int, str] = {}
    trailing: dict[int, str] = {}
    depth = 0
    tokens = list(tokenize.generate_tokens(io.StringIO(source).readline))
    for token, after in zip(tokens, [*tokens[1:], tokens[-1]], strict=True):
        if token.type == tokenize.OP and token.string in "([{":
            depth += 1
        elif token.type == tokenize.OP and token.string in ")]}":
            depth -= 1
        elif token.type == tokenize.COMMENT:
            trailing[token.start[0]] = _comment_text(token)
            if token.line.strip().startswith("#") and depth == 0:
                pending.append(_comment_text(token))
        elif token.type == tokenize.NAME and depth == 0 and token.start[1] == _BODY_INDENT:
            if after.string == ":":
                field_lines[token.start[0]] = token.string
                above[token.string] = pending
            pending = []
    found = {name: " ".join(lines) for name, lines in above.items() if lines}
    for line, name in field_lines.items():
        if trailing.get(line):
            found[name] = f"{found[name]} {trailing[line]}" if name in found else trailing[line]
    return {name: text.strip() for name, text in found.items() if text.strip()}


# A comment that still names a section as the README's ("README: X") shows it as the
# manual's: the README's sections are the manual's pages now.
_README: Final = re.compile(r"(?<![/\w])README(?!\.md)")


def _description(model: type[BaseModel], name: str, field: FieldInfo) -> str:
    text = _README.sub("the manual", _code_description(model, name, field))
    return text.replace(". the manual", ". The manual")


def _code_description(model: type[BaseModel], name: str, field: FieldInfo) -> str:
    if field.description:
        return " ".join(field.description.split())
    comment = _comments(model).get(name)
    if comment:
        return comment
    inner = _models(field.annotation)
    if inner and inner[0].__doc__:
        return " ".join(inner[0].__doc__.strip().split("\n\n")[0].split())
    for klass in model.__mro__[1:]:
        if isinstance(klass, type) and issubclass(klass, BaseModel) and name in _comments(klass):
            return _comments(klass)[name]
    return ""


GUIDE: Final = "configuration/index.md"


def guide_meanings(text: str) -> dict[str, str]:
    """The meaning of each key the configuration guide's table names, by dotted path.

    A row names one key in full and the keys beside it by their last parts
    (`` `mqtt.tls.ca`, `cert`, `key` ``): each of those is looked up beside the first.
    """
    found: dict[str, str] = {}
    for line in text.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split(" | ")]
        if len(cells) < 2 or not cells[0].startswith("`"):  # noqa: PLR2004 - key, meaning
            continue
        names = re.findall(r"`([^`]+)`", cells[0])
        if not names:
            continue
        first = names[0].split("…")[0].rstrip(".")
        meaning = " | ".join(cells[1:])
        found.setdefault(first, meaning)
        parent = first.rsplit(".", 1)[0] if "." in first else ""
        for name in names[1:]:
            bare = name.rstrip(".…")
            candidates = [f"{parent}.{bare}" if parent else bare, bare]
            root = first.split(".", 1)[0]
            candidates.append(f"{root}.{bare}")
            for candidate in candidates:
                found.setdefault(candidate, meaning)
    return found


def config_keys(model: type[BaseModel] = GatewayConfig, prefix: str = "") -> Iterator[Key]:
    """Every key under ``model``, depth first, in the models' order."""
    for name, field in model.model_fields.items():
        key = field.alias or name
        path = f"{prefix}{key}"
        annotation = field.annotation
        yield Key(path, type_name(annotation), _default(field), _description(model, name, field))
        seen: set[type[BaseModel]] = set()
        for inner in _models(annotation):
            if inner in seen or inner is model:
                continue
            seen.add(inner)
            yield from config_keys(inner, f"{path}{_container(annotation)}.")


def describe(key: Key, meanings: dict[str, str]) -> str:
    """The key's description: the code's, and the guide's where the guide names it."""
    guide = meanings.get(key.path) or meanings.get(key.path.replace(".NAME", ""))
    if guide and key.description:
        return f"{key.description.rstrip('. ')}. Guide: {guide}"
    if guide or key.description:
        return guide or key.description
    # A key the guide explains with its section: the nearest section it names.
    parent = key.path
    while "." in parent or parent.endswith("[]"):
        parent = parent.removesuffix("[]") if parent.endswith("[]") else parent.rsplit(".", 1)[0]
        for name in (parent, f"{parent}[]", f"{parent}.…", parent.replace(".NAME", ".ID")):
            if name in meanings:
                return f"part of `{name}`: {meanings[name]}"
    return ""


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def page(guide: str = "") -> str:
    """The reference as a Markdown page; ``guide``: the configuration guide's text."""
    meanings = guide_meanings(guide)
    example = f"{ENV_PREFIX}LOGGING{ENV_NESTED_DELIMITER}LEVEL=DEBUG"
    lines = [
        "# Configuration reference",
        "",
        "Every key of the config file, read from the config's own models when this site was",
        "built: its path (`[]` an entry of a list, `NAME` a key you choose), its type, its",
        "default and what the code says of it. The",
        "[configuration guide](../configuration/index.md) explains the keys by task; the",
        "examples in `config/` show them in use.",
        "",
        f"Any key can be set from the environment: `{ENV_PREFIX}` and the path in capitals",
        f"with `{ENV_NESTED_DELIMITER}` between levels (`{example}`).",
        "",
        "| key | type | default | description |",
        "|---|---|---|---|",
    ]
    lines.extend(
        f"| `{key.path}` | {_cell(key.type)} | `{_cell(key.default)}` | "
        f"{_cell(describe(key, meanings))} |"
        for key in config_keys()
    )
    return "\n".join(lines) + "\n"
