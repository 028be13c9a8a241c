"""The config's YAML read by libyaml's parser and by PyYAML's own: the same document.

``parse_yaml`` reads with libyaml's parser (ten times faster) and falls back to PyYAML's
for a file it refuses. The lines of the keys, the duplicate keys and the data must not
depend on which parser read them: every config and profile shipped or tested is read by
both and compared.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from gateway.config.yaml_lines import _parse, parse_yaml

ROOT = Path(__file__).parents[1]
FILES = sorted(
    [
        *(ROOT / "config").glob("*.yaml"),
        *(ROOT / "tests" / "configs").rglob("*.yaml"),
        *(ROOT / "gateway" / "profiles" / "data").glob("*.yaml"),
    ]
)


@pytest.mark.parametrize("path", FILES, ids=lambda path: str(path.relative_to(ROOT)))
def test_both_parsers_read_the_same_document(path: Path) -> None:
    text = path.read_text(encoding="utf-8")
    try:
        own = _parse(yaml.SafeLoader(text))
    except yaml.YAMLError:  # a broken file: refused by both, and worded by PyYAML
        with pytest.raises(yaml.YAMLError):
            _parse(yaml.CSafeLoader(text))
        assert parse_yaml(text).problems[0].message.startswith("not valid YAML: ")
        return
    fast = _parse(yaml.CSafeLoader(text))
    assert fast.data == own.data
    assert fast.lines == own.lines
    assert fast.problems == own.problems


def test_the_files_were_found() -> None:
    assert len(FILES) > 20  # the examples, the broken configs, the profiles


def test_a_duplicate_key_is_located_as_before() -> None:
    document = parse_yaml("mqtt:\n  host: a\n  host: b\n")
    assert [(p.key, p.line) for p in document.problems] == [("mqtt.host", 3)]
    assert "repeats line 2" in document.problems[0].message


def test_a_file_libyaml_refuses_is_worded_by_pyyaml() -> None:
    """The problem's words are PyYAML's, as they were before libyaml read the files."""
    text = "buses:\n  - name: a\n    port: [unclosed\n"
    with pytest.raises(yaml.YAMLError):
        yaml.load(text, Loader=yaml.CSafeLoader)
    try:
        yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        expected = exc.problem
    (problem,) = parse_yaml(text).problems
    assert problem.message.startswith(f"not valid YAML: {expected}")
