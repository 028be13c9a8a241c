"""YAML read with the line of every mapping key and sequence item, duplicate keys reported."""

from __future__ import annotations

from dataclasses import dataclass
from typing import (
    TYPE_CHECKING,
)

import yaml

from gateway.config.problems import KeyPart, KeyPath, Problem, format_key

if TYPE_CHECKING:
    from collections.abc import Iterable, Iterator


_MERGE_TAG = "tag:yaml.org,2002:merge"


@dataclass(frozen=True, slots=True)
class YamlDocument:
    """A parsed file: its data, the line of every key path, and the problems found."""

    data: object  # None for an empty file or one that is not valid YAML
    lines: dict[KeyPath, int]  # 1-based line of every mapping key and sequence item
    problems: list[Problem]


def parse_yaml(text: str) -> YamlDocument:
    """Parse ``text``; a file that is not valid YAML is one located problem, not an error."""
    loader = yaml.SafeLoader(text)
    index = _LineIndex(loader)
    try:
        node = loader.get_single_node()
        if node is None:
            return YamlDocument(None, {}, [])
        index.lines[()] = node.start_mark.line + 1
        index.walk(node)
        data = loader.construct_document(node)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        what = exc.problem or "cannot parse"
        if exc.context:
            what += f" ({exc.context})"
        line = mark.line + 1 if mark is not None else None
        return YamlDocument(None, {}, [Problem("", line, f"not valid YAML: {what}")])
    except yaml.YAMLError as exc:
        return YamlDocument(None, {}, [Problem("", None, f"not valid YAML: {exc}")])
    finally:
        loader.dispose()
    return YamlDocument(data, index.lines, index.problems)


class _LineIndex:
    """The 1-based line of every mapping key and sequence item, by key path.

    Works on the composed node tree, before construction, so that duplicate keys (which
    PyYAML would silently collapse) are still visible and reported.
    """

    def __init__(self, loader: yaml.SafeLoader) -> None:
        self._loader = loader
        self.lines: dict[KeyPath, int] = {}
        self.problems: list[Problem] = []

    def walk(
        self, node: yaml.Node, path: KeyPath = (), on_path: frozenset[int] = frozenset()
    ) -> None:
        """Index ``node`` and everything below it."""
        if id(node) in on_path:  # a recursive alias
            return
        on_path |= {id(node)}
        if isinstance(node, yaml.SequenceNode):
            for index, item in enumerate(node.value):
                self.lines[(*path, index)] = item.start_mark.line + 1
                self.walk(item, (*path, index), on_path)
        elif isinstance(node, yaml.MappingNode):
            self._mapping(node, path, on_path)

    def _mapping(self, node: yaml.MappingNode, path: KeyPath, on_path: frozenset[int]) -> None:
        seen: dict[KeyPart, int] = {}
        merges: list[yaml.Node] = []
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE_TAG:
                merges.append(value_node)
                continue
            key = self._key(key_node)
            if key is None:
                continue
            line = key_node.start_mark.line + 1
            if key in seen:
                self.problems.append(
                    Problem(
                        format_key((*path, key)),
                        line,
                        f"duplicate key; it repeats line {seen[key]}, whose value it would "
                        "silently replace",
                    )
                )
            seen[key] = line
            self.lines[(*path, key)] = line
            self.walk(value_node, (*path, key), on_path)
        # ``<<: *anchor`` merges: keys given explicitly win, as in the constructed data.
        for source in _merge_sources(merges):
            merged = _LineIndex(self._loader)
            merged.walk(source, path, on_path)
            for key_path, line in merged.lines.items():
                if key_path[len(path)] not in seen:
                    self.lines.setdefault(key_path, line)

    def _key(self, node: yaml.Node) -> KeyPart | None:
        if not isinstance(node, yaml.ScalarNode):
            return None
        key = self._loader.construct_object(node)
        return key if isinstance(key, str | int) else None


def _merge_sources(values: Iterable[yaml.Node]) -> Iterator[yaml.Node]:
    for value in values:
        if isinstance(value, yaml.SequenceNode):
            yield from value.value
        else:
            yield value
