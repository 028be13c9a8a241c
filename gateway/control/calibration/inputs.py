"""A calibration's inputs: each parameter with its default and source, checked once.

What a front end gives a procedure (text from the page's form, typed values from the
command line) goes through :meth:`Parameter.parse`: a blank or absent input is the
default, a number is checked against its bounds, a choice against its choices, with an
error that names the input. :class:`Inputs` holds the result, typed, for the flow. The
parameters themselves, with their defaults, are the catalogue's
(:mod:`~gateway.control.calibration.catalogue`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, TypeAlias

from gateway.errors import CommandRejectedError

if TYPE_CHECKING:
    from collections.abc import Mapping

Value: TypeAlias = float | int | str | None


class InputKind(StrEnum):
    """What a parameter holds (the page draws its field by it)."""

    NUMBER = "number"
    INTEGER = "integer"
    CHOICE = "choice"


@dataclass(frozen=True, slots=True, kw_only=True)
class Parameter:
    """One input of a procedure, its default and where the default comes from."""

    name: str  # the page's field and the JSON key; the command line's ``--name``
    label: str  # the page's form label
    help: str  # the command line's option help
    kind: InputKind
    source: str  # the manual's section, or why the number is ours
    default: Value = None  # None: required, or not given (then ``absent`` says what happens)
    absent: str = ""  # what an optional input without a default means when left out
    required: bool = False
    unit: str = ""
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[str, ...] = ()

    @property
    def option(self) -> str:
        """The command line's option: ``--cell-current`` for ``cell_current``."""
        return "--" + self.name.replace("_", "-")

    def parse(self, raw: object) -> Value:
        """``raw`` (text from a form, or a typed value) checked; empty or absent: the default."""
        if raw is None or (isinstance(raw, str) and not raw.strip()):
            if self.required:
                raise CommandRejectedError(f"{self.name} is required: {self.label}")
            return self.default
        if self.kind is InputKind.CHOICE:
            text = str(raw).strip()
            if text not in self.choices:
                raise CommandRejectedError(
                    f"{self.name} must be one of {', '.join(self.choices)}, got {text!r}"
                )
            return text
        number = self._number(raw)
        whole = self.kind is InputKind.INTEGER
        low = -math.inf if self.minimum is None else self.minimum
        high = math.inf if self.maximum is None else self.maximum
        if (whole and number != int(number)) or not low <= number <= high:
            unit = f" {self.unit}" if self.unit else ""
            what = "a whole number" if whole else "a number"
            raise CommandRejectedError(
                f"{self.name} must be {what} from {low:g} to {high:g}{unit}, got {raw!r}"
            )
        return int(number) if whole else number

    def _number(self, raw: object) -> float:
        if isinstance(raw, bool):
            raise CommandRejectedError(f"{self.name}: {raw!r} is not a number")
        try:
            number = float(raw) if isinstance(raw, int | float) else float(str(raw).strip())
        except ValueError:
            raise CommandRejectedError(f"{self.name}: {raw!r} is not a number") from None
        if not math.isfinite(number):
            raise CommandRejectedError(f"{self.name}: {raw!r} is not a number")
        return number

    def as_dict(self) -> dict[str, object]:
        """JSON-ready: the page draws its form field from it."""
        return {
            "name": self.name,
            "option": self.option,
            "label": self.label,
            "help": self.help,
            "kind": self.kind.value,
            "default": self.default,
            "absent": self.absent,
            "required": self.required,
            "unit": self.unit,
            "min": self.minimum,
            "max": self.maximum,
            "choices": list(self.choices),
            "source": self.source,
        }


@dataclass(frozen=True, slots=True)
class Inputs:
    """A procedure's inputs, checked and typed, every one present (its default if not given)."""

    values: Mapping[str, Value]

    def number(self, name: str) -> float:
        """A number input."""
        value = self.optional_number(name)
        if value is None:
            raise TypeError(_not_parsed(name, None))
        return value

    def optional_number(self, name: str) -> float | None:
        """A number input that may be left out."""
        value = self.values[name]
        if value is None or (isinstance(value, int | float) and not isinstance(value, bool)):
            return None if value is None else float(value)
        raise TypeError(_not_parsed(name, value))

    def integer(self, name: str) -> int:
        """A whole-number input."""
        value = self.values[name]
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise TypeError(_not_parsed(name, value))

    def text(self, name: str) -> str:
        """A choice."""
        value = self.optional_text(name)
        if value is None:
            raise TypeError(_not_parsed(name, None))
        return value

    def optional_text(self, name: str) -> str | None:
        """A choice that may be left out."""
        value = self.values[name]
        if value is None or isinstance(value, str):
            return value
        raise TypeError(_not_parsed(name, value))


def _not_parsed(name: str, value: object) -> str:
    """A flow asked for an input of another kind than :meth:`Procedure.parse` made."""
    return f"input {name!r} holds {value!r}: not what the procedure's parameter parses to"
