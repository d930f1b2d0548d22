"""The station cycle's steps, one module each, in the order they run (OpenHTF's phases are the model).

Each step module has ``NAME`` (as the record's ``steps`` and the executor's events name it) and
``run(ctx)``, a function of the :class:`~eol_cal.station.context.CycleContext` that does the step's
work through the library, fills the context, and returns None (go on) or a
:class:`~eol_cal.station.context.StepVerdict` (a finding about the motor: ``fail`` ends the cycle
there). :mod:`eol_cal.station.executor` runs them: the master check (on a station with a gate,
:func:`eol_cal.station.steps.check_master.gate_steps`), then :data:`MEASURING`, then, whatever
happened, :mod:`~eol_cal.station.steps.decide_verdict`, :mod:`~eol_cal.station.steps.write_report`
and :mod:`~eol_cal.station.steps.save_record`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from eol_cal.station.steps import (acquire_after, acquire_before, check_ready, fit_capture, flash_calibrated,
                                   make_table, measure_ripple, prepare_ecu)

StepFn = Callable[[Any], Any]

#: the steps from the pre-flight to the ripple's verdict, in order: (name, function of the context)
MEASURING: tuple[tuple[str, StepFn], ...] = tuple((m.NAME, m.run) for m in (
    check_ready, prepare_ecu, acquire_before, fit_capture, make_table, flash_calibrated, acquire_after, measure_ripple))
