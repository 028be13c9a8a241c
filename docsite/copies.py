"""Copies of the repository's own READMEs that stay beside the files they describe.

``deploy/README.md`` and ``bench/README.md`` are read by the tests and linked from the
benches, so they stay where they are; the site shows a copy of each. A link in them to a
file of the repository (outside the site) becomes its path in code, and their anchors are
written as the site's headings are (a run of dashes is one).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Final

ROOT: Final = Path(__file__).resolve().parent.parent
# The site's page of each copy, by the repository's file.
COPIES: Final = {
    "deploy/README.md": "installation/deploy.md",
    "bench/README.md": "development/bench.md",
}
_LINK: Final = re.compile(r"\[([^\]]+)\]\(([^)\s]+)\)")


def copy(source: str) -> str:
    """The text of the repository file ``source`` as a page of the site."""
    text = (ROOT / source).read_text(encoding="utf-8")
    base = Path(source).parent

    def link(match: re.Match[str]) -> str:
        label, target = match.groups()
        if target.startswith(("http://", "https://", "mailto:")):
            return match.group(0)
        if target.startswith("#"):
            return f"[{label}]({re.sub('-{2,}', '-', target)})"
        path, _, anchor = target.partition("#")
        repository = os.path.normpath(base / path)
        page = COPIES.get(repository) or (
            repository.removeprefix("docs/") if repository.startswith("docs/") else None
        )
        if page is not None:
            target = os.path.relpath(page, Path(COPIES[source]).parent)
            return f"[{label}]({target}{'#' + anchor if anchor else ''})"
        return f"{label} (`{repository}`)" if label.strip("`") != repository else f"`{repository}`"

    lead = f"*This page is a copy of `{source}` in the repository, made when the site was built.*"
    lines = text.splitlines()
    title = next((i for i, line in enumerate(lines) if line.startswith("# ")), None)
    if title is None:
        return f"{lead}\n\n{_LINK.sub(link, text)}"
    lines.insert(title + 1, f"\n{lead}")
    return _LINK.sub(link, "\n".join(lines)) + "\n"
