"""Realistic run records for tests and benchmarks: the real record of an `eol-cal demo` motor
(``fixtures/run_record_demo.json``) with its serial, time, station, values and kind changed, its
checks judged by the limits table on the values it then holds (so verdict, checks and causes
agree as the station's would).
"""

from __future__ import annotations

import dataclasses
import json
import uuid
from typing import Any

from eol_cal.sim import FIXTURES
from eol_cal.records.limits import Measured, VariantLimits, all_checks, failed, judge
from eol_cal.records.record import EcuActive, ErrorInfo, PreflightResult, Problem, RunRecord

TEMPLATE_JSON: dict[str, Any] = json.loads((FIXTURES / "run_record_demo.json").read_text())
TEMPLATE = RunRecord.from_json(TEMPLATE_JSON, "run_record_demo.json")


def _estimate(est: Any, value: float | None) -> Any:
    return est if value is None else dataclasses.replace(est, value=value)


def make_record(serial: str = "M-1", *, started: str = "2026-11-22T10:00:00.000+00:00", station: str | None = "EOL-1",
                operator: str | None = None, variant: str = "EPS-STD", limits: dict[str, float | None] | None = None,
                k6: float | None = None, phase_k6: float | None = None, c6: float | None = None,
                phase_c6: float | None = None, r2: float | None = None, rms: float | None = None,
                pp_before: float | None = None, pp_after: float | None = None, error_step: str | None = None,
                refused: tuple[str, ...] = (), kind: str = "production", run_id: str | None = None) -> RunRecord:
    """A record like the demo's with these values (stored units: k6 N*m/A, c6 N*m, phases rad, p-p %).

    ``error_step``: the run ended in an error there (no fit before ``table``, no ripple);
    ``refused``: a refusal with these codes (nothing written or measured).
    """
    t = TEMPLATE
    fit, m, tl = t.fit, t.metrics, t.limits
    e = fit.estimates if fit is not None else None
    if fit is None or e is None or m is None or tl is None:
        raise ValueError("the template record (fixtures/run_record_demo.json) has no fit, ripple or limits")
    lim = VariantLimits(variant, {**tl.values, **(limits or {})}, tl.source, tl.estimator)
    est = dataclasses.replace(e, k6=_estimate(e.k6, k6), phase_k6=_estimate(e.phase_k6, phase_k6),
                              c6=_estimate(e.c6, c6), phase_c6=_estimate(e.phase_c6, phase_c6))
    quality = {**fit.fit, **({"r2": r2} if r2 is not None else {}), **({"rms": rms} if rms is not None else {})}
    fit = dataclasses.replace(fit, serial=serial, estimates=est, fit=quality)
    metrics = dataclasses.replace(m, before=dataclasses.replace(m.before, pp_pct=pp_before or m.before.pp_pct),
                                  after=dataclasses.replace(m.after, pp_pct=pp_after or m.after.pp_pct))
    st = dataclasses.replace(t.station, id=station, operator=operator)
    rec = dataclasses.replace(t, run_id=run_id or uuid.uuid4().hex, serial=serial, started_at=started, ended_at=started,
                              kind=kind, station=st, limits=lim)
    if refused:
        pre = PreflightResult(None, None, tuple(Problem(c, f"{c} (test)") for c in refused))
        return dataclasses.replace(
            rec, kind="refusal", verdict="error", reasons=tuple(f"pre-flight: {c} (test)" for c in refused),
            refusal_codes=tuple(dict.fromkeys(refused)), error=ErrorInfo("pre-flight", "PreflightFailed", "test"),
            checks=tuple(all_checks({}, lim)), preflight=pre, captures={}, fit=None, blocks=(), metrics=None,
            ecu_active=EcuActive("unchanged"))
    measured = Measured.of_fit(fit)
    judged = {"fit": judge(measured, lim, "fit")}
    if error_step is not None:
        early = error_step in ("pre-flight", "prepare ECU", "acquire", "fit")
        return dataclasses.replace(
            rec, verdict="error", reasons=(f"{error_step}: simulated fault",),
            error=ErrorInfo(error_step, "DynoError", "simulated fault"), fit=None if early else fit,
            checks=tuple(all_checks({} if early else judged, lim)), metrics=None,
            blocks=rec.blocks[:1] if early else rec.blocks)
    judged["ripple"] = judge(measured.with_ripple(metrics.before.pp_pct, metrics.after.pp_pct,
                                                  metrics.after.pp_no_mech1_pct), lim, "ripple")
    reasons = failed(judged["fit"]) + failed(judged["ripple"])
    return dataclasses.replace(rec, fit=fit, metrics=metrics, checks=tuple(all_checks(judged, lim)),
                               verdict="fail" if reasons else "pass", reasons=tuple(reasons))


#: a record as eol-cal wrote it before RunRecord (schema 1): a real demo run on that code
V1_PASS: dict[str, Any] = json.loads((FIXTURES / "run_record_v1_pass.json").read_text())
#: its wrong-serial pre-flight refusal (schema 1 stored it as the serial's run with verdict error)
V1_REFUSAL: dict[str, Any] = json.loads((FIXTURES / "run_record_v1_refusal.json").read_text())


def v1_record(serial: str, *, started: str = "2026-11-22T10:00:00.000+00:00", station: str | None = "EOL-1",
              operator: str | None = "ab", refusal: bool = False, k6: float | None = None) -> dict[str, Any]:
    """A schema-1 record (a real one with serial, time, station, operator and k6 changed)."""
    doc = json.loads(json.dumps(V1_REFUSAL if refusal else V1_PASS))
    doc.update(run_id=uuid.uuid4().hex, serial=serial, started_at=started, ended_at=started)
    doc["station"].update(id=station, operator=operator)
    if k6 is not None and doc["fit"]:
        doc["fit"]["k6"]["value"] = k6
    return doc
