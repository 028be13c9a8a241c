"""Where the tests find the checkout's files, wherever in ``tests/`` a module sits."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent  # the checkout: gateway/, config/, deploy/
TESTS = ROOT / "tests"
