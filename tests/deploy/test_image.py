"""The container image: built from the Dockerfile and smoke-tested by ``deploy/test-image``.

The script does the work (build with podman or docker, then ``profiles``, the user,
``check-config`` of the shipped configs, a simulated line served from a read-only
container, the healthcheck going healthy and unhealthy); this module runs it with the
other tests so that CI builds and runs the image every time. Without podman (or docker)
the script exits non-zero with the ``apt-get install`` line, and the test fails with it:
a skipped image test would pass CI unseen.
"""

from __future__ import annotations

import pytest

from tests import paths
from tests.rigs import assert_deploy_checks_pass

# One podman test at a time, on one worker: they share the base images and the build cache.
pytestmark = [pytest.mark.podman, pytest.mark.xdist_group("podman")]

ROOT = paths.ROOT
SCRIPT = ROOT / "deploy" / "test-image"

# A warm run takes under a minute; a cold one builds the stand-in base image (about 40 s)
# and downloads the dependencies' wheels. The script gets the time left after its own
# clean-up allowance, so that it removes its containers before pytest gives up.
TIMEOUT_S = 900
CLEANUP_S = 60


@pytest.mark.timeout(TIMEOUT_S)
def test_image_builds_and_passes_its_smoke_tests() -> None:
    assert_deploy_checks_pass(SCRIPT, timeout_s=TIMEOUT_S, cleanup_s=CLEANUP_S)
