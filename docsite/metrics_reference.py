"""The metric reference: every family of a running demo's ``/metrics``, with HELP and TYPE.

``gateway demo`` runs for the few seconds it takes to read every sensor once (its simulated
plant: every family, a feed, the shared bus, the web page, an embedded broker), and its
exposition is read as Prometheus reads it. The demo exports the poll groups a plant gets by
default (process values and status); the value families of the other groups, which a config
asks for with ``prometheus.groups``, are added from the profiles, named as the gateway names
them. ``docs/metrics.md`` explains them, family by family.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from gateway.profiles import PollGroup, builtin_profiles
from gateway.publish.prometheus.naming import help_text, point_naming

PAGE: Final = "reference/metrics.md"
DEFAULT_GROUPS: Final = frozenset({PollGroup.PROCESS, PollGroup.STATUS})
STARTUP_S: Final = 90.0  # the demo's first full read, on a loaded machine
STEADY_SCRAPES: Final = 3  # the same families this many scrapes in a row: all there


@dataclass(frozen=True)
class Family:
    """A metric family: its name, type and help, and where it comes from."""

    name: str
    type: str
    help: str
    groups: str = ""  # the poll groups of a value family, else empty


def parse(exposition: str) -> dict[str, Family]:
    """The families of a text exposition, by name (``# HELP`` and ``# TYPE``)."""
    helps: dict[str, str] = {}
    types: dict[str, str] = {}
    for line in exposition.splitlines():
        if line.startswith("# HELP "):
            name, _, text = line.removeprefix("# HELP ").partition(" ")
            helps[name] = text.replace("\\n", " ").replace("\\\\", "\\")
        elif line.startswith("# TYPE "):
            name, _, kind = line.removeprefix("# TYPE ").partition(" ")
            types[name] = kind.strip()
    return {name: Family(name, types.get(name, "untyped"), helps.get(name, "")) for name in types}


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def _scrape(port: int) -> str | None:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as reply:
            text: str = reply.read().decode()
            return text
    except OSError:
        return None


def demo_exposition() -> str:
    """``gateway demo``'s ``/metrics`` once every sensor was read, the demo stopped after."""
    metrics = _free_port()
    command = [
        sys.executable, "-m", "gateway", "demo", "--no-live",
        "--mqtt-port", str(_free_port()), "--metrics-port", str(metrics),
        "--web-port", str(_free_port()), "--modbus-port", str(_free_port()),
    ]  # fmt: skip
    with tempfile.TemporaryDirectory() as home:
        log = Path(home) / "demo.log"
        with (
            log.open("wb") as errors,
            subprocess.Popen(  # noqa: S603 - this interpreter, fixed arguments
                command,
                stdout=subprocess.DEVNULL,
                stderr=errors,
                env=os.environ | {"HOME": home},
                cwd=home,
            ) as demo,
        ):
            try:
                return _steady(demo, metrics, log)
            finally:
                demo.send_signal(signal.SIGINT)
                try:
                    demo.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    demo.kill()
                    demo.wait()


def _steady(demo: subprocess.Popen[bytes], port: int, log: Path) -> str:
    """The exposition once care is assessed and the families stayed the same a while."""
    deadline = time.monotonic() + STARTUP_S
    seen: list[frozenset[str]] = []
    while time.monotonic() < deadline:
        if demo.poll() is not None:
            error = log.read_text(encoding="utf-8", errors="replace")[-2000:]
            raise RuntimeError(f"gateway demo stopped with {demo.returncode}: {error}")
        text = _scrape(port)
        if text is not None and "gateway_care_state{" in text:
            seen.append(frozenset(parse(text)))
            if len(seen) >= STEADY_SCRAPES and len(set(seen[-STEADY_SCRAPES:])) == 1:
                return text
        time.sleep(1.0)
    raise RuntimeError(f"gateway demo's /metrics did not settle in {STARTUP_S:.0f} s")


def value_families() -> dict[str, Family]:
    """The value family of every numeric point of every built-in profile, with its groups."""
    found: dict[str, tuple[str, set[str]]] = {}
    for profile in builtin_profiles().values():
        for point in profile.points:
            naming = point_naming(point)
            if naming is None:
                continue
            entry = found.setdefault(naming.family, (help_text(point, naming), set()))
            entry[1].add(point.group.value)
    return {
        name: Family(name, "gauge", help_, ", ".join(sorted(groups)))
        for name, (help_, groups) in found.items()
    }


def families(exposition: str) -> dict[str, Family]:
    """The exposition's families, and the value families of the other poll groups."""
    found = parse(exposition)
    values = value_families()
    for name, family in values.items():
        if name in found:
            found[name] = Family(name, found[name].type, found[name].help, family.groups)
        else:
            found[name] = family
    return dict(sorted(found.items()))


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def page(exposition: str) -> str:
    """The reference as a Markdown page, from an exposition."""
    lines = [
        "# Metric reference",
        "",
        "Every metric family a gateway exports, made when this site was built from a running",
        "`gateway demo`'s `/metrics` (the default poll groups, process values and status) and,",
        "for the families of the other poll groups (`prometheus.groups`), from the profiles.",
        "Each family is named as its `# TYPE` line names it (a counter with its `_total`).",
        "[The metrics explained](../metrics.md) says what each one means and how to use it;",
        "the labels of each family are in its samples at `/metrics`.",
        "",
        "| family | type | poll groups | help |",
        "|---|---|---|---|",
    ]
    lines.extend(
        f"| `{f.name}` | {f.type} | {f.groups or '—'} | {_cell(f.help)} |"
        for f in families(exposition).values()
    )
    return "\n".join(lines) + "\n"


def main() -> None:
    """Print the demo's exposition (to keep one, e.g. for the docs' tests)."""
    sys.stdout.write(demo_exposition())


if __name__ == "__main__":
    main()
