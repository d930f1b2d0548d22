"""The one executor of the station's runs: runs a context's steps in order, times each into the
record's ``steps``, emits each step's start and end as a :class:`StepEvent` to its observers (the
command's progress lines, an operator panel), stops at a step's ``fail``, turns an exception into
the right record, holds signals off while the record is written, and ends with the one
:class:`~eol_cal.records.record.RunRecord` (:mod:`eol_cal.station.outcome`).

The order: the plan's steps (on a line the master check, then
:data:`eol_cal.station.steps.MEASURING`), then, whatever happened, the verdict (fixed, journaled
into the spool and shown first), the report and the record (:mod:`eol_cal.station.steps`). An
``ecu restore`` run is one step, ``restore`` (:func:`eol_cal.station.restore.restore_run`).
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from eol_cal.infra.interrupts import raise_if_received, shielded
from eol_cal.records.record import RunRecord, Step
from eol_cal.station.context import CycleContext, StepVerdict
from eol_cal.station.run import EXIT, RunOutcome
from eol_cal.station.steps import decide_verdict, save_record, write_report

if TYPE_CHECKING:
    from eol_cal.station.report_behind import ReportsBehind

#: the interpreter's thread switch interval while a cycle runs (s; Python's default 0.005): the
#: calibrated flash's first half (sessions, identification, erase) runs its requests while the fit
#: computes; at 0.5 ms its ten round trips took 0.14 s against the fit's 0.13, at 0.1 ms 0.11 s
#: (the fit's CPU the same, issue 37 item 6)
SWITCH_INTERVAL_S = 0.0001

class RunContext(Protocol):
    """What the executor needs of any run's context: the run, the serial, the record's steps."""

    run_id: str
    steps: list[Step]

    @property
    def serial(self) -> str: ...


StepFn = Callable[[CycleContext], Any]
Plan = Callable[[CycleContext], Sequence[tuple[str, StepFn]]]


@dataclass(frozen=True)
class StepEvent:
    """One step of one run began or ended.

    Attributes
    ----------
    run_id, serial : str
        The run's.
    step : str
        The step's name (as the record's ``steps`` keep it; ``verdict`` and ``record`` too).
    what : str
        ``start``, ``done`` or ``failed`` (it raised).
    module : str
        The module of the step's function (``eol_cal.station.steps.fit_capture``...).
    elapsed_s : float or None
        Seconds the step took (None at its start).
    context : object or None
        The run's context (:class:`~eol_cal.station.context.CycleContext`), for a display that shows
        what a step produced (the operator panel's torque trace after the acquisition); read only.
    """

    run_id: str
    serial: str
    step: str
    what: str
    module: str
    elapsed_s: float | None = None
    context: Any = field(default=None, compare=False, repr=False)


Observer = Callable[[StepEvent], None]


class Executor:
    """Runs one station cycle's steps over its context; ``observers`` get each :class:`StepEvent`
    (one that raises is ignored: a display must not cost the run or its record)."""

    def __init__(self, observers: Sequence[Observer] = ()) -> None:
        self.observers: list[Observer] = list(observers)

    def subscribe(self, observer: Observer) -> None:
        self.observers.append(observer)

    def _emit(self, ctx: RunContext, step: str, what: str, fn: Callable, elapsed_s: float | None = None) -> None:
        event = StepEvent(ctx.run_id, ctx.serial, step, what, getattr(fn, "__module__", "") or "", elapsed_s, ctx)
        for observer in list(self.observers):
            with contextlib.suppress(Exception):
                observer(event)

    def timed(self, ctx: Any, name: str, fn: Callable[[Any], Any]) -> Any:
        """Run one step, timed into ``ctx.steps``; a returned :class:`StepVerdict` still counts as done."""
        self._emit(ctx, name, "start", fn)
        t0 = time.perf_counter()
        ctx.steps.append(Step(name, None, False))
        try:
            out = fn(ctx)
        except BaseException:
            ctx.steps[-1] = Step(name, round(time.perf_counter() - t0, 4), False)
            self._emit(ctx, name, "failed", fn, ctx.steps[-1].seconds)
            raise
        ctx.steps[-1] = Step(name, round(time.perf_counter() - t0, 4), True)
        self._emit(ctx, name, "done", fn, ctx.steps[-1].seconds)
        return out

    def untimed(self, ctx: RunContext, name: str, fn: Callable[[], Any], module: Callable) -> Any:
        """Run a closing step that the record's ``steps`` do not list (its events only)."""
        self._emit(ctx, name, "start", module)
        t0 = time.perf_counter()
        try:
            out = fn()
        except BaseException:
            self._emit(ctx, name, "failed", module, round(time.perf_counter() - t0, 4))
            raise
        self._emit(ctx, name, "done", module, round(time.perf_counter() - t0, 4))
        return out

    def run(self, ctx: CycleContext, plan: Plan, on_verdict: Callable[[RunRecord, bool], None] | None = None,
            behind: ReportsBehind | None = None) -> RunOutcome:
        """Every step of ``plan(ctx)`` in order; the record is written whether the motor passed,
        failed or the cycle erred. ``on_verdict(record, spooled)`` shows the verdict as soon as it
        is known, the record in the spool (``spooled`` False: the spool could not take it, and the
        record is written at once, before the report thread or the next serial). With ``behind`` the report and the
        record follow on its thread (:mod:`eol_cal.station.report_behind`) once the verdict's
        record is in the spool, and the outcome returned is the verdict's (``pending``)."""
        previous = sys.getswitchinterval()
        # The main thread waits on the dyno and the ECU (a status poll, a chunk of the buffer, a
        # frame) while the helper thread computes (imports, the windows, the frame): with
        # Python's default 5 ms turns each of those answers waited for the interpreter that long.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        try:
            return self._run(ctx, plan, on_verdict, behind)
        finally:
            sys.setswitchinterval(previous)

    def _run(self, ctx: CycleContext, plan: Plan, on_verdict: Callable[[RunRecord, bool], None] | None,
             behind: ReportsBehind | None) -> RunOutcome:
        try:
            for name, fn in plan(ctx):
                # a signal whose exception a finalizer swallowed (JAX's gc callback, during the
                # fit) stops the cycle here: nothing is flashed after it (eol_cal.infra.interrupts)
                raise_if_received(name)
                found = self.timed(ctx, name, fn)
                if isinstance(found, StepVerdict):
                    ctx.verdict, ctx.reasons = found.verdict, list(found.reasons)
                    if found.verdict != "pass":
                        break
        except BaseException as exc:  # noqa: BLE001 - every failure becomes an error record
            ctx.failure = exc
        interrupted = ctx.failure is not None and not isinstance(ctx.failure, Exception)
        # From here on a signal waits until the record is written (eol_cal.infra.interrupts).
        with shielded():
            rec = self.untimed(ctx, decide_verdict.NAME, lambda: decide_verdict.run(ctx, on_verdict), decide_verdict.run)
            # behind only with the record durable in the spool; a Ctrl-C ends the session: at once;
            # a master run's record is what the next motor's gate reads (eol_cal.msa.gate): at once
            close_now = behind is None or ctx.journal is None or interrupted or ctx.kind == "master"
            if close_now:
                out = self._close(ctx)
        if interrupted:  # Ctrl-C: recorded; now end the process
            raise ctx.failure  # type: ignore[misc]
        if not close_now:
            assert behind is not None  # close_now otherwise
            from eol_cal.records.spool import SaveResult

            # the report thread's steps emit no events: the screen has moved on to the next motor
            job = behind.submit(lambda: Executor()._close(ctx))
            return RunOutcome(rec, SaveResult("spool", str(ctx.journal), "the record at the verdict; the report and "
                                              "the database follow"), None, EXIT[rec.verdict], pending=job)
        return out

    def _close(self, ctx: CycleContext) -> RunOutcome:
        """The run's report, then its record (``report.json``, the database or the spool)."""
        try:
            ctx.report_html = self.timed(ctx, write_report.NAME, write_report.run)
        except Exception as exc:  # noqa: BLE001 - the record must still be written
            write_report.failed(ctx, exc)
        rec, saved = self.untimed(ctx, save_record.NAME, lambda: save_record.run(ctx), save_record.run)
        return RunOutcome(rec, saved, ctx.report_html, EXIT[rec.verdict])
