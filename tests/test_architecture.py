"""The house rules: imports only go down the floors of docs/ARCHITECTURE.md, and never in a circle.

Every module of ``gateway/`` is parsed (not imported), and every import it holds is counted:
at the top, inside functions, and under ``if TYPE_CHECKING:`` alike, since an annotation
that points up is a dependency that points up.
"""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from collections.abc import Iterator

PACKAGE = Path(__file__).parent.parent / "gateway"

# The floors, low to high: a module may import its own floor and the floors it lists.
# The simulator stands beside the gateway, on the wire and the profiles only; the command
# line is the one floor that starts it.
_ORDER = (
    "root",
    "wire",
    "profiles",
    "config",
    "line",
    "transports",
    "engine",
    "care",
    "shared",
    "publish",
    "records",
    "control",
    "web",
    "app",
    "cli",
)
MAY_IMPORT: dict[str, frozenset[str]] = {
    floor: frozenset(_ORDER[:rank]) for rank, floor in enumerate(_ORDER)
}
MAY_IMPORT["simulator"] = frozenset({"root", "wire", "profiles"})
MAY_IMPORT["cli"] |= {"simulator"}
MAY_IMPORT["entry"] = frozenset({*_ORDER, "simulator"})

# Module (or package) -> floor; the longest matching name wins.
FLOOR_OF = {
    "gateway": "root",
    "gateway.errors": "root",
    "gateway.wire": "wire",
    "gateway.profiles": "profiles",
    "gateway.config": "config",
    "gateway.line": "line",
    "gateway.line.transports": "transports",
    "gateway.line.engine": "engine",
    "gateway.line.scan": "engine",
    "gateway.care": "care",
    "gateway.shared": "shared",
    "gateway.publish": "publish",
    "gateway.records": "records",
    "gateway.control": "control",
    "gateway.web": "web",
    "gateway.app": "app",
    "gateway.cli": "cli",
    "gateway.simulator": "simulator",
    "gateway.__main__": "entry",
}

# Only the port touches the serial line (STYLE.md: pure core, I/O at the edges), and two
# modules beside it that need pyserial's Serial before the port has a transport:
# port_access (the device opened exclusively, in its RS485 mode) and usb_adapter (the
# driver asked for low-latency mode). The port's names and why it is not open need none.
PORT_LIBRARIES = ("serial", "serial_asyncio_fast", "pymodbus.client")
PORT_OWNERS = frozenset(
    {
        "gateway.line.transports.serial_line",
        "gateway.line.transports.port_access",
        "gateway.line.transports.usb_adapter",
    }
)


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


MODULES = _modules()


@functools.cache
def _parsed(source: str) -> ast.Module:
    """The syntax tree of a module's text, parsed once for all the tests that read it."""
    return ast.parse(source)


@pytest.fixture(autouse=True, scope="module")
def _trees_forgotten() -> Iterator[None]:
    """The trees go with this module's tests: some 360,000 objects kept alive after it
    made every later test's garbage collection (tests/conftest.py) 0.2 s longer."""
    yield
    _parsed.cache_clear()


def _imports(module: str, source: str | None = None) -> list[tuple[int, str]]:
    """Every ``(line, imported name)`` in the module, wherever the import statement stands.

    ``from X import Y`` imports the module ``X.Y`` if there is one, else (a name of) ``X``.
    """
    path = MODULES[module]
    text = path.read_text(encoding="utf-8") if source is None else source
    tree = _parsed(text)
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolved against the module's package
                package = module if path.name == "__init__.py" else module.rpartition(".")[0]
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                found.append((node.lineno, submodule if submodule in MODULES else base))
    return found


def _gateway_imports(module: str, source: str | None = None) -> list[tuple[int, str]]:
    return [
        (line, name)
        for line, name in _imports(module, source)
        if name == "gateway" or name.startswith("gateway.")
    ]


def _floor(module: str) -> str | None:
    parts = module.split(".")
    for end in range(len(parts), 0, -1):
        floor = FLOOR_OF.get(".".join(parts[:end]))
        if floor is not None:
            return floor
    return None


def _graph() -> dict[str, set[str]]:
    return {module: {name for _, name in _gateway_imports(module)} for module in MODULES}


def test_every_module_stands_on_a_floor() -> None:
    assert [module for module in MODULES if _floor(module) is None] == []


def test_every_import_names_a_module_of_the_package() -> None:
    unknown = [
        f"{module}:{line} imports {name}"
        for module in MODULES
        for line, name in _gateway_imports(module)
        if name not in MODULES
    ]
    assert unknown == []


def test_imports_only_go_down() -> None:
    wrong = []
    for module in MODULES:
        floor = _floor(module)
        assert floor is not None
        for line, name in _gateway_imports(module):
            target = _floor(name)
            if target != floor and target not in MAY_IMPORT[floor]:
                wrong.append(f"{module}:{line} ({floor}) imports {name} ({target})")
    assert wrong == []


def _reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    seen: set[str] = set()
    pending = list(graph.get(start, ()))
    while pending:
        name = pending.pop()
        if name not in seen:
            seen.add(name)
            pending.extend(graph.get(name, ()))
    return seen


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Groups of modules that reach each other through their imports (a module alone if it
    imports itself)."""
    reach = {module: _reachable(graph, module) for module in graph}
    groups: list[list[str]] = []
    for module in sorted(graph):
        if module in reach[module] and not any(module in group for group in groups):
            groups.append(sorted(n for n in reach[module] if module in reach.get(n, ())))
    return groups


def test_no_import_cycles() -> None:
    assert _cycles(_graph()) == []


def test_the_cycle_finder_finds_cycles() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"d"}, "e": {"a"}}
    assert sorted(_cycles(graph)) == [["a", "b", "c"], ["d"]]


@pytest.mark.parametrize(
    ("module", "line_imports", "expected"),
    [
        ("gateway.control.writes", "from gateway.wire import codec", "gateway.wire.codec"),
        ("gateway.control.writes", "from gateway.config import FlashPolicy", "gateway.config"),
        ("gateway.control.writes", "from . import link", "gateway.control.link"),
        ("gateway.control.writes", "from .flash import Action", "gateway.control.flash"),
        ("gateway.cli", "from .root import main", "gateway.cli.root"),
        ("gateway.cli.root", "from ..line import scan", "gateway.line.scan"),
    ],
)
def test_imports_are_resolved_to_modules(module: str, line_imports: str, expected: str) -> None:
    source = f"if TYPE_CHECKING:\n    {line_imports}\n"
    assert _gateway_imports(module, source) == [(2, expected)]


def test_only_the_port_touches_the_serial_line() -> None:
    touching = [
        f"{module}:{line} imports {name}"
        for module in MODULES
        if module not in PORT_OWNERS
        for line, name in _imports(module)
        if any(name == lib or name.startswith(f"{lib}.") for lib in PORT_LIBRARIES)
    ]
    assert touching == []


# --- docs/ARCHITECTURE.md's table of modules, kept true --------------------------------------

ARCHITECTURE = PACKAGE.parent / "docs" / "ARCHITECTURE.md"


def _rows() -> list[list[str]]:
    """The modules each row of the table names in its first column (``line/transports/rtu``, ...)."""
    rows = []
    for line in ARCHITECTURE.read_text(encoding="utf-8").splitlines():
        if line.startswith("| `"):
            first = line.split("|")[1]
            rows.append(first.replace("`", "").replace(",", " ").split())
    return rows


def _documented_modules() -> set[str]:
    """Every module the table must name: all but packages' ``__init__`` (they re-export)."""
    return {
        str(path.relative_to(PACKAGE).with_suffix(""))
        for path in PACKAGE.rglob("*.py")
        if path.name != "__init__.py"
    }


def test_every_module_has_one_row_and_every_row_a_module() -> None:
    named = [module for row in _rows() for module in row]
    modules = _documented_modules()
    assert sorted(modules - set(named)) == [], "modules without a row in docs/ARCHITECTURE.md"
    assert sorted(set(named) - modules) == [], "rows of modules that do not exist"
    assert sorted({m for m in named if named.count(m) > 1}) == [], "modules with two rows"


def test_the_table_reader_reads_rows_of_several_modules() -> None:
    rows = _rows()
    assert ["cli/write", "cli/calibrate", "cli/operations"] in rows
    assert ["line/transports/rtu"] in rows


# --- its known debt, measured ----------------------------------------------------------------

MODULE_LINES_MAX = 600  # a module longer is named under "Known debt"
CLASS_LINES_MAX = 300  # and so is a class longer


def _listed_debt() -> set[str]:
    """What the "Known debt" section names before each item's colon: modules and classes."""
    text = ARCHITECTURE.read_text(encoding="utf-8")
    section = text.split("\n## Known debt\n", 1)[1].split("\n## ", 1)[0]
    heads = [line.split(":", 1)[0] for line in section.splitlines() if line.startswith("- `")]
    return {name for head in heads for name in re.findall(r"`([^`]+)`", head)}


def _measured_debt() -> set[str]:
    """The modules and classes over the bounds, as the section names them."""
    found = set()
    for path in PACKAGE.rglob("*.py"):
        source = path.read_text(encoding="utf-8")
        name = str(path.relative_to(PACKAGE).with_suffix(""))
        if source.count("\n") > MODULE_LINES_MAX:
            found.add(name)
        for node in ast.walk(_parsed(source)):
            if not isinstance(node, ast.ClassDef) or node.end_lineno is None:
                continue
            if node.end_lineno - node.lineno + 1 > CLASS_LINES_MAX:
                found.add(f"{name}.{node.name}")
    return found


def test_the_known_debt_is_what_is_measured() -> None:
    listed, measured = _listed_debt(), _measured_debt()
    assert sorted(measured - listed) == [], "over the bounds, not named under Known debt"
    assert sorted(listed - measured) == [], "named under Known debt, within the bounds now"


# --- a device's running state: each part written by its owner alone ---------------------------

ENGINE = PACKAGE / "line" / "engine"
# The parts of DeviceState (line/engine/devices) and the one module that writes each; the
# part's own methods (in devices) are how the others ask.
PART_OWNERS = {
    "deadlines": "schedule",
    "presence": "health",
    "holds": "transactions",
}
MUTATORS = frozenset(
    {"add", "discard", "remove", "clear", "update", "pop", "setdefault", "difference_update"}
)


def _part_named(node: ast.expr, parts: dict[str, str]) -> str | None:
    """The part an expression is (``state.holds``, or a name bound to it), else None."""
    if isinstance(node, ast.Attribute) and node.attr in PART_OWNERS:
        return node.attr
    if isinstance(node, ast.Name):
        return parts.get(node.id)
    return None


def _field_of(node: ast.expr, parts: dict[str, str], fields: dict[str, str]) -> str | None:
    """The part whose field an expression is (``holds.unreadable``, ``x[k]`` of one), else None."""
    if isinstance(node, ast.Subscript):
        return _field_of(node.value, parts, fields)
    if isinstance(node, ast.Attribute):
        return _part_named(node.value, parts)
    if isinstance(node, ast.Name):
        return fields.get(node.id)
    return None


def _bindings(tree: ast.Module) -> tuple[dict[str, str], dict[str, str]]:
    """Names bound to a part (``presence = state.presence``) and to a part's field."""
    assigns = [
        (node.targets[0].id, node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Assign)
        and len(node.targets) == 1
        and isinstance(node.targets[0], ast.Name)
    ]
    parts = {name: part for name, value in assigns if (part := _part_named(value, {}))}
    fields = {
        name: part
        for name, value in assigns
        if isinstance(value, ast.Attribute) and (part := _part_named(value.value, parts))
    }
    return parts, fields


def _part_writes(source: str) -> list[tuple[int, str]]:
    """Every write to a field of a part (assigned, or mutated in place), with its line.

    A method of the part itself (``state.holds.hold_until(...)``) is asking, not writing;
    names bound to a part or to one of its fields are followed.
    """
    tree = _parsed(source)
    parts, fields = _bindings(tree)
    writes: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        targets: list[ast.expr] = []
        if isinstance(node, ast.Assign):
            targets = [t for t in node.targets if not isinstance(t, ast.Name)]  # not bindings
        elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
            targets = [node.target]
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            targets = [node.func.value] if node.func.attr in MUTATORS else []
        writes.extend(
            (node.lineno, part)
            for target in targets
            if isinstance(node, ast.stmt | ast.expr)
            and (part := _field_of(target, parts, fields)) is not None
        )
    return sorted(writes)


def test_each_part_of_a_devices_state_has_one_writer() -> None:
    wrong = [
        f"line/engine/{path.stem}:{line} writes the {part} ({PART_OWNERS[part]}'s)"
        for path in sorted(ENGINE.glob("*.py"))
        for line, part in _part_writes(path.read_text(encoding="utf-8"))
        if path.stem not in {PART_OWNERS[part], "devices"}
    ]
    outside = [
        f"{path.relative_to(PACKAGE)}:{line} writes the {part}"
        for path in sorted(PACKAGE.rglob("*.py"))
        if ENGINE not in path.parents
        for line, part in _part_writes(path.read_text(encoding="utf-8"))
    ]
    assert wrong == []
    assert outside == []


def test_the_writer_finder_sees_each_kind_of_write() -> None:
    source = (
        "state.presence.online = False\n"
        "state.holds.not_before += 1\n"
        "state.deadlines.next_due[name] = 0.0\n"
        "state.deadlines.identity_pending.discard(name)\n"
        "pending = state.deadlines.identity_pending\n"
        "pending.add(name)\n"
        "presence = state.presence\n"
        "presence.failures = 0\n"
        "state.holds.hold_until(1.0)\n"  # asking: not a write
        "deadlines = state.deadlines\n"
        "deadlines.identity_read(name)\n"  # asking
        "x = state.holds.not_before\n"  # reading
    )
    assert [line for line, _ in _part_writes(source)] == [1, 2, 3, 4, 6, 8]
