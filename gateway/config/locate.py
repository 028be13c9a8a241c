"""Problems located: a key path to its file line or its environment variable.

pydantic's errors are told in the config's words: the allowed keys of an unknown one, and
no secret echoed.
"""

from __future__ import annotations

import types
from typing import (
    TYPE_CHECKING,
    Annotated,
    Any,
    Union,
    get_args,
    get_origin,
)

from pydantic import (
    BaseModel,
)

from gateway.config.model import ENV_NESTED_DELIMITER, ENV_PREFIX, GatewayConfig
from gateway.config.problems import KeyPath, Problem, close_matches, format_key

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping

    from pydantic_core import ErrorDetails


class Locator:
    """Turns key paths into :class:`Problem` values with lines or environment names."""

    def __init__(self, lines: Mapping[KeyPath, int], env: Mapping[str, str]) -> None:
        """Locate by the file's ``lines`` (key path -> line) and the variables of ``env``."""
        self._lines = lines
        self._env = {name.upper(): name for name in env}

    def __call__(self, path: KeyPath, message: str) -> Problem:
        """The problem at ``path``: with its variable if the environment set it, else its line."""
        variable = self._variable(path)
        if variable is not None:
            return Problem(format_key(path), None, f"{message} (from {variable})")
        return Problem(format_key(path), self._line(path), message)

    def error(self, error: ErrorDetails) -> Problem:
        """A pydantic error as a problem at its key path."""
        path: KeyPath = tuple(part for part in error["loc"] if part != "[key]")
        return self(path, _describe(error, path))

    def _line(self, path: KeyPath) -> int | None:
        for end in range(len(path), 0, -1):
            line = self._lines.get(path[:end])
            if line is not None:
                return line
        return None

    def _variable(self, path: KeyPath) -> str | None:
        for end in range(len(path), 0, -1):
            name = ENV_PREFIX + ENV_NESTED_DELIMITER.join(str(p) for p in path[:end]).upper()
            if name in self._env:
                return self._env[name]
        return None


def _describe(error: ErrorDetails, path: KeyPath) -> str:
    kind = error["type"]
    if kind == "missing":
        return "required, but missing"
    if kind == "extra_forbidden":
        return _unknown_key(path)
    if kind == "value_error":
        return str(error.get("ctx", {}).get("error", error["msg"]))
    message = error["msg"]
    value = error.get("input")
    secret = any(part == "password" for part in path)
    if not secret and isinstance(value, str | int | float):
        message += f", got {value!r}"
    return message


def _unknown_key(path: KeyPath) -> str:
    key = str(path[-1]) if path else ""
    model = _model_at(path[:-1])
    allowed = list(model.model_fields) if model is not None else []
    if not allowed:
        return "unknown key"
    close = close_matches(key, allowed, n=1)
    hint = f"; did you mean {close[0]}?" if close else ""
    return f"unknown key {key!r}{hint} (allowed: {', '.join(allowed)})"


def _model_at(path: KeyPath) -> type[BaseModel] | None:
    """The model that validates the mapping at ``path``, if any."""
    current: Any = GatewayConfig
    for part in path:
        current = _unwrap(current)
        origin = get_origin(current)
        if origin is list:
            current = get_args(current)[0]
        elif origin is dict:
            current = get_args(current)[1]
        elif isinstance(current, type) and issubclass(current, BaseModel):
            field = current.model_fields.get(str(part))
            if field is None:
                return None
            current = field.annotation
        else:
            return None
    current = _unwrap(current)
    return current if isinstance(current, type) and issubclass(current, BaseModel) else None


def _unwrap(annotation: Any) -> Any:  # noqa: ANN401 - walks arbitrary type expressions
    """``X`` from ``Annotated[X, ...]`` and ``X | None``."""
    while True:
        origin = get_origin(annotation)
        if origin is Annotated:
            annotation = get_args(annotation)[0]
        elif origin is Union or origin is types.UnionType:
            options = [arg for arg in get_args(annotation) if arg is not type(None)]
            if len(options) != 1:
                return annotation
            annotation = options[0]
        else:
            return annotation


def top_level_keys(
    data: Mapping[object, Any], lines: Mapping[KeyPath, int], problems: list[Problem]
) -> dict[str, Any]:
    """The file's top-level mapping as keyword arguments; other keys become problems.

    Keys that are not strings cannot be keywords, and keys with a leading underscore would
    be taken by pydantic-settings as its own options (``_env_file``), so both are refused.
    """
    kept: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(key, str) and not key.startswith("_"):
            kept[key] = value
        else:
            line = lines.get((key,)) if isinstance(key, str | int) else None
            problems.append(Problem(str(key), line, _unknown_key((str(key),))))
    return kept


def in_file_order(problems: Iterable[Problem]) -> list[Problem]:
    """File order; problems from the environment last."""
    return sorted(problems, key=lambda p: (p.line is None, p.line or 0))
