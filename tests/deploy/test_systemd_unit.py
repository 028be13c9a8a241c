"""The systemd unit under a real systemd, by ``deploy/test-systemd``.

``tests/deploy/test_deploy.py`` verifies the unit file (``systemd-analyze verify`` and
``security``); whether its sandbox still lets the gateway open a serial port, keep its
state, restart and stop can only be seen by running it. The script does that: a container
with systemd as PID 1, the gateway installed as deploy/README.md says, a simulated line on
a pseudo-terminal bound at ``/dev/ttyUSB0`` and one over TCP, a broker with a password
(its header lists every check). This module runs it with the other tests, so that a
hardening change that breaks the service fails CI, not a plant's first boot.

Without podman the script exits non-zero with the ``apt-get install`` line, and this test
fails with it: a skipped check would pass CI unseen (the rule of ``tests/deploy/test_deploy.py``).
"""

from __future__ import annotations

import pytest

from tests import paths
from tests.rigs import assert_deploy_checks_pass

# One podman test at a time, on one worker: they share the base images and the build cache.
pytestmark = [pytest.mark.podman, pytest.mark.xdist_group("podman")]

ROOT = paths.ROOT
SCRIPT = ROOT / "deploy" / "test-systemd"

# A warm run takes under a minute. A cold one first builds the base image with systemd and
# Mosquitto from Debian packages (deploy/standin-base, over a minute) and downloads the
# gateway's dependencies; a failing one waits out its checks' deadlines (about four
# minutes). The script gets the time left after its clean-up allowance, so that it removes
# its container before pytest gives up.
TIMEOUT_S = 900
CLEANUP_S = 60


@pytest.mark.timeout(TIMEOUT_S)
def test_unit_runs_under_systemd() -> None:
    output = assert_deploy_checks_pass(SCRIPT, timeout_s=TIMEOUT_S, cleanup_s=CLEANUP_S)
    # The checks that make it a test of the unit, not of a container that merely started.
    for check in (
        "ok: systemd is PID 1",
        "ok: control: with DevicePolicy=strict the open is refused",
        "ok: serial port: the gateway holds /dev/ttyUSB0 open",
        "ok: systemctl reload of a config with a problem fails",
        "ok: systemctl reload of an edited config: applied",
        "ok: SIGKILL: active again",
        "ok: systemctl stop: exit status 0",
    ):
        assert check in output, check
