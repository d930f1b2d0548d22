"""The run record: one typed object per station run, and the one place its JSON is spelled.

:class:`RunRecord` is what the station cycle fills (:mod:`eol_cal.station.cycle`), what the
records database and the spool store, and what the reports, the lot page, ``lot stats``,
``lot diff`` and ``refit`` read. :meth:`RunRecord.to_json` writes schema ``eol-cal/run-record/2``
(``eol_cal/schemas/run-record.schema.json``, keys in ``docs/json.md``); :meth:`RunRecord.from_json`
reads it and, through :mod:`eol_cal.records.v1`, every record written before it
(``eol-cal/run-record/1``): nothing else parses a record's JSON.

Every run has a **kind** (:data:`KINDS`): ``production`` (a motor measured or its ECU written:
its verdict is the motor's), ``refusal`` (the run ended before anything was written to the ECU
or measured: settings, pre-flight; its :data:`REFUSAL_CODES` say why), ``restore`` (an earlier
calibration flashed again, ``eol-cal ecu restore``), ``master`` (a master motor's check) and
``simulated`` (``lot simulate``). Lot statistics, first-pass yield, a serial's latest status,
``lot diff`` and ``refit`` take ``production`` runs unless asked for others (``docs/records.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Mapping

from eol_cal.analysis.motor_result import MotorResult
from eol_cal.records.limits import LimitCheck, VariantLimits
from eol_cal.records.parts_json import (Reader, block_json, check_from, check_json, common_from, ecu_active_from,
                                         gate_from, gate_json, limits_from, metrics_from, metrics_json, preflight_from,
                                         preflight_json,
                                         restored_from, station_from, station_json, capture_json, block_from,
                                         limits_json, error_json, step_json, restored_json)
from eol_cal.records.kinds import KINDS, MEASURED_KIND
from eol_cal.records.parts import (BLOCK_ROLES, REFUSAL_CODES, SCHEMA, SCHEMA_V1,
                                          VERDICTS, CaptureRef, DynoStatus, EcuActive, EcuFound, ErrorInfo,
                                          FlashedBlock, GateInfo, MasterCheck, PointFigures, PreflightResult,
                                          PreviousBlock, Problem,
                                          RecordFormatError, RestoredFrom, RippleMetrics, StationInfo, Step)
from eol_cal.infra.jsonsafe import json_safe
from eol_cal.records.v1 import fields_from_v1, kind_v1

__all__ = ["BLOCK_ROLES", "KINDS", "MEASURED_KIND", "NO_STATION", "REFUSAL_CODES", "SCHEMA", "SCHEMA_V1", "VERDICTS",
           "CaptureRef", "DynoStatus", "EcuActive", "EcuFound", "ErrorInfo", "FlashedBlock", "GateInfo", "MasterCheck",
           "PointFigures", "PreflightResult",
           "PreviousBlock", "Problem", "RecordFormatError", "RestoredFrom", "RippleMetrics", "RunRecord", "StationInfo",
           "Step", "record_kind"]

#: the station label of a run whose record names no station (lots group such runs together)
NO_STATION = "(no station id)"


@dataclass(frozen=True)
class RunRecord:
    """One station run (module doc; keys of the JSON in ``docs/json.md``)."""

    kind: str
    run_id: str
    serial: str
    started_at: str
    ended_at: str | None
    verdict: str
    reasons: tuple[str, ...]
    tool_version: str
    layout_version: int
    station: StationInfo
    refusal_codes: tuple[str, ...] = ()
    error: ErrorInfo | None = None
    limits: VariantLimits | None = None
    limits_sha256: str | None = None
    checks: tuple[LimitCheck, ...] = ()
    steps: tuple[Step, ...] = ()
    preflight: PreflightResult | None = None
    captures: Mapping[str, CaptureRef] = field(default_factory=dict)
    fit: MotorResult | None = None
    blocks: tuple[FlashedBlock, ...] = ()
    metrics: RippleMetrics | None = None
    report_dir: str | None = None
    safe_state: str | None = None
    ecu_active: EcuActive = EcuActive("unchanged")
    restored_from: RestoredFrom | None = None
    report_error: str | None = None
    gate: GateInfo | None = None

    # ------------------------------------------------------------------ reading it
    def block(self, role: str) -> FlashedBlock | None:
        """The last block of ``role`` the run flashed (None: none)."""
        return next((b for b in reversed(self.blocks) if b.role == role), None)

    def check(self, key_or_quantity: str) -> LimitCheck | None:
        """The record's check of a limit key or of the quantity it bounds (None: not among them)."""
        return next((c for c in self.checks if key_or_quantity in (c.key, c.quantity)), None)

    @property
    def station_name(self) -> str | None:
        """The station's id (None: the record has none)."""
        return self.station.id or None

    @property
    def station_label(self) -> str:
        """The station a run was made on as lots group it: its id, or :data:`NO_STATION`."""
        return self.station_name or NO_STATION

    @property
    def operator(self) -> str | None:
        return self.station.operator

    @property
    def total_s(self) -> float:
        """The steps' wall time (s)."""
        return sum(s.seconds or 0.0 for s in self.steps)

    def value(self, quantity: str) -> float:
        """A lot quantity of the run, stored units (NaN: the run has none): ``k6``, ``phase_k6``,
        ``c6``, ``phase_c6`` (N*m/A, N*m, rad), ``pp_before_pct``, ``pp_after_pct``,
        ``improvement_pct`` (%), ``fit_r2`` (1), ``fit_rms_nm`` (N*m)."""
        e = self.fit.estimates if self.fit is not None else None
        m = self.metrics
        if quantity in ("k6", "phase_k6", "c6", "phase_c6"):
            return math.nan if e is None else float(getattr(e, quantity).value)
        if quantity in ("fit_r2", "fit_rms_nm"):
            x = None if self.fit is None else self.fit.fit.get("r2" if quantity == "fit_r2" else "rms")
            return math.nan if x is None else float(x)
        if m is None:
            return math.nan
        return {"pp_before_pct": m.before.pp_pct, "pp_after_pct": m.after.pp_pct,
                "improvement_pct": m.improvement_pct}.get(quantity, math.nan)

    def causes(self) -> list[str]:
        """Why the run did not pass, for a Pareto: a failed run's failed limit keys (or its fit's
        status), an error run's ``error in STEP``, a refusal's codes; empty for a pass."""
        if self.kind == "refusal":
            return list(self.refusal_codes) or ["station_error"]
        if self.verdict == "pass":
            return []
        if self.verdict == "error":
            return [f"error in {self.error.step}" if self.error is not None else "error"]
        keys = [c.key for c in self.checks if c.passed is False]
        if self.fit is not None and not self.fit.usable:
            keys.insert(0, f"fit {self.fit.status}")
        return keys or ["fail (no reason recorded)"]

    # ------------------------------------------------------------------ JSON
    def to_json(self) -> dict[str, Any]:
        """The record as JSON (schema :data:`SCHEMA`; non-finite numbers as null; keys in ``docs/json.md``)."""
        return json_safe({
            "schema": SCHEMA, "kind": self.kind, "run_id": self.run_id, "serial": self.serial,
            "started_at": self.started_at, "ended_at": self.ended_at, "verdict": self.verdict,
            "reasons": list(self.reasons), "refusal_codes": list(self.refusal_codes), "error": error_json(self.error),
            "tool_version": self.tool_version, "layout_version": self.layout_version,
            "station": station_json(self.station), "limits": limits_json(self.limits, self.limits_sha256),
            "checks": [check_json(c) for c in self.checks], "steps": [step_json(s) for s in self.steps],
            "preflight": preflight_json(self.preflight),
            "captures": {k: capture_json(c) for k, c in self.captures.items()},
            "fit": None if self.fit is None else self.fit.to_json(), "blocks": [block_json(b) for b in self.blocks],
            "metrics": metrics_json(self.metrics), "report_dir": self.report_dir, "safe_state": self.safe_state,
            "ecu_active": {"block": self.ecu_active.block, "sequence": self.ecu_active.sequence,
                           "bank": self.ecu_active.bank},
            "restored_from": restored_json(self.restored_from), "report_error": self.report_error,
            # written when the run went through the master gate (records before it have none)
            **({"gate": gate_json(self.gate)} if self.gate is not None else {}),
        })

    @classmethod
    def from_json(cls, doc: Any, source: str = "<record>") -> RunRecord:
        """A record of schema :data:`SCHEMA` or :data:`SCHEMA_V1` (migrated as it is read,
        :mod:`eol_cal.records.v1`); :class:`RecordFormatError` names ``source``, the field and
        the reason."""
        r = Reader(source)
        if not isinstance(doc, dict):
            raise RecordFormatError(source, None, f"expected a record object, got {type(doc).__name__}")
        schema = doc.get("schema")
        if schema == SCHEMA_V1:
            return cls(**fields_from_v1(r, doc))
        if schema != SCHEMA:
            raise r.error("schema", f"{schema!r}: not a run record ({SCHEMA} or {SCHEMA_V1})")
        lim, sha = limits_from(r.at("limits."), r.obj(doc, "limits", null=True))
        return cls(
            kind=r.choice(doc, "kind", KINDS), refusal_codes=r.strs(doc, "refusal_codes"),
            station=station_from(r.at("station."), r.obj(doc, "station")), limits=lim, limits_sha256=sha,
            checks=r.items(doc, "checks", check_from),
            preflight=preflight_from(r.at("preflight."), r.obj(doc, "preflight", null=True)),
            blocks=r.items(doc, "blocks", block_from),
            metrics=metrics_from(r.at("metrics."), r.obj(doc, "metrics", null=True)),
            ecu_active=ecu_active_from(r.at("ecu_active."), r.obj(doc, "ecu_active")),
            restored_from=restored_from(r.at("restored_from."), r.obj(doc, "restored_from", null=True)),
            report_error=r.str(doc, "report_error", null=True),
            gate=gate_from(r.at("gate."), r.obj(doc, "gate", null=True, default=None)), **common_from(r, doc))


def record_kind(doc: Any) -> str | None:
    """The kind of a record's JSON without reading the rest (None: not a record): a v1 record that
    ended in the pre-flight is a refusal, any other v1 record production."""
    if not isinstance(doc, dict):
        return None
    if doc.get("schema") == SCHEMA:
        return doc.get("kind")
    if doc.get("schema") == SCHEMA_V1:
        return kind_v1(doc)
    return None
