"""Records written before :class:`~eol_cal.records.record.RunRecord` (schema ``eol-cal/run-record/1``),
read into one: the migration of a stored record, applied whenever one is read.

What the first schema did not say is derived here, once, by fixed rules:

- **kind**: a run that ended in its pre-flight (or before it) with nothing flashed and nothing
  captured is a ``refusal``; every other run is ``production``. The refusal's codes come from the
  pre-flight's reasons as that version worded them (:data:`V1_PROBLEMS`).
- **checks**: the first schema kept the limits and the values, not the checks. They are judged by
  the limits table of :mod:`eol_cal.records.limits` on the values the record holds: the fit's
  limits when the fit was usable, the ripple's when the record has the ripple; the others are
  not judged. (The same rules the record's verdict came from, so the checks agree with it.)
- **blocks**: ``ecu_prepared`` and ``block`` + ``flash`` become the flashed blocks ``prepare`` and
  ``calibrated`` (only a block with a sequence was flashed). Their files in the run directory are
  the blocks *before* the flash set sequence and CRC: ``sha256`` is null (the record never
  had the bytes as flashed).
"""

from __future__ import annotations

from typing import Any

from eol_cal.records.limits import STAGES, Measured, all_checks, judge
from eol_cal.records.parts_json import (Reader, common_from, ecu_active_from, limits_from, metrics_from,
                                         preflight_from, previous_from, station_from)
from eol_cal.records.parts import SCHEMA_V1, EcuActive, FlashedBlock, Problem, StationInfo

#: the pre-flight's reasons as schema 1 worded them -> refusal code (first match)
V1_PROBLEMS = (
    ("dyno not reachable", "dyno_unreachable"),
    ("latched faults", "dyno_fault"),
    ("drive tripped", "dyno_tripped"),
    ("interlocks not met", "dyno_interlocks"),
    ("ECU bus cannot be opened", "ecu_bus"),
    ("ECU not reachable", "ecu_silent"),
    ("security key not accepted", "key_refused"),
    ("serial", "wrong_serial"),
)
_BEFORE_ANYTHING = ("start", "pre-flight")


def kind_v1(doc: dict[str, Any]) -> str:
    """``refusal`` for a run that ended before anything was written or measured, else ``production``."""
    step = (doc.get("error") or {}).get("step") if isinstance(doc.get("error"), dict) else None
    touched = doc.get("ecu_prepared") or doc.get("block") or doc.get("captures")
    return "refusal" if doc.get("verdict") == "error" and step in _BEFORE_ANYTHING and not touched else "production"


def code_of(text: str) -> str:
    """The refusal code of a pre-flight reason worded by schema 1."""
    return next((code for words, code in V1_PROBLEMS if words in text), "station_error")


def _station(r: Reader, doc: dict[str, Any]) -> StationInfo:
    st = station_from(r.at("station."), r.obj(doc, "station", default=None) or {})
    # the first records kept the station id and operator beside the station as well
    ident = st.id or r.str(doc, "station_id", null=True, default=None)
    operator = st.operator or r.str(doc, "operator", null=True, default=None)
    extra = {k: v for k, v in st.extra.items() if k not in ("station_id", "name") or not ident}
    if ident is None:
        ident = st.extra.get("station_id") or st.extra.get("name")
    return StationInfo(**{**st.__dict__, "id": ident, "operator": operator, "extra": extra})


def _blocks(r: Reader, doc: dict[str, Any]) -> tuple[FlashedBlock, ...]:
    out = []
    prep = r.obj(doc, "ecu_prepared", default=None)
    if prep and prep.get("sequence") is not None:
        rp = r.at("ecu_prepared.")
        out.append(FlashedBlock("prepare", rp.str(prep, "path", null=True, default=None), None, None,
                                rp.int(prep, "bank", null=True, default=None), rp.int(prep, "sequence"),
                                rp.str(prep, "crc32", null=True, default=None), rp.str(prep, "flags", default=None),
                                rp.str(prep, "estimator", default=None), verified=rp.bool(prep, "verified", default=False),
                                previous=previous_from(rp.at("previous."), prep.get("previous"))))
    blk = r.obj(doc, "block", default=None)
    if blk and blk.get("sequence") is not None:
        rb, rf = r.at("block."), r.at("flash.")
        fl = r.obj(doc, "flash", default=None) or {}
        out.append(FlashedBlock(
            "calibrated", rb.str(blk, "path", null=True, default=None), None, rb.int(blk, "bytes", default=None),
            rb.int(blk, "bank", null=True, default=None), rb.int(blk, "sequence"),
            rb.str(blk, "crc32", null=True, default=None), rb.str(blk, "flags", default=None),
            rb.str(blk, "estimator", default=None), rb.int(blk, "table_len", default=None),
            rb.opt_num(blk, "lead_s", default=None), rb.opt_num(blk, "iqc_limit", default=None),
            verified=rf.bool(fl, "verified", default=False), previous=previous_from(rf.at("previous."), fl.get("previous")),
            seconds=rf.opt_num(fl, "seconds", default=None), transfer_blocks=rf.int(fl, "transfer_blocks", default=None),
            retries=rf.int(fl, "retries", default=None)))
    return tuple(out)


def _ecu_active(blocks: tuple[FlashedBlock, ...]) -> EcuActive:
    for role, word in (("calibrated", "calibrated"), ("prepare", "uncompensated")):
        b = next((b for b in blocks if b.role == role), None)
        if b is not None:
            return EcuActive(word, b.sequence, b.bank)
    return EcuActive("unchanged")


def fields_from_v1(r: Reader, doc: dict[str, Any]) -> dict[str, Any]:
    """A schema-1 record's :class:`~eol_cal.records.record.RunRecord` fields (module doc)."""
    assert doc.get("schema") == SCHEMA_V1
    common = common_from(r, doc)
    kind = kind_v1(doc)
    pf = r.obj(doc, "preflight", default=None)
    problems = None
    if pf is not None:
        problems = tuple(Problem(code_of(t), t) for t in r.at("preflight.").strs(pf, "reasons", default=[]))
    preflight = preflight_from(r.at("preflight."), pf, problems)
    codes: tuple[str, ...] = ()
    if kind == "refusal":
        err = common["error"]
        if preflight is not None and preflight.problems:
            codes = preflight.codes
        elif err is not None and err.type in ("KeyboardInterrupt", "Interrupted"):
            codes = ("interrupted",)
        else:
            codes = ("station_error",)
    lim, sha = limits_from(r.at("limits."), r.obj(doc, "limits", null=True, default=None))
    metrics = metrics_from(r.at("metrics."), r.obj(doc, "metrics", null=True, default=None))
    checks: tuple = ()
    fit = common["fit"]
    if lim is not None:
        m = Measured.of_fit(fit) if fit is not None and fit.usable else None
        if m is not None and metrics is not None:
            m = m.with_ripple(metrics.before.pp_pct, metrics.after.pp_pct, metrics.after.pp_no_mech1_pct)
        judged = {"fit": judge(m, lim, "fit")} if m is not None else {}
        if m is not None and metrics is not None:
            judged["ripple"] = judge(m, lim, "ripple")
        checks = tuple(all_checks(judged, lim))
        assert set(judged) <= set(STAGES)
    blocks = _blocks(r, doc)
    active = r.obj(doc, "ecu_active", default=None)
    return dict(
        kind=kind, refusal_codes=codes, station=_station(r, doc), limits=lim, limits_sha256=sha, checks=checks,
        preflight=preflight, blocks=blocks, metrics=metrics,
        ecu_active=ecu_active_from(r.at("ecu_active."), active) if active else _ecu_active(blocks),
        report_error=r.str(doc, "report_error", default=None), **common)
