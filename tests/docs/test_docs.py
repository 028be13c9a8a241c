"""The manual: every page in its navigation, every config key, command, profile and metric
family in its reference pages, and the site built with ``--strict`` as ``scripts/docs`` does.

The reference pages are made as the site is built (``docsite``); these tests make them the
same way and check what they cover. The build and the metric reference run the demo
(simulated sensors on a pseudo-terminal, an embedded broker), so those two are not in the
quick tier.
"""

from __future__ import annotations

import asyncio
import os
import posixpath
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from docsite import cli_reference, config_reference, copies, metrics_reference, sensors
from docsite.hooks import pages
from gateway.profiles import builtin_profiles
from tests import paths
from tests.mqtt_broker import Broker
from tests.publish.prometheus.test_prometheus import scrape_until
from tests.publish.prometheus.test_prometheus_names import (
    demo_plant,
    everything_read,
    scrape_port,
)

ROOT = paths.ROOT
DOCS = ROOT / "docs"
MKDOCS = ROOT / "mkdocs.yml"
MKDOCS_BIN = Path(sys.executable).parent / "mkdocs"


def nav_pages(entries: object) -> list[str]:
    """Every page the navigation of ``mkdocs.yml`` names, in order."""
    if isinstance(entries, str):
        return [entries]
    if isinstance(entries, list):
        return [page for entry in entries for page in nav_pages(entry)]
    if isinstance(entries, dict):
        return [page for value in entries.values() for page in nav_pages(value)]
    return []


def site_config() -> dict[str, object]:
    loaded = yaml.safe_load(MKDOCS.read_text(encoding="utf-8"))
    assert isinstance(loaded, dict)
    return loaded


def generated_paths() -> set[str]:
    return {
        config_reference.PAGE,
        cli_reference.PAGE,
        metrics_reference.PAGE,
        *(sensors.page_path(family) for family in sensors.families()),
        *copies.COPIES.values(),
    }


def test_every_page_is_in_the_navigation_once() -> None:
    nav = nav_pages(site_config()["nav"])
    written = {path.relative_to(DOCS).as_posix() for path in DOCS.rglob("*.md")}
    assert sorted(p for p in nav if nav.count(p) > 1) == []
    assert set(nav) == written | generated_paths()
    assert not written & generated_paths(), "a generated page is also a file"


def test_the_readme_starts_with_the_two_commands_and_links_to_the_manual() -> None:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert text.startswith("```sh\nscripts/test    #")
    assert "\nscripts/demo    #" in text.split("```")[1]
    assert "scripts/docs serve" in text
    assert len(text.splitlines()) < 80  # about a screen and a half
    for link in ("docs/getting-started/index.md", "docs/configuration/index.md"):
        assert (ROOT / link).is_file()
        assert f"]({link})" in text


def test_the_configuration_reference_names_and_describes_every_key() -> None:
    guide = (DOCS / config_reference.GUIDE).read_text(encoding="utf-8")
    text = config_reference.page(guide)
    meanings = config_reference.guide_meanings(guide)
    keys = list(config_reference.config_keys())
    assert len(keys) > 150
    paths_ = [key.path for key in keys]
    assert sorted(p for p in paths_ if paths_.count(p) > 1) == []
    for key in keys:
        assert f"| `{key.path}` |" in text
    for top in ("buses", "devices", "mqtt", "prometheus", "logging", "state_dir"):
        assert top in paths_
    for expected in ("buses[].port", "devices[].points.NAME.interval", "mqtt.servers[].host"):
        assert expected in paths_
    undescribed = [key.path for key in keys if not config_reference.describe(key, meanings)]
    assert undescribed == [], "keys neither the models nor the guide explain"


def test_the_configuration_reference_gives_types_and_defaults() -> None:
    found = {key.path: key for key in config_reference.config_keys()}
    assert found["buses[].parity"].type == "'N' | 'E' | 'O'"
    assert found["buses[].parity"].default == "'N'"
    assert found["buses[].name"].default == "required"
    assert found["devices[].poll_interval"].default == "1.0"
    assert found["mqtt.base_topic"].default == "'gateway'"
    assert found["prometheus.port"].default == "9108"
    assert found["state_dir"].type == "Path or null"


def test_the_command_reference_has_every_commands_help() -> None:
    text = cli_reference.page()
    words = list(cli_reference.commands())
    names = {" ".join(w) for w in words}
    contract = {"run", "demo", "scan", "read", "write", "profiles", "check-config", "simulate"}
    assert contract | {"calibrate", "profiles show", "records verify", "users add"} <= names
    for command in words:
        assert f"\n## gateway {' '.join(command)}\n" in text
        assert f"Usage: gateway {' '.join(command)}" in " ".join(text.split())


def test_each_sensor_family_has_its_register_map() -> None:
    nav = nav_pages(site_config()["nav"])
    families = sensors.families()
    assert set(families) >= set(sensors.FAMILIES)
    for family, profiles in families.items():
        assert sensors.page_path(family) in nav
        text = sensors.page(family, profiles)
        for profile in profiles:
            assert f"`{profile.id}`" in text
            for point in builtin_profiles()[profile.id].points:
                assert f"| `0x{point.address:04X}` ({point.address}) | `{point.name}` |" in text
    assert sum(len(p) for p in families.values()) == len(builtin_profiles())


def test_the_copies_link_only_to_pages_of_the_site() -> None:
    pages_ = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*")} | generated_paths()
    for source, page in copies.COPIES.items():
        text = copies.copy(source)
        assert f"a copy of `{source}`" in text
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if target.startswith(("http://", "https://", "#")):
                continue
            path = posixpath.normpath(posixpath.join(posixpath.dirname(page), target.split("#")[0]))
            assert path in pages_, (source, target)


@pytest.mark.line
@pytest.mark.broker
async def test_the_metric_reference_names_every_family_of_a_running_gateway(
    tmp_path: Path, broker: Broker
) -> None:
    # The reference as the site makes it (the demo's /metrics), against a gateway with every
    # poll group, a feed and the shared bus: the families it exports are all in it.
    exposition = await asyncio.to_thread(metrics_reference.demo_exposition)
    reference = metrics_reference.families(exposition)
    text = metrics_reference.page(exposition)
    async with demo_plant(tmp_path, broker) as plant:
        await scrape_until(plant.legacy, everything_read, timeout_s=60)
        every = await asyncio.to_thread(scrape_port, plant.configured)
    assert everything_read(every)
    missing = [
        name
        for name in every.families
        if name not in reference and f"{name}_total" not in reference
    ]
    assert missing == []
    for family in reference.values():
        assert f"| `{family.name}` | {family.type} |" in text
        assert family.help, family.name
    assert "gateway_care_state" in reference
    # Beyond the values (one family per kind of point, named by rule), every family is
    # explained by hand in docs/metrics.md.
    explained = (DOCS / "metrics.md").read_text(encoding="utf-8")
    values = metrics_reference.value_families()
    unexplained = [
        name for name in every.families if name not in values and f"`{name}" not in explained
    ]
    assert unexplained == []
    assert reference["gateway_oxygen"].groups == "process"


@pytest.mark.line
@pytest.mark.broker
def test_the_site_builds_strict(tmp_path: Path) -> None:
    # As scripts/docs builds it: a broken link or anchor, or a page outside the navigation,
    # is a warning, and --strict makes it fail.
    site = tmp_path / "site"
    result = subprocess.run(
        [str(MKDOCS_BIN), "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=os.environ | {"NO_MKDOCS_2_WARNING": "1"},
        timeout=300,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-4000:]
    assert "WARNING" not in result.stderr, result.stderr[-4000:]
    for page in (
        "index.html",
        "reference/configuration.html",
        "sensors/jumo-tecline.html",
    ):
        assert (site / page).is_file(), page
    configuration = (site / "reference/configuration.html").read_text(encoding="utf-8")
    assert "buses[].port" in configuration
    assert (site / "search/search_index.json").is_file()


def test_the_generated_pages_are_what_the_hooks_add(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("docsite.hooks._exposition", lambda: "# TYPE gateway_up gauge\n")
    assert set(pages(DOCS)) == generated_paths()
