"""A calibration run's every ending is shown and frees the device, an unexpected error too.

Against the simulator on a pseudo-terminal, through the page's :class:`Calibrations` (the
state the page shows): a flow whose code fails with an error the gateway does not expect
(a defect, here a runner that raises ``RuntimeError``, the one stand-in of this test) ends
as ``error`` with the error in its verdict, the device is free for the next run, and a
real run of the same device then goes on as usual.
"""

from __future__ import annotations

import asyncio
import dataclasses
from typing import TYPE_CHECKING

import pytest

from gateway.config import FlashPolicy
from gateway.control.calibration import catalogue
from gateway.control.flash import FlashLedger
from gateway.control.writes import SafeWriter
from gateway.web.calibration import Calibrations, Phase
from tests.rigs import link_rig, link_target

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.control.calibration.catalogue import Inputs, Procedure
    from gateway.control.calibration.steps import CalibrationOutcome, Operator

pytestmark = [pytest.mark.line]

SENSORS = [{"profile": "jumo-tecline-cl2", "address": 20}]


async def _broken(
    _writer: SafeWriter, _operator: Operator, _inputs: Inputs, _when: object
) -> CalibrationOutcome:
    raise RuntimeError("a defect in a flow")


async def test_an_unexpected_error_ends_the_run_says_so_and_frees_the_device(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    async with link_rig(tmp_path, SENSORS, [link_target("cl2", "jumo-tecline-cl2", 20)]) as rig:
        writer = SafeWriter(
            rig.links["cl2"],
            policy=FlashPolicy(allowed=frozenset(), daily_budget=4),
            ledger=FlashLedger(None),
        )
        calibrations = Calibrations({"cl2": writer})
        check: Procedure = catalogue.BY_ID["check"]
        broken = dataclasses.replace(check, id="broken", runner=_broken)
        monkeypatch.setitem(catalogue.BY_ID, "broken", broken)
        run = calibrations.start("cl2", "broken", {"reference": "0.5"}, "ana")
        assert run.task is not None
        await asyncio.wait_for(run.task, timeout=10)  # ends: the error is the run's, not raised
        shown = run.as_dict()
        assert run.phase is Phase.ERROR
        assert shown["phase"] == "error"
        assert shown["error"] == "RuntimeError: a defect in a flow"
        assert str(shown["verdict"]).startswith("Stopped by an unexpected error: RuntimeError")
        assert shown["can_cancel"] is False
        assert calibrations.active("cl2") == []  # free for the next run
        assert rig.writes(20) == []
        again = calibrations.start("cl2", "check", {"reference": "0.5"}, "ana")  # the real one
        assert again.task is not None
        await asyncio.wait_for(again.task, timeout=30)
        assert again.phase is Phase.DONE, again.as_dict()
