"""A dead session ends within the configured time: the peer's packets dropped for real.

A converter that loses power or its cable sends no FIN and no RST; only TCP's own timers
can tell. Each case runs ``tests/dead_session.py`` in a user and network namespace of its
own (``unshare -rn``: no root needed, nothing of this machine's network touched), where
iptables drops every packet to the simulator after one good answer.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest

from tests import paths

UNSHARE = shutil.which("unshare")
ROOT = paths.ROOT


def _namespaces_work() -> bool:
    if UNSHARE is None or shutil.which("iptables") is None:
        return False
    probe = [UNSHARE, "-rn", "iptables", "-L", "INPUT"]
    return subprocess.run(probe, capture_output=True, check=False).returncode == 0


pytestmark = [
    # The simulator and the line run in the namespace's own process (tests/dead_session.py),
    # where the tier guard does not see them.
    pytest.mark.line,
    pytest.mark.timing,
    pytest.mark.skipif(
        not _namespaces_work(), reason="needs unshare -rn and iptables (user namespaces allowed)"
    ),
]


@pytest.mark.parametrize(("scheme", "mode"), [("tcp", "busy"), ("tcp", "idle"), ("socket", "busy")])
def test_a_vanished_converter_ends_the_session_after_the_user_timeout(
    scheme: str, mode: str
) -> None:
    assert UNSHARE is not None
    command = [UNSHARE, "-rn", sys.executable, "-m", "tests.dead_session", scheme, mode, "2"]
    done = subprocess.run(
        command, capture_output=True, text=True, check=False, cwd=ROOT, timeout=60
    )
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    # 2 s of user timeout; the kernel acts on its next retransmission or keepalive probe.
    assert 2.0 <= result["ended_after_s"] < 2.0 + 1.5, result
    if mode == "busy":
        assert result["failures"] >= 3, result  # every request meanwhile timed out
