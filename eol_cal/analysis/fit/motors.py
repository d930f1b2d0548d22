"""Captures -> judged motors: the one path from captures to typed fit results.

``eol-cal fit`` and the end-of-line station (:mod:`eol_cal.station.run`) both call
:func:`fit_motors`: captures are split into their windows (:func:`eol_cal.capture.windows.split_windows`,
a dyno capture's windows are one motor's captures), grouped by serial, segmented, fitted, and
judged into :class:`~eol_cal.analysis.motor_result.MotorResult` s with the phases in the firmware
estimator's angle frame unless told otherwise. The ``eol-cal/fit-result/1`` document is made from
them only where a file or stdout is written (:meth:`MotorsFit.to_json`).
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Callable

from eol_cal.analysis.fit import FitSpec, MotorFit, check_identifiable, pick_mode
from eol_cal.analysis.fit.capture import MotorInput, PreparedWindows
from eol_cal.analysis.motor_result import MotorResult
from eol_cal.analysis.intervals import CiLimits
from eol_cal.capture.data import Capture
from eol_cal.firmware.options import DEFAULT_PRESET, PRESETS
from eol_cal.domain.bench_mechanics import BenchMechanics, load_mechanics
from eol_cal.domain.motor_params import MotorParams


@dataclass(frozen=True)
class FitOptions:
    """How :func:`fit_motors` fits and judges.

    Attributes
    ----------
    spec : FitSpec
        Model and solver settings.
    limits : CiLimits
        Widest intervals of a usable fit.
    settle_s : float
        Settling time dropped after each step (s).
    min_revs : int
        Fewest electrical revolutions per segment.
    frame : {"firmware", "offline"}
        Angle frame the phases are reported in (``firmware``: the frame the ECU evaluates its
        table in, :func:`eol_cal.analysis.firmware_angle.firmware_frame_offset`).
    batch : {"auto", "loop", "vmap", "map"}
        How motors are solved in JAX (auto: :func:`eol_cal.analysis.fit.pick_mode`).
    capture_metrics : bool
        Add each window's p-p ripple to the record's ``metrics.captures``.
    mechanics : BenchMechanics or None
        The dyno bench of the captures (:mod:`eol_cal.domain.bench_mechanics`; default the built-in ``paper``
        bench, which the plant and ``eol-cal dyno-sim`` model): its shaft response is divided out
        of the measured ripple. ``None``: rigid coupling (the measured ripple taken as the motor's).
    hall_angle : {"measured", "nominal"}
        The hall table the record (and ``eol-cal table``'s block) carries: measured from the
        motor's transitions (:mod:`eol_cal.analysis.halls`) or the contract's nominal one.
    motor : MotorParams or None
        Rotor inertia and friction for the shaft response, kt when the captures have none
        (default: the ``paper`` preset).
    cache_dir : Path or None
        Directory of the fit's serialized solvers (:mod:`eol_cal.analysis.fit.cache`); ``None``:
        the process's (:func:`~eol_cal.analysis.fit.batch.fit_many`), where none is set the solver
        is traced in every process.
    estimator_options : int
        The estimator options (contract flags bits 2-5) the ECU ran during the captures, for the
        firmware frame (default the ``best`` choice of :mod:`eol_cal.firmware.options`, what the
        station measures under).
    mech : bool
        Measure each usable motor's mechanical result (its fingerprint's predicted margin, the
        orders, the block's ``MECH_COMP_ENABLE``: :func:`eol_cal.analysis.fit.mech_orders.fit_mech`).
        Off: ``MotorResult.mech`` is None and nothing else changes (the fingerprint that corrects
        the angle is measured with the inputs either way); a refit, whose rows and verdicts never
        read it and which writes no block, leaves it out (:mod:`eol_cal.lot.refit`).
    """

    spec: FitSpec = field(default_factory=FitSpec)
    limits: CiLimits = field(default_factory=CiLimits)
    settle_s: float = 0.1
    min_revs: int = 1
    frame: str = "firmware"
    batch: str = "auto"
    capture_metrics: bool = True
    mechanics: BenchMechanics | None = field(default_factory=lambda: load_mechanics("paper"))
    hall_angle: str = "measured"
    motor: MotorParams | None = None
    cache_dir: Path | None = None
    estimator_options: int = field(default_factory=lambda: PRESETS[DEFAULT_PRESET])
    mech: bool = True


@dataclass
class MotorsFit:
    """What :func:`fit_motors` returns: the motors' typed results and what the plots need.

    Attributes
    ----------
    results : list of MotorResult
        Per motor, its judged result (:class:`~eol_cal.analysis.motor_result.MotorResult`: status,
        the solver's result, estimates); ``results[i].status`` says whether motor i is usable.
    inputs : list of MotorInput
        Per motor, in the order of ``results``.
    fits : list of MotorFit
        Per motor, in the offline angle frame (the plots draw them against the offline angle).
    solver_mode : str
        The batch mode used.
    limits : CiLimits
        The interval limits the results were judged by.
    tool_version : str
        This package's version (the document's ``tool``).
    created : datetime
        When the results were made (UTC, to the second): the document's ``created``, a block's
        ``calibrated_at``.
    """

    results: list[MotorResult]
    inputs: list[MotorInput]
    fits: list[MotorFit]
    solver_mode: str
    limits: CiLimits
    tool_version: str
    created: dt.datetime

    def to_json(self) -> dict[str, Any]:
        """The result document (schema ``eol-cal/fit-result/1``, ``docs/json.md``), for a file or stdout."""
        from eol_cal.analysis.result import result_document

        return result_document(self.results, self.limits, self.tool_version, self.created)


def fit_motors(
    captures: list[Capture],
    options: FitOptions = FitOptions(),
    tool_version: str | None = None,
    progress: Callable[[int], None] | None = None,
    prepared: PreparedWindows | None = None,
) -> MotorsFit:
    """Fit every motor of ``captures`` and judge each into a typed result.

    Parameters
    ----------
    captures : list of Capture
        Any number of motors and captures; joined captures (``segment_starts``, or gaps in ``t``)
        are split into windows, and all windows of one serial are fitted jointly.
    options : FitOptions
        Model, limits, segmentation, frame, batching.
    tool_version : str, optional
        For the document's ``tool`` (default: this package's version).
    progress : callable, optional
        Called with the number of motors fitted so far.
    prepared : PreparedWindows, optional
        Work done on the windows before the fit (the station, while the dyno turned): their
        angles, p-p figures and parts of the firmware frame.

    Returns
    -------
    MotorsFit
        ``results[i].status`` says whether motor i is usable.

    Raises
    ------
    InputError
        A capture without serial, torque, i_qo or any steady segment.
    """
    from eol_cal.analysis.fit.capture import motor_inputs

    inputs = motor_inputs(captures, options.motor, settle_s=options.settle_s, min_revs=options.min_revs,
                          frame=options.frame, mechanics=options.mechanics, hall_angle=options.hall_angle,
                          estimator_options=options.estimator_options, prepared=prepared)
    return fit_inputs(inputs, options, tool_version, progress, prepared)


def fit_inputs(
    inputs: list[MotorInput],
    options: FitOptions = FitOptions(),
    tool_version: str | None = None,
    progress: Callable[[int], None] | None = None,
    prepared: PreparedWindows | None = None,
) -> MotorsFit:
    """The part of :func:`fit_motors` after the inputs (:func:`eol_cal.analysis.fit.capture.motor_inputs`,
    or :func:`~eol_cal.analysis.fit.capture.segment_motors` and
    :func:`~eol_cal.analysis.fit.capture.measure_firmware_frames` for many motors' frames in one
    batch): the fit and the typed results. ``options``' segmentation and frame settings are
    those the inputs were made with; ``prepared`` (as for :func:`fit_motors`) gives the windows'
    p-p figures."""
    from eol_cal.analysis.fit import fit_many
    from eol_cal.analysis.fit.compression import shared_compression
    from eol_cal.analysis.metrics import eta_percent
    from eol_cal.analysis.result import result_for_motor

    if tool_version is None:
        from eol_cal import __version__

        tool_version = __version__
    prepared = prepared or PreparedWindows()
    for m in inputs:  # fit_many checks again, without the captures left out that often explain a refusal
        check_identifiable(m.segments, options.spec, ", ".join(m.sources), m.left_out)
    mode = options.batch if options.batch != "auto" else pick_mode(len(inputs))
    from eol_cal.domain.motor_params import load_motor

    tick_hz = float((options.motor or load_motor("paper")).f_pwm) if options.mech else None
    results = []
    # the model check fits its speed bands on the joint fit's segments: compressed once for both
    with shared_compression():
        fits = fit_many(
            [m.segments for m in inputs],
            options.spec,
            mode=mode,
            chunk=max(1, min(64, len(inputs))),
            sources=[", ".join(m.sources) for m in inputs],
            progress=progress,
            cache_dir=options.cache_dir,
        )
        for mi, f in zip(inputs, fits, strict=True):
            metrics: dict[str, Any] = {"eta_percent": float(eta_percent(mi.encoder_ppr, mi.poles))}
            if options.capture_metrics:
                metrics["captures"] = [prepared.metrics_of(c, a) for c, a in zip(mi.captures, mi.angles, strict=True)]
            results.append(result_for_motor(mi, f, options.spec, options.limits, metrics=metrics, solver_mode=mode,
                                            tick_hz=tick_hz, cache_dir=options.cache_dir))
    created = dt.datetime.now(dt.UTC).replace(microsecond=0)
    return MotorsFit(results, inputs, fits, mode, options.limits, tool_version, created)
