"""Fit results: a motor's fit judged into a typed :class:`~eol_cal.analysis.motor_result.MotorResult`,
and the results as the JSON document at the file's edge (schema ``eol-cal/fit-result/1``, keys in
``docs/json.md``).

A motor whose fit did not converge, or whose 95 % interval is wider than the limits, gets a
``status`` other than ``"ok"`` and no estimates (``null`` in every estimate field of the file:
``k6``, ``phase_k6``, ``c6``, ``phase_c6``, ``delay_s``, ``harmonics``): such a fit is reported,
never used.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from eol_cal.analysis.fit import Estimate, FitSpec, MotorFit, load_points
from eol_cal.analysis.intervals import CiLimits, ci_phasor, ci_rel, within
from eol_cal.analysis.motor_result import FitEstimates, FitStatus, Harmonic, MotorResult, OperatingPoint, ValueCi
from eol_cal.errors import InputError
from eol_cal.infra.jsonsafe import json_safe

if TYPE_CHECKING:
    from eol_cal.analysis.fit.motor_input import MotorInput
    from eol_cal.analysis.fit.model_check import ModelCheck

SCHEMA = "eol-cal/fit-result/1"
STATUS_OK = FitStatus.OK
STATUS_NOT_CONVERGED = FitStatus.NOT_CONVERGED
STATUS_CI_TOO_WIDE = FitStatus.CI_TOO_WIDE
STATUS_MODEL_MISMATCH = FitStatus.MODEL_MISMATCH


def judge(fit: MotorFit, spec: FitSpec, limits: CiLimits, model_check: ModelCheck | None = None
          ) -> tuple[FitStatus, list[str]]:
    """Status of a fit and the reasons it is not usable (empty when ``"ok"``); ``model_check`` the
    speed bands' agreement (:func:`eol_cal.analysis.fit.model_check.check_model`), a mismatch
    below ``limits.model_p`` makes the status ``model_mismatch``."""
    if not fit.converged:
        return STATUS_NOT_CONVERGED, [f"solver did not converge in {fit.steps} steps (or produced non-finite values)"]
    reasons = []
    six = fit.harmonics[6]
    # the interval quantities and their comparison are the limits table's (eol_cal.analysis.intervals)
    if spec.fit_k:
        k = six["k"]
        if not within(ci_rel(k.ci95, k.value), limits.k6_rel):
            reasons.append(f"ci95(k6) = {k.ci95:.3g} N*m/A exceeds {100 * limits.k6_rel:g} % of k6 = {k.value:.3g}")
        if not within(math.degrees(k.phase_ci95), limits.phase_k6_deg):
            reasons.append(f"ci95(phase_k6) = {math.degrees(k.phase_ci95):.3g} deg exceeds {limits.phase_k6_deg:g} deg")
    if spec.fit_c:
        c = six["c"]
        bound = ci_phasor(c.ci95, c.value, c.phase_ci95)
        if not within(bound, limits.c6_nm):
            reasons.append(f"c6 phasor ci95 = {bound:.3g} N*m exceeds {limits.c6_nm:g} N*m")
    if reasons:
        return STATUS_CI_TOO_WIDE, reasons
    if model_check is not None and model_check.status == "mismatch" and model_check.p_value < limits.model_p:
        return STATUS_MODEL_MISMATCH, [model_check.note]
    return STATUS_OK, []


def unseparated(spec: FitSpec, i_qo: list[float]) -> str | None:
    """Why the load-proportional phases get no interval, or None when they do.

    With the load-independent part left out (``--no-c6``, the paper's eq. 17) on one load point,
    the fitted k_h phasor is ``k_h + c_h / i_qo``: a cogging c_h the user told the fit to leave out
    moves it identically in every segment, so no lack of fit can show it and no interval can
    include it (a generator with c6 = 10 % of k6 * i_qo: phase_k6 0.378 +- 0.050 rad against 0.30).
    The value stands as what the ripple at that load point says under that assumption."""
    if spec.fit_c or not spec.fit_k or load_points(i_qo) >= 2:
        return None
    return (f"phase intervals of k not given: with c6 left out on one load point (i_qo = {i_qo[0]:.4g} A) a "
            "cogging part would move the k phasors unseen; capture at two load points to have them")


def _vc(value: float, ci95: float | None) -> ValueCi:
    if ci95 is None:
        return ValueCi(json_safe(float(value)), None)
    return ValueCi(json_safe(float(value)), json_safe(float(ci95)))


def _pair(e: Estimate, phase_ci: bool = True) -> tuple[ValueCi, ValueCi]:
    """Amplitude and phase of one fitted part, each with its interval (the phase's only with ``phase_ci``)."""
    return _vc(e.value, e.ci95), _vc(e.phase, e.phase_ci95 if phase_ci else None)


def _harmonic(order: int, parts: dict[str, Estimate], k_phase_ci: bool) -> Harmonic:
    kw: dict[str, ValueCi] = {}
    for p in ("c", "k"):
        if p in parts:
            kw[p], kw[f"phase_{p}"] = _pair(parts[p], p == "c" or k_phase_ci)
    return Harmonic(order, **kw)


def motor_result(
    serial: str,
    fit: MotorFit,
    spec: FitSpec,
    limits: CiLimits,
    *,
    kt: float,
    kt_source: str,
    poles: int,
    encoder_ppr: int,
    sources: list[str],
    segments: list[dict[str, Any]],
    metrics: dict[str, Any],
    solver_mode: str,
    frame: str = "offline",
    frame_offset_rad: float = 0.0,
    frame_offset_sd_rad: float = 0.0,
    bench: dict[str, Any] | None = None,
    hall_angle: dict[str, Any] | None = None,
    frame_estimator: str | None = None,
    mech: Any = None,
    left_out: list[tuple[str, str]] | None = None,
    angle_correction: str = "none",
    model_check: ModelCheck | None = None,
    current_ripple: str = "not measured",
) -> MotorResult:
    """One motor's judged result (an entry of the file's ``motors``, ``docs/json.md``).

    ``fit`` must already be in the frame named by ``frame`` (:func:`eol_cal.analysis.fit.shift_frame`);
    ``frame_offset_rad`` is where that frame sits against the offline hall frame (rad); ``bench``
    the bench mechanics divided out of the measured ripple (None: rigid coupling); ``hall_angle``
    the hall table the phases' frame was measured with (``HallAngles.to_dict``; None: nominal);
    ``frame_estimator`` the estimator options of the firmware frame (``paper``, ``best`` or names);
    ``mech`` the mechanical result (:class:`eol_cal.analysis.motor_result.MechResult`, contract
    revision 1.2), written only with a usable fit; ``left_out`` the captures that gave no segment,
    each with its reason; ``angle_correction`` how the fitted angle was corrected by the encoder's
    fingerprint (:mod:`eol_cal.analysis.fit.fp_angle`), or why not; ``model_check`` the speed
    bands' agreement (None: not run); ``current_ripple`` how the ECU's own current ripple entered
    the fit (:func:`eol_cal.analysis.fit.capture.current_torque`). Its objects hold what the file
    holds (:func:`~eol_cal.infra.jsonsafe.json_safe`: a non-finite number is None), so the result equals
    the one :meth:`MotorResult.from_json` reads back from the file.
    """
    status, reasons = judge(fit, spec, limits, model_check)
    six = fit.harmonics[6]
    estimates = None
    no_phase_ci = unseparated(spec, [float(s["i_qo_a"]) for s in segments]) if segments else None
    if status == STATUS_OK:
        parts: dict[str, ValueCi] = {}
        for part, amp, phase in (("k", "k6", "phase_k6"), ("c", "c6", "phase_c6")):
            # a part not fitted is held at 0 by the model
            parts[amp], parts[phase] = (_pair(six[part], part == "c" or no_phase_ci is None) if part in six
                                        else (ValueCi(0.0, 0.0), ValueCi(0.0, 0.0)))
        estimates = FitEstimates(delay_s=_vc(fit.delay_s, fit.delay_ci95), **parts,
                                 harmonics=tuple(_harmonic(h, fit.harmonics[h], no_phase_ci is None)
                                                 for h in spec.harmonics[1:]))
    if hall_angle is None:
        from eol_cal.analysis.halls import nominal_hall_angles

        hall_angle = nominal_hall_angles("not measured").to_dict()
    fit_stats = {
        "rms": json_safe(float(fit.rms)),
        "r2": json_safe(float(fit.r2)),
        "converged": fit.converged,
        "steps": fit.steps,
        "birge": json_safe(float(fit.birge)),
        "n_samples": fit.n_samples,
        "n_segments": len(segments),
        "solver": spec.solver,
        "batch": solver_mode,
    }
    model = {
        "harmonics": list(spec.harmonics),
        "fit_c6": spec.fit_c,
        "fit_k6": spec.fit_k,
        "delay": "fitted" if spec.fit_delay else "fixed",
        "transducer": spec.transducer,
        "drift_degree": spec.drift_degree,
        "mech_order1": spec.mech_order1,
        "mech_orders": spec.mech_orders if spec.mech_order1 else 0,
        "angle_correction": angle_correction,
        "current_ripple": current_ripple,
        "angle_frame": frame,
        "frame_offset_deg": math.degrees(frame_offset_rad),
        "frame_offset_sd_deg": math.degrees(frame_offset_sd_rad),
        "bench": bench if bench is not None else "rigid",
    }
    if frame_estimator is not None:
        model["frame_estimator"] = frame_estimator
    if no_phase_ci is not None:
        model["unchecked"] = no_phase_ci
    op = operating_point(segments)
    return MotorResult(
        serial=serial, status=status, reasons=tuple(reasons), estimates=estimates, kt=json_safe(float(kt)),
        kt_source=kt_source, metrics=json_safe(metrics), fit=json_safe(fit_stats), model=json_safe(model),
        hall_angle=json_safe(hall_angle), poles=int(poles), encoder_ppr=int(encoder_ppr),
        operating_point=OperatingPoint(json_safe(op["speed_rpm"]), json_safe(op["i_qo_a"])),
        segments=tuple(json_safe(segments)), sources=tuple(sources),
        mech=mech if status == STATUS_OK else None,
        left_out=None if left_out is None else tuple((str(src), str(why)) for src, why in left_out),
        model_check=None if model_check is None else json_safe(model_check.to_json()),
        # values that are not finite: optimistix's own name for it, whatever the solver said
        solver_result=fit.solver_result if fit.finite else "nonfinite",
    )


def result_for_motor(mi: MotorInput, fit: MotorFit, spec: FitSpec, limits: CiLimits, *, metrics: dict[str, Any],
                     solver_mode: str, tick_hz: float | None = 20000.0,
                     cache_dir: str | os.PathLike[str] | None = None) -> MotorResult:
    """:func:`motor_result` for a :class:`~eol_cal.analysis.fit.capture.MotorInput` and its fit.

    Moves the phases into the frame ``motor_inputs`` measured (the firmware's by default,
    :func:`eol_cal.analysis.fit.shift_frame`) and fills the per-segment table; ``fit`` itself
    stays in the offline frame (the plots draw it against the offline angle). With ``tick_hz``
    (the firmware's tick, Hz) the mechanical part is measured too
    (:func:`eol_cal.analysis.fit.mech_orders.fit_mech`); None leaves it out. ``cache_dir``: the
    fit's serialized solvers, for the model check's speed bands.
    """
    import dataclasses

    from eol_cal.analysis.fit import path_gain, shift_frame
    from eol_cal.analysis.fit.motor_fit import at_line_noise, takes_line_noise
    from eol_cal.analysis.fit.segment_noise import segment_noise
    from eol_cal.firmware.options import options_label

    # the intervals at the noise each harmonic has at its own frequency, measured once for them and
    # for the model check's speed bands; a fit whose intervals keep the white noise (fewer than 7
    # segments) leaves the model check to measure the 6th's alone, when it gets that far
    noise = segment_noise(mi.segments, spec, fit.delay_s) if takes_line_noise(fit) else None
    if noise is not None:
        fit = at_line_noise(fit, spec, noise.row_variance())
    g6 = path_gain(mi.segments, FitSpec(harmonics=(6,)))[:, 0]
    segments = [
        {"source": i.source, "t_start": i.t_start, "t_end": i.t_end, "i_qo_a": i.i_qo, "speed_rpm": i.speed_rpm,
         "T_avg_nm": float(fit.t_avg[k]), "shaft_gain_6": float(abs(g6[k])),
         "shaft_phase_6_deg": math.degrees(float(np.angle(g6[k])))}
        for k, i in enumerate(mi.info)
    ]
    from eol_cal.analysis.fit.model_check import bench_provenance, check_model

    mech = None
    if tick_hz is not None and fit.converged:
        from eol_cal.analysis.fit.mech_orders import fit_mech

        mech = fit_mech(mi, fit, spec, tick_hz)
    check = check_model(mi.segments, fit, spec, limits.model_p, bench=bench_provenance(mi.mechanics, mi.captures),
                        noise=noise, cache_dir=cache_dir)
    return motor_result(
        mi.serial, shift_frame(fit, mi.frame_offset_rad, mi.frame_sd_rad), spec, limits, kt=mi.kt, kt_source=mi.kt_source,
        mech=mech,
        poles=mi.poles, encoder_ppr=mi.encoder_ppr, sources=mi.sources, segments=segments, metrics=metrics,
        solver_mode=solver_mode, frame=mi.frame, frame_offset_rad=mi.frame_offset_rad, frame_offset_sd_rad=mi.frame_sd_rad,
        bench=None if mi.mechanics is None else dataclasses.asdict(mi.mechanics),
        hall_angle=None if mi.hall is None else mi.hall.to_dict(),
        frame_estimator=options_label(mi.frame_options) if mi.frame == "firmware" else None,
        left_out=mi.left_out, angle_correction=mi.angle_correction, model_check=check,
        current_ripple=mi.current_ripple,
    )


def operating_point(segments: list[dict[str, Any]]) -> dict[str, float]:
    """The segment the compensation is tuned for: the largest |i_qo|, then the lowest |speed|.

    Returns ``{"speed_rpm": ..., "i_qo_a": ...}``; ``eol-cal table --lead auto`` uses the speed.
    """
    best = max(segments, key=lambda s: (abs(s["i_qo_a"]), -abs(s["speed_rpm"])))
    return {"speed_rpm": float(best["speed_rpm"]), "i_qo_a": float(best["i_qo_a"])}


def result_document(results: Sequence[MotorResult], limits: CiLimits, tool_version: str,
                    created: dt.datetime | None = None) -> dict[str, Any]:
    """The whole result file: the document of ``results`` judged by ``limits`` (the file's edge:
    the one place a fit's results become JSON). ``created``: when they were made (default now, UTC),
    written to the second."""
    created = created or dt.datetime.now(dt.UTC)
    return {
        "schema": SCHEMA,
        "created": created.isoformat(timespec="seconds"),
        "tool": f"eol-cal {tool_version}",
        "limits": limits.to_dict(),
        "motors": [r.to_json() for r in results],
    }


def write_result(doc: dict[str, Any], path: str | Path) -> None:
    """Write the result JSON atomically (temp file in the same directory, fsync, os.replace)."""
    from eol_cal.infra.atomic import atomic_write

    atomic_write(path, json.dumps(doc, indent=2, allow_nan=False) + "\n")


def read_result(path: str | Path) -> dict[str, Any]:
    """Read and check a fit result file (schema, motors list)."""
    from eol_cal.infra.inputs import load_json

    path = Path(path)
    doc = load_json(path)  # a FIFO, non-UTF-8, deep nesting or a 5000-digit number: one line naming the file
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
        got = doc.get("schema") if isinstance(doc, dict) else type(doc).__name__
        raise InputError(str(path), "schema", f"expected {SCHEMA!r}, got {got!r}")
    if not isinstance(doc.get("motors"), list) or not doc["motors"]:
        raise InputError(str(path), "motors", "missing or empty list")
    from eol_cal.firmware.block import serial_problem

    for i, m in enumerate(doc["motors"]):
        if not isinstance(m, dict) or not isinstance(m.get("serial"), str) or "status" not in m:
            raise InputError(str(path), f"motors[{i}]", "needs at least serial and status")
        why = serial_problem(m["serial"])
        if why is not None:  # the serial a block would carry to the ECU
            raise InputError(str(path), f"motors[{i}].serial", why)
    return doc
