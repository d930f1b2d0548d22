"""The JSON of a run record's parts (schema ``eol-cal/run-record/2``): one writer and one reader
per part, used by :meth:`eol_cal.records.record.RunRecord.to_json` / ``from_json`` (which spell
the record's top-level keys) and by :mod:`eol_cal.records.v1` (records of schema 1).
Together they are the one place the record's keys are spelled.

Numbers that are not finite (a ripple that could not be measured) are ``null`` in JSON and NaN
in the record; ``to_json(from_json(doc)) == doc`` for every document ``to_json`` wrote.
"""

from __future__ import annotations

import builtins
import math
from collections.abc import Callable, Mapping
from typing import Any

from eol_cal.analysis.motor_result import MotorResult
from eol_cal.capture.ecu_state import EcuState
from eol_cal.errors import ResultFormatError
from eol_cal.records.limits import LimitCheck, VariantLimits
from eol_cal.records.parts import (
    BLOCK_ROLES,
    VERDICTS,
    CaptureRef,
    DynoStatus,
    EcuActive,
    EcuFound,
    ErrorInfo,
    FlashedBlock,
    GateInfo,
    MasterCheck,
    PointFigures,
    PreflightResult,
    PreviousBlock,
    Problem,
    RecordFormatError,
    RestoredFrom,
    RippleMetrics,
    StationInfo,
    Step,
)

_MISSING = object()
#: the station's typed keys, in the order they are written (its other keys go between settings and profile)
_STATION_HEAD = ("id", "operator", "settings")
_STATION_TAIL = ("profile", "verify", "rate_hz", "motor", "bench", "dyno_register_map")
_LIMITS_META = ("variant", "source", "estimator", "sha256")


# --------------------------------------------------------------------------- writing
def ecu_state_json(s: EcuState | None) -> dict[str, Any] | None:
    return None if s is None else s.to_dict()


def station_json(st: StationInfo) -> dict[str, Any]:
    out: dict[str, Any] = {k: getattr(st, k) for k in _STATION_HEAD}
    out.update(st.extra)
    out.update({k: getattr(st, k) for k in _STATION_TAIL})
    return out


def limits_json(lim: VariantLimits | None, sha256: str | None) -> dict[str, Any] | None:
    return None if lim is None else {**lim.to_dict(), "sha256": sha256}


def check_json(c: LimitCheck) -> dict[str, Any]:
    """One check as the record holds it (values in ``unit``; ``pass`` null: not judged)."""
    return {"key": c.key, "quantity": c.quantity, "title": c.title, "unit": c.unit, "sense": c.sense,
            "stage": c.stage, "value": c.value, "limit": c.limit, "margin": c.margin, "pass": c.passed,
            "reason": c.reason}


def capture_json(c: CaptureRef) -> dict[str, Any]:
    return {"path": c.path, "sha256": c.sha256, "samples": c.samples, "segments": c.segments,
            "ecu_before": ecu_state_json(c.ecu_before), "ecu_after": ecu_state_json(c.ecu_after),
            **({} if c.lead_in_s is None else {"lead_in_s": c.lead_in_s}),
            **({} if c.lead_in_point is None else
               {"lead_in_point": {"speed_rpm": c.lead_in_point[0], "seconds": c.lead_in_point[1]}})}


def block_json(b: FlashedBlock) -> dict[str, Any]:
    """One flashed block as the record holds it."""
    prev = None if b.previous is None else {"bank": b.previous.bank, "sequence": b.previous.sequence}
    return {"role": b.role, "path": b.path, "sha256": b.sha256, "bytes": b.bytes, "bank": b.bank,
            "sequence": b.sequence, "crc32": b.crc32, "flags": b.flags, "estimator": b.estimator,
            "table_len": b.table_len, "lead_s": b.lead_s, "iqc_limit": b.iqc_limit, "verified": b.verified,
            "confirmed": b.confirmed, "previous": prev, "seconds": b.seconds, "transfer_blocks": b.transfer_blocks,
            "retries": b.retries, "layout_version": b.layout_version, "mech": b.mech}


def _figures(p: PointFigures) -> dict[str, Any]:
    return {"pp_pct": p.pp_pct, "pp_raw_pct": p.pp_raw_pct, "pp_nm": p.pp_nm, "pp_no_mech1_pct": p.pp_no_mech1_pct,
            "T_avg_nm": p.T_avg_nm, "amp6_nm": p.amp6_nm, "span_s": list(p.span_s), "mech1_nm": p.mech1_nm}


def error_json(e: ErrorInfo | None) -> dict[str, Any] | None:
    return None if e is None else {"step": e.step, "type": e.type, "message": e.message, "traceback": e.traceback}


def step_json(s: Step) -> dict[str, Any]:
    return {"step": s.step, "seconds": s.seconds, "ok": s.ok, "error": s.error}


def restored_json(rf: RestoredFrom | None) -> dict[str, Any] | None:
    return None if rf is None else {"run_id": rf.run_id, "path": rf.path, "sha256": rf.sha256,
                                    "sequence": rf.sequence, "crc32": rf.crc32}


def metrics_json(m: RippleMetrics | None) -> dict[str, Any] | None:
    if m is None:
        return None
    return {"operating_point": {"speed_rpm": m.speed_rpm, "i_qo_a": m.i_qo_a}, "pp_before_pct": m.before.pp_pct,
            "pp_after_pct": m.after.pp_pct, "improvement_pct": m.improvement_pct,
            "pp_after_no_mech1_pct": m.after.pp_no_mech1_pct, "before": _figures(m.before),
            "after": _figures(m.after), "definition": m.definition}


def preflight_json(p: PreflightResult | None) -> dict[str, Any] | None:
    if p is None:
        return None
    dyno = None if p.dyno is None else {"map_version": p.dyno.map_version, "dut_serial": p.dyno.dut_serial,
                                         "faults": p.dyno.faults, "interlocks": p.dyno.interlocks,
                                         "drive_state": p.dyno.drive_state}
    ecu = None if p.ecu is None else {"state": ecu_state_json(p.ecu.state), "key_accepted": p.ecu.key_accepted,
                                       "problems": list(p.ecu.problems)}
    return {"dyno": dyno, "ecu": ecu, "problems": [{"code": x.code, "text": x.text} for x in p.problems]}


# --------------------------------------------------------------------------- reading
class Reader:
    """Typed getters over a decoded JSON object that raise :class:`RecordFormatError` naming the
    source and the field (``where`` is the path so far, e.g. ``blocks[1].``)."""

    # the methods str and bool shadow the builtins in the annotations below them: builtins.str, builtins.bool

    def __init__(self, source: str, where: str = "") -> None:
        self.source = source
        self.where = where

    def at(self, where: str) -> Reader:
        return Reader(self.source, f"{self.where}{where}")

    def error(self, key: str | None, reason: str) -> RecordFormatError:
        name = f"{self.where}{key}" if key is not None else self.where.rstrip(".") or None
        return RecordFormatError(self.source, name, reason)

    def _get(self, d: Mapping[str, Any], key: str, default: Any) -> Any:
        if key in d:
            return d[key]
        if default is _MISSING:
            raise self.error(key, "missing")
        return default

    def value(self, d: Mapping[str, Any], key: str, check: Callable[[Any], bool], what: str, *,
              null: bool = False, default: Any = _MISSING) -> Any:
        x = self._get(d, key, default)
        if x is None and (null or default is None):
            return None
        if not check(x):
            raise self.error(key, f"expected {what}{' or null' if null else ''}, got {type(x).__name__} {x!r:.60}")
        return x

    def str(self, d: Mapping[str, Any], key: str, *, null: bool = False, default: Any = _MISSING) -> Any:
        return self.value(d, key, lambda x: isinstance(x, str), "a string", null=null, default=default)

    def int(self, d: Mapping[builtins.str, Any], key: builtins.str, *, null: bool = False, default: Any = _MISSING) -> Any:
        return self.value(d, key, lambda x: isinstance(x, int) and not isinstance(x, bool), "an integer", null=null,
                          default=default)

    def bool(self, d: Mapping[builtins.str, Any], key: builtins.str, *, null: bool = False, default: Any = _MISSING) -> Any:
        return self.value(d, key, lambda x: isinstance(x, bool), "true or false", null=null, default=default)

    def num(self, d: Mapping[builtins.str, Any], key: builtins.str, *, nan: builtins.bool = False,
            default: Any = _MISSING) -> float:
        """A finite number; with ``nan`` null is NaN (a figure that was not measured)."""
        x = self.value(d, key, lambda x: isinstance(x, (int, float)) and not isinstance(x, bool)
                       and math.isfinite(x), "a finite number", null=nan, default=default)
        return math.nan if x is None else float(x)

    def opt_num(self, d: Mapping[builtins.str, Any], key: builtins.str, default: Any = _MISSING) -> float | None:
        x = self.value(d, key, lambda x: isinstance(x, (int, float)) and not isinstance(x, bool)
                       and math.isfinite(x), "a finite number", null=True, default=default)
        return None if x is None else float(x)

    def obj(self, d: Mapping[builtins.str, Any], key: builtins.str, *, null: builtins.bool = False,
            default: Any = _MISSING) -> Any:
        return self.value(d, key, lambda x: isinstance(x, dict), "an object", null=null, default=default)

    def list(self, d: Mapping[builtins.str, Any], key: builtins.str, *, default: Any = _MISSING) -> list[Any]:
        x = self.value(d, key, lambda x: isinstance(x, list), "a list", default=default)
        return [] if x is None else x

    def strs(self, d: Mapping[builtins.str, Any], key: builtins.str, *, default: Any = _MISSING) -> tuple[builtins.str, ...]:
        x = self.list(d, key, default=default)
        if not all(isinstance(v, str) for v in x):
            raise self.error(key, "expected a list of strings")
        return tuple(x)

    def choice(self, d: Mapping[builtins.str, Any], key: builtins.str, options: tuple[builtins.str, ...], *,
               default: Any = _MISSING) -> builtins.str:
        x = self.str(d, key, default=default)
        if x not in options:
            raise self.error(key, f"{x!r} is not one of {', '.join(options)}")
        return x

    def items(self, d: Mapping[builtins.str, Any], key: builtins.str, read: Callable[[Reader, Any], Any], *,
              default: Any = _MISSING) -> tuple[Any, ...]:
        """``read`` of each element of the list ``d[key]`` (``key[i].`` in errors)."""
        return tuple(read(self.at(f"{key}[{i}]."), x) for i, x in enumerate(self.list(d, key, default=default)))


def gate_json(g: GateInfo | None) -> dict[str, Any] | None:
    if g is None:
        return None
    return {"rules": dict(g.rules), "source": g.source, "station": g.station, "seq": g.seq, "set_at": g.set_at,
            "master_run": g.master_run, "master_started_at": g.master_started_at, "master_verdict": g.master_verdict,
            "checks": [{"quantity": c.quantity, "unit": c.unit, "value": c.value, "reference": c.reference,
                        "tolerance": c.tolerance, "deviation": c.deviation, "passed": c.passed} for c in g.checks]}


def _master_check_from(r: Reader, x: Any) -> MasterCheck:
    d = _need_obj(r, x)
    return MasterCheck(r.str(d, "quantity"), r.str(d, "unit"), r.opt_num(d, "value"), r.num(d, "reference"),
                       r.num(d, "tolerance"), r.opt_num(d, "deviation"), r.bool(d, "passed"))


def gate_from(r: Reader, d: dict[str, Any] | None) -> GateInfo | None:
    if d is None:
        return None
    return GateInfo(r.obj(d, "rules"), r.str(d, "source"), r.str(d, "station", null=True), r.int(d, "seq", null=True),
                    r.str(d, "set_at", null=True), r.str(d, "master_run", null=True),
                    r.str(d, "master_started_at", null=True), r.str(d, "master_verdict", null=True),
                    r.items(d, "checks", _master_check_from))


def _need_obj(r: Reader, x: Any) -> dict[str, Any]:
    if not isinstance(x, dict):
        raise r.error(None, f"expected an object, got {type(x).__name__}")
    return x


def ecu_state_from(r: Reader, x: Any) -> EcuState | None:
    """An :class:`EcuState` of the record (null: none)."""
    if x is None:
        return None
    d = _need_obj(r, x)
    bank = r.value(d, "bank", lambda v: v in (0, 1) and not isinstance(v, bool), "0 or 1", null=True)
    crc = r.str(d, "crc32", null=True, default=None)
    if crc is not None and (len(crc) != 8 or any(ch not in "0123456789abcdef" for ch in crc)):
        raise r.error("crc32", f"{crc!r}: must be 8 lower-case hex digits")
    return EcuState(bank, r.int(d, "sequence", null=True, default=None), crc, r.str(d, "flags", null=True, default=None),
                    r.str(d, "serial", null=True, default=None))


def station_from(r: Reader, d: dict[str, Any]) -> StationInfo:
    typed = {k: r.str(d, k, null=True, default=None) for k in (*_STATION_HEAD, *_STATION_TAIL) if k != "rate_hz"}
    known = set(_STATION_HEAD) | set(_STATION_TAIL)
    return StationInfo(rate_hz=r.int(d, "rate_hz", null=True, default=None),
                       extra={k: v for k, v in d.items() if k not in known}, **typed)


def limits_from(r: Reader, d: dict[str, Any] | None) -> tuple[VariantLimits | None, str | None]:
    """The record's limits (as it kept them: the values it holds) and the limits file's SHA-256."""
    if d is None:
        return None, None
    values = {k: r.opt_num(d, k) for k in d if k not in _LIMITS_META}
    lim = VariantLimits(variant=r.str(d, "variant", default="-"), values=values,
                        source=r.str(d, "source", default="<not recorded>"), estimator=r.str(d, "estimator", default="-"))
    return lim, r.str(d, "sha256", null=True, default=None)


def check_from(r: Reader, x: Any) -> LimitCheck:
    d = _need_obj(r, x)
    passed = r.bool(d, "pass", null=True)
    return LimitCheck(key=r.str(d, "key"), quantity=r.str(d, "quantity"), title=r.str(d, "title"),
                      unit=r.str(d, "unit"), sense=r.choice(d, "sense", ("max", "min")),
                      stage=r.str(d, "stage"), value=r.num(d, "value", nan=True), limit=r.num(d, "limit"),
                      passed=passed, reason=r.str(d, "reason"))


def step_from(r: Reader, x: Any) -> Step:
    d = _need_obj(r, x)
    return Step(r.str(d, "step"), r.opt_num(d, "seconds"), r.bool(d, "ok"), r.str(d, "error", null=True, default=None))


def error_from(r: Reader, d: dict[str, Any] | None) -> ErrorInfo | None:
    if d is None:
        return None
    return ErrorInfo(r.str(d, "step"), r.str(d, "type"), r.str(d, "message"), r.str(d, "traceback", null=True))


def capture_from(r: Reader, x: Any) -> CaptureRef:
    d = _need_obj(r, x)
    return CaptureRef(r.str(d, "path"), r.str(d, "sha256"), r.int(d, "samples"), r.int(d, "segments"),
                      ecu_state_from(r.at("ecu_before."), d.get("ecu_before")),
                      ecu_state_from(r.at("ecu_after."), d.get("ecu_after")),
                      r.num(d, "lead_in_s") if "lead_in_s" in d else None,  # none in records before the lead-in
                      _lead_in_point(r.at("lead_in_point."), d["lead_in_point"]) if "lead_in_point" in d else None)


def _lead_in_point(r: Reader, x: Any) -> tuple[float, float]:
    d = _need_obj(r, x)
    return r.num(d, "speed_rpm"), r.num(d, "seconds")


def previous_from(r: Reader, x: Any) -> PreviousBlock | None:
    if x is None:
        return None
    d = _need_obj(r, x)
    return PreviousBlock(r.value(d, "bank", lambda v: v in (0, 1) and not isinstance(v, bool), "0 or 1", null=True),
                         r.int(d, "sequence"))


def block_from(r: Reader, x: Any) -> FlashedBlock:
    d = _need_obj(r, x)
    n = lambda k: r.int(d, k, null=True)  # noqa: E731
    return FlashedBlock(
        role=r.choice(d, "role", BLOCK_ROLES), path=r.str(d, "path", null=True), sha256=r.str(d, "sha256", null=True),
        bytes=n("bytes"), bank=n("bank"), sequence=n("sequence"), crc32=r.str(d, "crc32", null=True),
        flags=r.str(d, "flags", null=True), estimator=r.str(d, "estimator", null=True), table_len=n("table_len"),
        lead_s=r.opt_num(d, "lead_s"), iqc_limit=r.opt_num(d, "iqc_limit"), verified=r.bool(d, "verified"),
        confirmed=r.bool(d, "confirmed"), previous=previous_from(r.at("previous."), d["previous"]) if "previous" in d
        else None, seconds=r.opt_num(d, "seconds"), transfer_blocks=n("transfer_blocks"), retries=n("retries"),
        layout_version=r.int(d, "layout_version", null=True, default=None),
        mech=r.choice(d, "mech", ("on", "off"), default=None) if d.get("mech") is not None else None)


def _figures_from(r: Reader, d: dict[str, Any]) -> PointFigures:
    span = r.list(d, "span_s")
    if len(span) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in span):
        raise r.error("span_s", "expected [start, end] in s")
    def num(key: str) -> float:
        return r.num(d, key, nan=True, default=None)

    return PointFigures(num("pp_pct"), num("pp_raw_pct"), num("pp_nm"), num("pp_no_mech1_pct"), num("T_avg_nm"),
                        num("amp6_nm"), span_s=(float(span[0]), float(span[1])), mech1_nm=num("mech1_nm"))


def metrics_from(r: Reader, d: dict[str, Any] | None) -> RippleMetrics | None:
    if not d:  # v1 wrote {} when the run ended before the compensated capture
        return None
    op = r.obj(d, "operating_point")
    return RippleMetrics(r.at("operating_point.").num(op, "speed_rpm"), r.at("operating_point.").num(op, "i_qo_a"),
                         _figures_from(r.at("before."), r.obj(d, "before")),
                         _figures_from(r.at("after."), r.obj(d, "after")),
                         r.str(d, "definition", default=""))


def preflight_from(r: Reader, d: dict[str, Any] | None, problems: tuple[Problem, ...] | None = None
                   ) -> PreflightResult | None:
    """The pre-flight; ``problems`` given (a v1 record: its reasons with codes), else read from ``d``."""
    if d is None:
        return None
    dy = r.obj(d, "dyno", null=True)
    dyno = None if dy is None else DynoStatus(*(r.at("dyno.").int(dy, k) if k != "dut_serial" else
                                                r.at("dyno.").str(dy, k) for k in
                                                ("map_version", "dut_serial", "faults", "interlocks", "drive_state")))
    ec = r.obj(d, "ecu", null=True)
    ecu = None if ec is None else EcuFound(ecu_state_from(r.at("ecu.state."), ec.get("state")),
                                           r.at("ecu.").bool(ec, "key_accepted", null=True),
                                           r.at("ecu.").strs(ec, "problems"))
    if problems is None:
        problems = r.items(d, "problems", lambda rr, x: Problem(rr.str(_need_obj(rr, x), "code"), rr.str(x, "text")))
    return PreflightResult(dyno, ecu, problems)


def fit_from(r: Reader, x: Any) -> MotorResult | None:
    if x is None:
        return None

    try:
        return MotorResult.from_json(x, r.source, f"{r.where}fit.")
    except ResultFormatError as exc:
        raise RecordFormatError(exc.file, exc.field, exc.reason) from None


def restored_from(r: Reader, d: dict[str, Any] | None) -> RestoredFrom | None:
    if d is None:
        return None
    return RestoredFrom(r.str(d, "run_id", null=True), r.str(d, "path"), r.str(d, "sha256", null=True),
                        r.int(d, "sequence", null=True), r.str(d, "crc32", null=True))


def common_from(r: Reader, d: dict[str, Any]) -> dict[str, Any]:
    """The fields both versions hold alike (``RunRecord`` keyword arguments)."""
    run_id = r.str(d, "run_id")
    if len(run_id) != 32 or any(ch not in "0123456789abcdef" for ch in run_id):
        raise r.error("run_id", f"{run_id!r}: expected 32 hex digits")
    return dict(run_id=run_id, serial=r.str(d, "serial"), started_at=r.str(d, "started_at"),
                ended_at=r.str(d, "ended_at", null=True, default=None), verdict=r.choice(d, "verdict", VERDICTS),
                reasons=r.strs(d, "reasons", default=[]), error=error_from(r.at("error."), r.obj(d, "error", default=None)),
                tool_version=r.str(d, "tool_version", default="unknown"),
                layout_version=r.int(d, "layout_version", default=1),
                steps=r.items(d, "steps", step_from, default=[]),
                captures={k: capture_from(r.at(f"captures.{k}."), v)
                          for k, v in (r.obj(d, "captures", default=None) or {}).items()},
                fit=fit_from(r, d.get("fit")), report_dir=r.str(d, "report_dir", null=True, default=None),
                safe_state=r.str(d, "safe_state", null=True, default=None))


def ecu_active_from(r: Reader, d: dict[str, Any]) -> EcuActive:
    return EcuActive(r.str(d, "block"), r.int(d, "sequence", null=True), r.int(d, "bank", null=True))
