"""The container image: built from the Dockerfile and smoke-tested by ``deploy/test-image``.

The script does the work (build with podman or docker, then ``profiles``, the user,
``check-config`` of the shipped configs, a simulated line served from a read-only
container, the healthcheck going healthy and unhealthy); this module runs it with the
other tests so that CI builds and runs the image every time. Without podman (or docker)
the script exits non-zero with the ``apt-get install`` line, and the test fails with it:
a skipped image test would pass CI unseen.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "deploy" / "test-image"

# A warm run takes under a minute; a cold one builds the stand-in base image (about 40 s)
# and downloads the dependencies' wheels. The script gets the time left after its own
# clean-up allowance, so that it removes its containers before pytest gives up.
TIMEOUT_S = 900
CLEANUP_S = 60


def run_script() -> tuple[int, str]:
    """Run the script in its own process group; its exit code and its output (merged)."""
    with subprocess.Popen(
        [str(SCRIPT)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # SIGTERM reaches the script and its podman commands alone
    ) as process:
        try:
            output, _ = process.communicate(timeout=TIMEOUT_S - CLEANUP_S)
        except subprocess.TimeoutExpired:
            # SIGTERM: the script's trap removes its containers, network and volume.
            os.killpg(process.pid, signal.SIGTERM)
            try:
                output, _ = process.communicate(timeout=CLEANUP_S / 2)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                output, _ = process.communicate()
            output += f"\n(test_image: stopped after {TIMEOUT_S - CLEANUP_S} s)\n"
    return process.returncode, output


@pytest.mark.timeout(TIMEOUT_S)
def test_image_builds_and_passes_its_smoke_tests() -> None:
    code, output = run_script()
    sys.stdout.write(output)  # pytest shows it when the test fails: every ok/FAIL line
    failed = [line for line in output.splitlines() if line.startswith("FAIL: ")]
    assert code == 0, "\n".join(failed) or output[-3000:]
    assert "deploy/test-image: every check passed" in output
    assert not failed
