"""One motor's station cycle: its steps (:mod:`eol_cal.station.steps`) through the one executor
(:mod:`eol_cal.station.executor`) over its context (:mod:`eol_cal.station.context`).

master check (a gated station) -> pre-flight -> prepare ECU -> acquire -> fit -> table -> flash
-> acquire compensated -> metrics -> verdict -> report -> record (see :mod:`eol_cal.station.run`).
A step that finds the motor failing returns a :class:`~eol_cal.station.context.StepVerdict` and
the cycle stops there; an exception ends it with verdict ``error``. Whatever happened,
:mod:`eol_cal.station.outcome` builds the one :class:`~eol_cal.records.record.RunRecord`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from eol_cal.infra.interrupts import emergency
from eol_cal.records.record import RunRecord
from eol_cal.station.context import CycleContext, start_context
from eol_cal.station.executor import Executor, Observer, StepEvent, StepFn
from eol_cal.station.instruments import Instruments
from eol_cal.station.run import ProgressFn, RunOutcome, StationConfig
from eol_cal.station.steps import MEASURING
from eol_cal.station.steps.check_master import gate_steps

if TYPE_CHECKING:
    from eol_cal.station.report_behind import ReportsBehind


def production_plan(ctx: CycleContext) -> tuple[tuple[str, StepFn], ...]:
    """The steps of a motor on a line: its station's master check, when gated, then the measuring steps."""
    return (*gate_steps(ctx), *MEASURING)


def progress_observer(progress: ProgressFn) -> Observer:
    """The command's progress callback ``(step, "start" | "done" | "failed")`` as an observer."""
    def observe(event: StepEvent) -> None:
        progress(event.step, event.what)

    return observe


def run_motor(cfg: StationConfig, progress: ProgressFn | None = None,
              on_verdict: Callable[[RunRecord, bool], None] | None = None,
              observers: Sequence[Observer] = (), behind: ReportsBehind | None = None,
              instruments: Instruments | None = None, run_id: str | None = None) -> RunOutcome:
    """Run the whole cycle for one motor; see :mod:`eol_cal.station.run`.

    ``on_verdict(record, spooled)`` shows the verdict as soon as it is known (``spooled``:
    the record is safe in the spool), before the report and the database; ``observers`` (and
    ``progress``) get each step's start and end.
    ``behind``: an operator loop's report thread; the run returns at its verdict, with the record in
    the spool, and the report and the database follow there (:meth:`RunOutcome.final`).
    ``instruments``: the dyno and ECU the steps call (default the configuration's Modbus dyno
    and CAN ECU, :class:`~eol_cal.station.instruments.BenchInstruments`); ``run_id``: the run's id
    when the caller names it (a what-if lot's motor), else a new one.

    Raises only :class:`InputError` for a configuration refused before anything ran (and
    :class:`~eol_cal.records.connect.RecordError` if neither database nor spool can take the
    record); every failure during the run is recorded (kind ``refusal`` before anything was
    written, else verdict ``error``).
    """
    ctx = start_context(cfg, instruments, run_id)
    executor = Executor([*([progress_observer(progress)] if progress else []), *observers])

    def dyno_safe_now() -> None:  # the watchdog's last resort if the main thread is stuck: once
        ctx.instruments.safe_state()

    with emergency(dyno_safe_now):
        return executor.run(ctx, production_plan, on_verdict, behind)
