"""The mkdocs hooks of ``mkdocs.yml``: the generated pages added to the site as it is built.

:mod:`docsite` says which pages and why they are generated; this module only puts them in
the site. mkdocs loads it by its path, so the repository is put on ``sys.path`` first.
The demo's exposition is taken once per process (``scripts/docs serve`` rebuilds at every
change of a page; the metrics do not change with the text).
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import TYPE_CHECKING

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from mkdocs.structure.files import File, Files  # noqa: E402 - after the path

from docsite import cli_reference, config_reference, copies, metrics_reference, sensors  # noqa: E402

if TYPE_CHECKING:
    from mkdocs.config.defaults import MkDocsConfig


@functools.cache
def _exposition() -> str:
    return metrics_reference.demo_exposition()


def pages(docs_dir: Path) -> dict[str, str]:
    """Every generated page's text, by its path in the site."""
    guide = (docs_dir / config_reference.GUIDE).read_text(encoding="utf-8")
    found = {
        config_reference.PAGE: config_reference.page(guide),
        cli_reference.PAGE: cli_reference.page(),
        metrics_reference.PAGE: metrics_reference.page(_exposition()),
    }
    for family, profiles in sensors.families().items():
        found[sensors.page_path(family)] = sensors.page(family, profiles)
    for source, page in copies.COPIES.items():
        found[page] = copies.copy(source)
    return found


def on_files(files: Files, config: MkDocsConfig, **_: object) -> Files:
    """Add the generated pages to the site's files."""
    for path, text in pages(Path(config.docs_dir)).items():
        files.append(File.generated(config, path, content=text))
    return files
