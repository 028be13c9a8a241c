"""What is wrong with a config, each problem located.

A :class:`Problem` is a key path, a file line and a message; :class:`ConfigProblems` raises
every problem of one load at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path  # noqa: TC003 - pydantic resolves annotations at run time
from typing import (
    TYPE_CHECKING,
    TypeAlias,
)

from gateway.errors import ConfigError

if TYPE_CHECKING:
    from collections.abc import Iterable, Sequence


KeyPart: TypeAlias = str | int
KeyPath: TypeAlias = tuple[KeyPart, ...]


def close_matches(word: str, known: Sequence[str], n: int, cutoff: float = 0.6) -> list[str]:
    """``difflib``'s close matches, imported with the first mistake: a valid config needs none."""
    import difflib  # noqa: PLC0415

    return difflib.get_close_matches(word, known, n=n, cutoff=cutoff)


# --- problems ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Problem:
    """One thing wrong with a config: where (key path, file line) and what.

    Example::

        Problem("devices[1].address", 14, "address 1 is already used on bus line1 by devices[0]")

    ``line`` is ``None`` where no line applies: a value from the environment, or a key
    missing from the file altogether.
    """

    key: str
    line: int | None
    message: str

    def __str__(self) -> str:
        """``devices[1].address (line 14): message``; parts that are not known are left out."""
        where = self.key
        if self.line is not None:
            where = f"{where} (line {self.line})" if where else f"line {self.line}"
        return f"{where}: {self.message}" if where else self.message


class ConfigProblems(ConfigError):  # noqa: N818 - a collection of problems; public name
    """Every problem found in a config, reported at once, one per line of ``str()``."""

    def __init__(self, problems: Sequence[Problem], *, path: Path | None = None) -> None:
        """Keep the problems; ``key`` and ``line`` are the first problem's."""
        self.problems = list(problems)
        self.path = path
        super().__init__("\n".join(str(problem) for problem in self.problems))
        if self.problems:
            self.key = self.problems[0].key
            self.line = self.problems[0].line


def format_key(path: Iterable[KeyPart]) -> str:
    """``devices[1].points.temperature`` from ``("devices", 1, "points", "temperature")``."""
    text = ""
    for part in path:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else part
    return text
