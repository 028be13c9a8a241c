"""The container image: built from the Dockerfile and smoke-tested by ``deploy/test-image``.

The script does the work (build with podman or docker, then ``profiles``, the user,
``check-config`` of the shipped configs, a simulated line served from a read-only
container, the healthcheck going healthy and unhealthy); this module runs it with the
other tests so that CI builds and runs the image every time. Without podman (or docker)
the script exits non-zero with the ``apt-get install`` line, and the test fails with it:
a skipped image test would pass CI unseen.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from tests.rigs import run_deploy_script

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "deploy" / "test-image"

# A warm run takes under a minute; a cold one builds the stand-in base image (about 40 s)
# and downloads the dependencies' wheels. The script gets the time left after its own
# clean-up allowance, so that it removes its containers before pytest gives up.
TIMEOUT_S = 900
CLEANUP_S = 60


@pytest.mark.timeout(TIMEOUT_S)
def test_image_builds_and_passes_its_smoke_tests() -> None:
    code, output = run_deploy_script(SCRIPT, timeout_s=TIMEOUT_S, cleanup_s=CLEANUP_S)
    sys.stdout.write(output)  # pytest shows it when the test fails: every ok/FAIL line
    failed = [line for line in output.splitlines() if line.startswith("FAIL: ")]
    assert code == 0, "\n".join(failed) or output[-3000:]
    assert "deploy/test-image: every check passed" in output
    assert not failed
