"""Guided calibration in the browser: the flows of ``gateway calibrate``, an operator at a page.

A :class:`CalibrationRun` runs one flow of :mod:`gateway.control.calibration` in a task of
the gateway's loop, with a :class:`WebOperator` that keeps every step for the page to
fetch and answers the flow's confirmation when the operator clicks (an
:class:`asyncio.Future` per question). The flows are the command line's, so the steps, the
checks, the flash preflight and the confirmation before anything is written are the same;
so are the procedures a device offers, their inputs, checks and defaults, which are the
calibration catalogue's (:mod:`gateway.control.calibration.catalogue`).

Cancelling is honoured at every step before the confirmation: while waiting for the answer
it is a "no" (the flow ends declined, nothing written); while reading, the next step the
flow shows stops it with :class:`CommandRejectedError`. Once the operator has confirmed,
the writes run to their end: a half-written calibration is what cancelling must not leave.

A run belongs to the session that started it: only that session's answer is taken, so a
confirmation cannot come from another phone with values computed long ago. A question left
unanswered (phone locked, page reloaded) ends after ``confirm_timeout_s`` as abandoned,
nothing written, so the device is free again; until then any signed-in user can see the
run on the device's page, take it over (it becomes theirs) or cancel it, and both are
logged. While a run is under way its session does not expire (:meth:`Sessions.hold`).

Its task is created under the starting user's :class:`~gateway.records.actor.Actor`
(:func:`~gateway.records.actor.acting`): asyncio copies the context into a task at its
creation, so every write of the flow, long after the request that started it has been
answered, is recorded as that user's, signed as the start was.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
from dataclasses import dataclass, field
from datetime import datetime
from enum import StrEnum
from typing import TYPE_CHECKING, Final

from gateway.control.calibration import catalogue
from gateway.errors import CalibrationInterruptedError, CommandRejectedError, GatewayError
from gateway.records import actor as actors

if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable, Mapping

    from gateway.control.calibration import Step
    from gateway.control.calibration.catalogue import Procedure
    from gateway.control.writes import SafeWriter
    from gateway.profiles import Profile
    from gateway.records.actor import Actor
    from gateway.web.auth import Sessions

_LOGGER = logging.getLogger(__name__)

KEEP_RUNS: Final = 20  # finished runs kept for the page to show
CONFIRM_TIMEOUT_S: Final = 600.0  # as web.confirm_minutes' default
ACTIVE: Final = frozenset({"running", "confirm", "writing"})


def procedures_for(profile: Profile) -> tuple[Procedure, ...]:
    """The procedures a device's profile offers: the catalogue's, as every front end's."""
    return catalogue.offered(profile)


def _now() -> datetime:
    return datetime.now().astimezone()


class Phase(StrEnum):
    """Where a run is."""

    RUNNING = "running"  # reading and computing; cancel stops it
    CONFIRM = "confirm"  # waiting for the operator's answer
    WRITING = "writing"  # confirmed: the writes run to their end
    DONE = "done"  # an outcome (calibrated, declined, verification failed, checked)
    REFUSED = "refused"  # stopped before writing (bad input, budget, a read failed)
    CANCELLED = "cancelled"  # stopped by the operator before writing
    ABANDONED = "abandoned"  # the question went unanswered too long: nothing written
    FAILED = "failed"  # stopped part-way through the writes
    ERROR = "error"  # an unexpected error stopped it (a defect): said, the device freed


class WebOperator:
    """The operator at the page: steps kept for it to fetch, the answer awaited."""

    def __init__(self, run: CalibrationRun) -> None:
        """Tell ``run``."""
        self._run = run

    def show(self, step: Step) -> None:
        """Keep the step; a cancel asked for before the confirmation stops the flow here."""
        run = self._run
        run.steps.append({"kind": step.kind.value, "text": step.text})
        if run.stop_at_next_step:
            run.stop_at_next_step = False
            raise CommandRejectedError("cancelled by the operator: nothing was written")

    def confirm(self, question: str) -> Awaitable[bool]:
        """Ask the page; the answer comes from :meth:`CalibrationRun.answer`."""
        run = self._run
        if run.cancel_requested:
            future: asyncio.Future[bool] = asyncio.get_running_loop().create_future()
            future.set_result(False)
            return future
        loop = asyncio.get_running_loop()
        run.question = question
        run.phase = Phase.CONFIRM
        run.answer_future = loop.create_future()
        run.asked_at = loop.time()
        run.timer = loop.call_later(run.confirm_timeout_s, run.abandon, "no answer in time")
        return run.answer_future


@dataclass(slots=True, kw_only=True)
class CalibrationRun:
    """One calibration started from the page: who, what, its steps, its end."""

    id: str
    device: str
    procedure: Procedure
    who: str
    session: str  # the token of the session it belongs to: only its answer is taken
    inputs: dict[str, object]
    confirm_timeout_s: float = CONFIRM_TIMEOUT_S
    asked_at: float | None = None  # the loop's time of the question
    timer: asyncio.TimerHandle | None = None
    abandoned: str | None = None  # why, once the question was left unanswered
    on_end: Callable[[CalibrationRun], None] | None = None
    phase: Phase = Phase.RUNNING
    steps: list[dict[str, str]] = field(default_factory=list)
    question: str | None = None
    answer_future: asyncio.Future[bool] | None = None
    cancel_requested: bool = False
    stop_at_next_step: bool = False
    outcome: dict[str, object] | None = None
    error: str | None = None
    task: asyncio.Task[None] | None = None
    actor: Actor = actors.UNATTRIBUTED  # who its writes are recorded as: its task's actor

    def as_dict(self) -> dict[str, object]:
        """What the page shows of it: the question in plain words, its detail apart."""
        waiting = self.phase is Phase.CONFIRM and self.question is not None
        summary, _, detail = (self.question or "").partition("\n")
        left = None
        if waiting and self.asked_at is not None:
            elapsed = asyncio.get_running_loop().time() - self.asked_at
            left = round(max(0.0, self.confirm_timeout_s - elapsed))
        return {
            "id": self.id,
            "device": self.device,
            "procedure": self.procedure.as_dict(),
            "who": self.who,
            "actor": self.actor.as_dict(),  # as its writes are recorded: user, signed, reason
            "phase": self.phase.value,
            "steps": list(self.steps),
            "question": self.question if waiting else None,
            "summary": summary if waiting else None,
            "detail": detail if waiting else None,
            "answer_within_s": left,
            "outcome": self.outcome,
            "verdict": self.verdict(),
            "error": self.error,
            "can_cancel": self.phase in {Phase.RUNNING, Phase.CONFIRM}
            and not self.cancel_requested
            and not (self.answer_future is not None and self.answer_future.done()),
        }

    def verdict(self) -> str | None:
        """How it ended, in a sentence for the operator (``None`` while under way)."""
        ended = {
            Phase.ABANDONED: f"Ended: {self.abandoned}. Nothing was written.",
            Phase.CANCELLED: "Cancelled. Nothing was written.",
            Phase.REFUSED: f"Not calibrated: {self.error}",
            Phase.FAILED: f"Stopped part-way through the writes: {self.error}",
            Phase.ERROR: f"Stopped by an unexpected error: {self.error}. What was written, if "
            "anything, is in the records: check the sensor before calibrating again.",
        }
        if self.phase in ended:
            return ended[self.phase]
        if self.phase is not Phase.DONE:
            return None
        outcome = self.outcome or {}
        writes = outcome.get("writes")
        checks = outcome.get("checks")
        failed = [
            str(c["name"])
            for c in (checks if isinstance(checks, list) else [])
            if isinstance(c, dict) and not c["ok"]
        ]
        count = len(writes) if isinstance(writes, list) else 0
        by_status = {
            "calibrated": f"Calibrated: {count} write(s), every check as expected.",
            "verification_failed": "Written, but the sensor does not read back as expected: "
            + ", ".join(failed)
            + ".",
            "declined": "Not written, as you chose: nothing was written, the sensor is as it was.",
            "checked": "Checked: "
            + ("outside limits: " + ", ".join(failed) if failed else "within limits")
            + ". Nothing was written.",
        }
        status = str(outcome.get("status"))
        return by_status.get(status, status)

    def take_over(self, session: str, who: str) -> str:
        """Make the run ``session``'s (its answer is taken from now on); the former owner."""
        if self.phase not in {Phase.RUNNING, Phase.CONFIRM} or self.cancel_requested:
            raise CommandRejectedError(
                f"the calibration is {self.phase.value}: it can no longer be taken over"
            )
        before = self.who
        _LOGGER.info(
            "web: %s took over the %s calibration of %s from %s",
            who,
            self.procedure.id,
            self.device,
            before,
        )
        self.session, self.who = session, who
        return before

    def abandon(self, reason: str) -> None:
        """End an unanswered question as abandoned: a "no", nothing written."""
        future = self.answer_future
        if self.phase is not Phase.CONFIRM or future is None or future.done():
            return
        _LOGGER.warning(
            "web: the %s calibration of %s by %s ended: %s; nothing was written",
            self.procedure.id,
            self.device,
            self.who,
            reason,
        )
        self.abandoned = reason
        self.phase = Phase.RUNNING
        future.set_result(False)

    def answer(self, yes: bool, who: str) -> None:  # noqa: FBT001 - the answer is the point
        """The operator's answer to the pending question."""
        future = self.answer_future
        if self.phase is not Phase.CONFIRM or future is None or future.done():
            raise CommandRejectedError("no question is waiting for an answer")
        _LOGGER.info(
            "web: %s %s the writes of the %s calibration of %s",
            who,
            "confirmed" if yes else "declined",
            self.procedure.id,
            self.device,
        )
        self.phase = Phase.WRITING if yes else Phase.RUNNING
        future.set_result(yes)

    def cancel(self, who: str) -> None:
        """Stop before anything is written; refused once the writes have begun."""
        answered = self.answer_future is not None and self.answer_future.done()
        if self.phase not in {Phase.RUNNING, Phase.CONFIRM} or answered or self.cancel_requested:
            raise CommandRejectedError(
                f"the calibration is {self.phase.value}: it can no longer be cancelled"
            )
        _LOGGER.info(
            "web: %s cancelled the %s calibration of %s", who, self.procedure.id, self.device
        )
        self.cancel_requested = True
        if self.phase is Phase.CONFIRM and self.answer_future is not None:
            self.phase = Phase.RUNNING
            self.answer_future.set_result(False)  # a "no": the flow ends declined
        else:
            self.stop_at_next_step = True  # reading: the flow stops at its next step

    async def execute(self, writer: SafeWriter) -> None:
        """Run the flow to its end and keep how it ended."""
        self.actor = actors.current()  # the task's own, copied at its creation
        try:
            inputs = self.procedure.parse(self.inputs)  # refused here: the run says why
            outcome = await self.procedure.run(writer, WebOperator(self), inputs, when=_now())
        except CalibrationInterruptedError as exc:
            self.phase, self.error = Phase.FAILED, str(exc)
            _LOGGER.exception("web: %s calibration of %s stopped", self.procedure.id, self.device)
        except GatewayError as exc:
            self.phase = Phase.CANCELLED if self.cancel_requested else Phase.REFUSED
            self.error = str(exc)
            _LOGGER.warning("web: %s calibration of %s: %s", self.procedure.id, self.device, exc)
        except asyncio.CancelledError:  # the gateway stops: the run ends with it, said so
            self.phase, self.error = Phase.CANCELLED, "the gateway stopped"
            raise
        except Exception as exc:  # a defect: the page says so and the device is free again
            self.phase, self.error = Phase.ERROR, f"{type(exc).__name__}: {exc}"
            _LOGGER.exception(
                "web: the %s calibration of %s stopped with an unexpected error",
                self.procedure.id,
                self.device,
            )
        else:
            self.outcome = outcome.as_dict()
            if self.abandoned:
                self.phase = Phase.ABANDONED
            else:
                self.phase = Phase.CANCELLED if self.cancel_requested else Phase.DONE
            _LOGGER.info(
                "web: %s calibration of %s by %s: %s, %d write(s): %s",
                self.procedure.id,
                self.device,
                self.who,
                outcome.status.value,
                len(outcome.writes),
                "; ".join(str(w) for w in outcome.writes) or "nothing written",
            )
        finally:
            self.question = None
            if self.timer is not None:
                self.timer.cancel()
            if self.on_end is not None:
                self.on_end(self)


class Calibrations:
    """The runs of this gateway: one at a time per device, the last few kept."""

    def __init__(
        self,
        writers: Mapping[str, SafeWriter],
        *,
        sessions: Sessions | None = None,
        confirm_timeout_s: float = CONFIRM_TIMEOUT_S,
    ) -> None:
        """Calibrate through ``writers`` (device name -> its write path).

        ``sessions`` are held while their runs are under way; a question is left
        unanswered at most ``confirm_timeout_s``.
        """
        self.writers = writers
        self.sessions = sessions
        self.confirm_timeout_s = confirm_timeout_s
        self.runs: dict[str, CalibrationRun] = {}
        self._ids = itertools.count(1)

    def active(self, device: str | None = None) -> list[CalibrationRun]:
        """The runs under way (of ``device``, or of every device)."""
        return [
            r
            for r in self.runs.values()
            if r.phase.value in ACTIVE and (device is None or r.device == device)
        ]

    def take_over(self, run: CalibrationRun, session: str, who: str) -> None:
        """``session`` takes ``run`` over: it holds that session now, not the former."""
        former = run.session
        run.take_over(session, who)
        if self.sessions is not None:
            self.sessions.hold(session)
            self.sessions.release(former)

    def session_ended(self, session: str, who: str) -> None:
        """A session was signed out: its runs that have not begun writing stop."""
        for run in self.runs.values():
            if run.session != session:
                continue
            if run.phase is Phase.CONFIRM:
                run.abandon(f"{who} signed out")
            elif run.phase is Phase.RUNNING and not run.cancel_requested:
                run.cancel(f"{who} (signing out)")

    def _ended(self, run: CalibrationRun) -> None:
        if self.sessions is not None:
            self.sessions.release(run.session)

    def start(
        self,
        device: str,
        procedure_id: str,
        inputs: object,
        who: str,
        session: str = "",
        *,
        actor: Actor | None = None,
    ) -> CalibrationRun:
        """Start a run in a task of its own; refused if the device is busy with one.

        The task acts for ``actor`` (``None``: the caller's actor): it is created inside
        :func:`~gateway.records.actor.acting`, so it inherits the actor with its context.
        """
        if not isinstance(inputs, dict):
            raise CommandRejectedError("inputs must be a JSON object")
        writer = self.writers.get(device)
        if writer is None:
            raise CommandRejectedError(f"no device {device!r}")
        procedure = catalogue.BY_ID.get(procedure_id)
        if procedure is None or not procedure.offered_by(writer.link.profile):
            raise CommandRejectedError(f"{device} has no calibration {procedure_id!r}")
        busy = self.active(device)
        if busy:
            raise CommandRejectedError(
                f"{device} is being calibrated by {busy[0].who} ({busy[0].phase.value}): "
                "take it over or cancel it on the device's page"
            )
        run = CalibrationRun(
            id=f"c{next(self._ids)}",
            device=device,
            procedure=procedure,
            who=who,
            session=session,
            inputs=dict(inputs),
            confirm_timeout_s=self.confirm_timeout_s,
            on_end=self._ended,
        )
        if self.sessions is not None:
            self.sessions.hold(session)
        _LOGGER.info(
            "web: %s started the %s calibration of %s with %s", who, procedure.id, device, inputs
        )
        with actors.acting(actor or actors.current()):
            run.task = asyncio.create_task(run.execute(writer), name=f"web.calibrate[{device}]")
        self.runs[run.id] = run
        self._forget_old()
        return run

    def _forget_old(self) -> None:
        finished = [
            r.id
            for r in self.runs.values()
            if r.phase not in {Phase.RUNNING, Phase.CONFIRM, Phase.WRITING}
        ]
        for run_id in finished[: max(0, len(finished) - KEEP_RUNS)]:
            del self.runs[run_id]

    async def close(self) -> None:
        """Stop the runs still waiting (as declined); let writes in flight finish."""
        for run in self.runs.values():
            if run.phase in {Phase.RUNNING, Phase.CONFIRM}:
                run.cancel("shutdown")
        tasks = [r.task for r in self.runs.values() if r.task is not None and not r.task.done()]
        if tasks:
            await asyncio.wait(tasks, timeout=10.0)
