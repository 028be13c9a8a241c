"""A kill between a write's record and the sensor's answer: the record stays, and says so.

``gateway write`` runs as its own process against the simulator on a pseudo-terminal, to
an address where no sensor answers, so that it waits for the answer of a write it has
recorded and sent; it is killed with SIGKILL there. The record is on the disk (the chain
intact), unanswered; at the next start the gateway completes it with the outcome
"unknown" and the reason, never loses it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from typing import TYPE_CHECKING

import pytest

from gateway.records import Kind, RecordStore, Result, records_path
from gateway.records.interrupted import INTERRUPTED, close_interrupted, unanswered
from tests.rigs import simulate_process
from tests.waiting import wait_until

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line]

SIMULATED = "devices:\n  - {profile: jumo-digiline-odo-s10, address: 1}\n"


def pending_writes(state_dir: Path) -> list[int]:
    path = records_path(state_dir)
    if not path.exists():
        return []
    store = RecordStore(path, read_only=True)
    try:
        return [record.seq for record in unanswered(store)]
    finally:
        store.close()


def test_a_kill_after_the_record_leaves_it_and_the_next_start_says_so(tmp_path: Path) -> None:
    with simulate_process(tmp_path, SIMULATED) as (port, _stats):
        command = [
            sys.executable,
            "-m",
            "gateway",
            "write",
            "--port",
            str(port),
            "--address",
            "99",  # nobody answers: the write waits for its answer
            "--profile",
            "jumo-digiline-odo-s10",
            "--timeout",
            "2",
            "--reason",
            "salinity from RAM",
            "compensation_control",  # a word of bits in RAM: no word order to read first
            "2",
        ]
        env = {**os.environ, "SUDO_USER": "alice"}
        with subprocess.Popen(
            command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
        ) as writer:
            wait_until(lambda: pending_writes(tmp_path / "state"), within_s=60)
            writer.send_signal(signal.SIGKILL)
            writer.wait(timeout=10)
        assert writer.returncode == -signal.SIGKILL
    state_dir = tmp_path / "state"
    store = RecordStore(records_path(state_dir))
    assert store.verify().intact
    [pending] = unanswered(store)
    assert pending.body["kind"] == Kind.WRITE
    assert pending.body["actor"]["via"] == "cli"
    assert pending.body["actor"]["detail"] in {"sudo by alice", ""}  # "" if run as alice
    assert pending.body["actor"]["reason"] == "salinity from RAM"
    assert pending.body["points"][0]["sent"] == "2"
    assert pending.body["points"][0]["registers"] == ["0x0002"]
    # What the gateway does first at its start (RunningGateway.start):
    [closed] = close_interrupted(store)
    assert closed.body["completes"] == pending.seq
    assert closed.body["result"] == Result.UNKNOWN
    assert closed.body["note"] == INTERRUPTED
    assert unanswered(store) == []
    assert close_interrupted(store) == []  # once only
    assert store.verify().intact
