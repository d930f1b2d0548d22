"""The station cycle as an object: one method per step, a field for what each step produced.

:class:`StationCycle` runs pre-flight -> prepare ECU -> acquire -> fit -> table -> flash -> acquire
compensated -> metrics (verdict) -> report -> record (see :mod:`eol_cal.station.run`). A step
that finds the motor failing returns a :class:`StepVerdict` and the cycle stops there; an
exception ends it with verdict ``error``. Whatever happened, :meth:`StationCycle.to_record`
builds the one record (keys: ``docs/json.md``, schema ``eol-cal/run-record/1``).
"""

from __future__ import annotations

import datetime as _dt
import time
import traceback
import uuid
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from eol_cal.analysis.point_metrics import PointRipple, nearest_segment, point_ripple, verify_segments
from eol_cal.errors import EolCalError
from eol_cal.interrupts import shielded
from eol_cal.jsonsafe import json_safe
from eol_cal.station.limits import Measured, fit_reasons, measured_from_fit, verdict
from eol_cal.station.run import (
    EXIT,
    ProgressFn,
    RunOutcome,
    StationConfig,
    check_config,
    check_motor,
    ecu_active,
    fit_motor,
    new_run_dir,
    safe_state,
    sha256_file,
)

if TYPE_CHECKING:
    from eol_cal.capture.model import Capture
    from eol_cal.ecu.sequence import FlashReport
    from eol_cal.station.preflight import Preflight
    from eol_cal.station.spool import SaveResult


@dataclass(frozen=True)
class StepVerdict:
    """A step's finding that ends the cycle early: ``fail`` and why."""

    verdict: str
    reasons: tuple[str, ...]


def now_iso() -> str:
    """UTC now, ISO 8601 with milliseconds (the record's time stamps)."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


@dataclass
class StationCycle:
    """One motor's cycle on the station.

    Create it with :meth:`start` (makes the run directory and starts the helper thread), then
    :meth:`run`. Each step method fills its fields; :meth:`to_record` reads them.
    """

    cfg: StationConfig
    progress: ProgressFn | None
    run_id: str
    started: _dt.datetime
    run_dir: Path
    profile_name: str
    segments: list
    station: dict[str, Any]
    limits: dict[str, Any]
    # what the steps produced
    steps: list[dict[str, Any]] = field(default_factory=list)
    preflight: Preflight | None = None
    captures: dict[str, dict[str, Any]] = field(default_factory=dict)
    ecu_prepared: dict[str, Any] | None = None
    before: Capture | None = None
    fit_doc: dict[str, Any] | None = None
    fit_record: dict[str, Any] | None = None
    fit_extra: Any = None
    measured: Measured | None = None
    block_bytes: bytes | None = None
    block: dict[str, Any] | None = None
    flash_result: dict[str, Any] | None = None
    after: Capture | None = None
    point_ripples: tuple[PointRipple, PointRipple] | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    verdict: str = "error"
    reasons: list[str] = field(default_factory=list)
    error: dict[str, Any] | None = None
    safe_state: str | None = None
    ecu_active: dict[str, Any] | None = None
    report_html: Path | None = None
    report_error: str | None = None
    ended_at: str | None = None
    # work on the helper thread
    _helper: ThreadPoolExecutor | None = None
    _prewarm: Future | None = None
    _fit_plots: Future | None = None
    _pr_before: Future | None = None

    @classmethod
    def start(cls, cfg: StationConfig, progress: ProgressFn | None = None) -> StationCycle:
        """Check the configuration, make the run directory, start the helper thread."""
        from eol_cal.dyno import client as dc
        from eol_cal.plant.profile import load_profile

        check_config(cfg)
        profile = load_profile(cfg.profile)
        segments = dc.setpoints_from_profile(profile)
        started = _dt.datetime.now(_dt.timezone.utc)
        run_id = uuid.uuid4().hex
        limits = cfg.limits.to_dict()
        if Path(cfg.limits.source).is_file():
            limits["sha256"] = sha256_file(cfg.limits.source)
        station = dict(cfg.station, profile=profile.name, verify=cfg.verify, rate_hz=cfg.rate_hz,
                       motor=cfg.motor.name, bench=cfg.mechanics.name if cfg.mechanics is not None else "rigid",
                       dyno_register_map=cfg.dyno.regmap.name)
        cycle = cls(cfg=cfg, progress=progress, run_id=run_id, started=started,
                    run_dir=new_run_dir(cfg.report_dir, cfg.serial, started, run_id), profile_name=profile.name,
                    segments=segments, station=station, limits=limits)
        # One helper thread: it imports JAX and matplotlib while the dyno spins the first time
        # (started once the pre-flight passed), and draws the fit's plots while it spins the
        # second time (the main thread mostly waits there).
        cycle._helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="eol-cal-run")
        return cycle

    # ------------------------------------------------------------------ the steps
    def pre_flight(self) -> None:
        """Dyno ready, ECU answering and accepting the key, serials agreeing: before anything is
        written to the ECU (:mod:`eol_cal.station.preflight`); any problem stops the cycle here."""
        from eol_cal.ecu.client import ClientTiming
        from eol_cal.station.preflight import PreflightFailed, preflight

        self.preflight = preflight(self.cfg.serial, self.cfg.dyno, self.cfg.open_bus, self.cfg.seed_to_key,
                                   self.cfg.ecu_timing or ClientTiming())
        if self.preflight.reasons:
            raise PreflightFailed(self.preflight.reasons)
        from eol_cal.analysis.fit.prewarm import prewarm_fit

        self._prewarm = self._helper.submit(prewarm_fit, len(self.segments), self.cfg.cache_dir)

    def prepare_ecu(self) -> None:
        """Flash the uncompensated block, so the calibration capture sees the field estimator alone:
        the same estimator options as the calibrated block will carry."""
        from eol_cal.analysis.fit.table import uncompensated_block
        from eol_cal.atomic import atomic_path
        from eol_cal.firmware.block import flag_names, pack
        from eol_cal.firmware.options import options_label

        options = self.cfg.estimator_options
        blk = uncompensated_block(self.cfg.serial, self.cfg.motor, options=options)
        data = pack(blk)
        path = self.run_dir / "block_uncompensated.bin"
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
        report = self._flash(data, str(path))
        self.ecu_prepared = {"path": str(path), "flags": flag_names(blk.flags), "estimator": options_label(options),
                             "crc32": f"{report.crc32:08x}",
                             "sequence": report.sequence, "bank": report.bank, "verified": report.verified,
                             "previous": previous_block(report)}

    def acquire(self) -> None:
        """The calibration capture over the whole profile."""
        self.before = self._acquire("before", self.segments)

    def fit(self) -> StepVerdict | None:
        """Fit the capture; a fit that is not usable or out of limits fails the motor here."""
        from eol_cal import __version__
        from eol_cal.analysis.result import write_result
        from eol_cal.station.report import fit_plots

        # never two fits at once: JAX tracing, the compilation cache and the fit's solver cache
        # are shared by the threads, and a cold start compiles the same solver in both
        check_motor(self.before, self.cfg.motor)
        self._prewarm.result()
        doc, frec, extra = fit_motor(self.before, self.cfg.limits, __version__, self.cfg.motor, self.cfg.mechanics,
                                     self.cfg.cache_dir, self.cfg.estimator_options)
        write_result(doc, self.run_dir / "fit.json")
        self.fit_doc, self.fit_record, self.fit_extra = doc, frec, extra
        self._fit_plots = self._helper.submit(fit_plots, self.run_dir, extra)
        if frec["status"] != "ok":
            return StepVerdict("fail", tuple(f"fit {frec['status']}: {r}" for r in frec["reasons"])
                               or (f"fit {frec['status']}",))
        self.measured = measured_from_fit(frec)
        reasons = fit_reasons(self.measured, self.cfg.limits)
        return StepVerdict("fail", tuple(reasons)) if reasons else None

    def table(self) -> None:
        """The calibrated block from the fit (lead automatic)."""
        from eol_cal.analysis.fit.table import block_from_record, created_unix
        from eol_cal.atomic import atomic_path
        from eol_cal.firmware.block import flag_names, pack
        from eol_cal.firmware.options import options_label

        options = self.cfg.estimator_options
        blk = block_from_record(self.fit_record, self.cfg.motor, calibrated_at=created_unix(self.fit_doc),
                                source=str(self.run_dir / "fit.json"), options=options)
        data = pack(blk)
        path = self.run_dir / "block.bin"
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
        self.block_bytes = data
        self.block = {"path": str(path), "bytes": len(data), "table_len": blk.table_len,
                      "lead_s": blk.lead_s, "iqc_limit": blk.iqc_limit, "flags": flag_names(blk.flags),
                      "estimator": options_label(options), "crc32": None, "sequence": None}

    def flash(self) -> None:
        """Write the calibrated block into the ECU's inactive bank (verified)."""
        report = self._flash(self.block_bytes, self.block["path"])
        self.block.update(crc32=f"{report.crc32:08x}", sequence=report.sequence, bank=report.bank)
        self.flash_result = {"seconds": round(report.seconds, 4), "verified": report.verified,
                             "transfer_blocks": report.transfer_blocks, "retries": report.retries,
                             "previous": previous_block(report)}

    def acquire_compensated(self) -> None:
        """The capture with the compensation the ECU now runs (the operating point, or everything)."""
        op = self.fit_record["operating_point"]
        segs = self.segments if self.cfg.verify == "full" else verify_segments(self.segments, op["speed_rpm"], op["i_qo_a"])
        # the before-capture's figures are computed meanwhile on the helper thread
        mi = self.fit_extra[0]
        k = nearest_segment(mi.captures, op["speed_rpm"], op["i_qo_a"])
        self._pr_before = self._helper.submit(point_ripple, mi.captures[k], mi.angles[k])
        self.after = self._acquire("after", segs)

    def judge(self) -> StepVerdict:
        """Ripple before and after at the operating point, and the verdict against the limits."""
        from eol_cal.analysis.angle import capture_angle
        from eol_cal.capture.windows import split_windows

        op = self.fit_record["operating_point"]
        before = self._pr_before.result()
        pieces = split_windows(self.after)
        after_cap = pieces[nearest_segment(pieces, op["speed_rpm"], op["i_qo_a"])]
        after = point_ripple(after_cap, capture_angle(after_cap))
        self.point_ripples = (before, after)
        m = Measured(**{**self.measured.__dict__, "pp_before_pct": before.pp_pct, "pp_after_pct": after.pp_pct,
                        "pp_after_no_mech1_pct": after.pp_no_mech1_pct})
        self.measured = m
        self.metrics = json_safe({
            "operating_point": op, "pp_before_pct": m.pp_before_pct, "pp_after_pct": m.pp_after_pct,
            "improvement_pct": m.improvement_pct, "pp_after_no_mech1_pct": after.pp_no_mech1_pct,
            "before": before.to_dict(), "after": after.to_dict(),
            "definition": "filtered p-p % (docs/metrics.md), median over the steady windows of the operating "
                          "point's segment",
        })
        result, reasons = verdict(m, self.cfg.limits)
        return StepVerdict(result, tuple(reasons))

    def report(self) -> Path:
        """The per-motor HTML report (the fit's plots come from the helper thread)."""
        from eol_cal.station.report import write_report

        figures = self._fit_plots.result() if self._fit_plots is not None else []
        return write_report(self.to_record(finite=False), self.run_dir, figures=figures, fit_extra=self.fit_extra,
                            point_ripple=self.point_ripples)

    def record(self, rec: dict[str, Any]) -> SaveResult:
        """Save the record: database, or the spool when the database cannot take it."""
        from eol_cal.station.spool import save_record

        self._progress("record", "start")
        saved = save_record(rec, self.cfg.db, self.cfg.spool_dir, self.cfg.db_timeout_s)
        self._progress("record", "done")
        return saved

    # ------------------------------------------------------------------ the cycle
    def run(self) -> RunOutcome:
        """Every step in order; the record is written whether the motor passed, failed or the cycle erred."""
        from eol_cal.station.report import write_record_json

        failure: BaseException | None = None
        try:
            for name, method in (("pre-flight", self.pre_flight), ("prepare ECU", self.prepare_ecu),
                                 ("acquire", self.acquire), ("fit", self.fit), ("table", self.table), ("flash", self.flash),
                                 ("acquire compensated", self.acquire_compensated), ("metrics", self.judge)):
                found = self._step(name, method)
                if found is not None:
                    self.verdict, self.reasons = found.verdict, list(found.reasons)
                    break
        except BaseException as exc:  # noqa: BLE001 - every failure becomes an error record
            failure = exc
        # From here on a signal waits until the record is written (eol_cal.interrupts).
        with shielded():
            if failure is not None:
                self._record_failure(failure)
            self.ecu_active = self._ecu_active(failure)
            try:
                self.report_html = self._step("report", self.report)
            except Exception as exc:  # noqa: BLE001 - the record must still be written
                self.steps[-1]["error"] = f"{type(exc).__name__}: {exc}"
                self.report_error = f"{type(exc).__name__}: {exc}"
                if self.verdict != "error":
                    self.verdict = "error"
                    self.reasons = self.reasons + [f"report: {exc}"]
            self.ended_at = now_iso()
            self._helper.shutdown(wait=True)
            rec = self.to_record()
            try:
                write_record_json(rec, self.run_dir)
            except Exception as exc:  # noqa: BLE001 - the database still gets it
                rec["report_error"] = f"report.json: {type(exc).__name__}: {exc}"
            saved = self.record(rec)
        if failure is not None and not isinstance(failure, Exception):  # Ctrl-C: recorded; now end the process
            raise failure
        return RunOutcome(rec, saved, self.report_html, EXIT[rec["verdict"]])

    def to_record(self, finite: bool = True) -> dict[str, Any]:
        """The run record (schema ``eol-cal/run-record/1``), from whatever the steps produced.

        Parameters
        ----------
        finite : bool
            Non-finite numbers as ``null`` (JSON); False keeps them for the report's own formatting.
        """
        from eol_cal import __version__
        from eol_cal.firmware.block import LAYOUT_VERSION
        from eol_cal.station.records import RECORD_SCHEMA

        rec: dict[str, Any] = {
            "schema": RECORD_SCHEMA, "run_id": self.run_id, "serial": self.cfg.serial,
            "started_at": self.started.isoformat(timespec="milliseconds"), "ended_at": self.ended_at,
            "verdict": self.verdict, "reasons": list(self.reasons), "error": self.error,
            "tool_version": __version__, "layout_version": LAYOUT_VERSION, "station": self.station,
            "limits": self.limits, "steps": self.steps, "captures": self.captures, "fit": self.fit_record,
            "block": self.block, "flash": self.flash_result, "ecu_prepared": self.ecu_prepared,
            "metrics": self.metrics, "report_dir": str(self.run_dir), "safe_state": self.safe_state,
            "preflight": None if self.preflight is None else self.preflight.to_dict(),
        }
        if self.ecu_active is not None:
            rec["ecu_active"] = self.ecu_active
        if self.report_error is not None:
            rec["report_error"] = self.report_error
        return json_safe(rec) if finite else rec

    # ------------------------------------------------------------------ helpers
    def _progress(self, name: str, what: str) -> None:
        if self.progress:
            self.progress(name, what)

    def _step(self, name: str, fn: Callable[[], Any]) -> Any:
        """Run one step, timed into ``steps``; a returned :class:`StepVerdict` still counts as done."""
        self._progress(name, "start")
        t0 = time.perf_counter()
        entry: dict[str, Any] = {"step": name, "seconds": None, "ok": False}
        self.steps.append(entry)
        try:
            out = fn()
        except BaseException:
            entry["seconds"] = round(time.perf_counter() - t0, 4)
            self._progress(name, "failed")
            raise
        entry["seconds"] = round(time.perf_counter() - t0, 4)
        entry["ok"] = True
        self._progress(name, "done")
        return out

    def _acquire(self, which: str, segs: list) -> Capture:
        """One acquisition with the ECU's state before and after (in the capture and the record);
        the ECU must have run the block this cycle flashed, unchanged, all along."""
        from eol_cal.capture.ecu_state import check_trace
        from eol_cal.ecu.client import ClientTiming
        from eol_cal.station.preflight import acquire_traced, expect_block, read_ecu_with

        path = self.run_dir / f"{which}.mf4"
        cap, trace = acquire_traced(read_ecu_with(self.cfg.open_bus, self.cfg.ecu_timing or ClientTiming()),
                                    self.cfg.dyno, segs, path, serial=self.cfg.serial, rate_hz=self.cfg.rate_hz,
                                    extra_metadata={"comment": f"eol-cal run {self.run_id}: {which}, "
                                                               f"profile {self.profile_name}"})
        self.captures[which] = {"path": str(path), "sha256": sha256_file(path), "samples": int(len(cap.t)),
                                "segments": len(segs), **trace.to_dict()}
        expect_block(trace, which, self.ecu_prepared if which == "before" else self.block)
        if which == "before":
            check_trace(trace, str(path))  # the calibration capture: never under compensation
        return cap

    def _flash(self, data: bytes, source: str) -> FlashReport:
        from eol_cal.ecu.client import ClientTiming, flash_block

        bus = self.cfg.open_bus()
        try:
            return flash_block(bus, data, seed_to_key=self.cfg.seed_to_key, verify=True, source=source,
                               timing=self.cfg.ecu_timing or ClientTiming(), motor=self.cfg.motor)
        finally:
            bus.shutdown()

    def _record_failure(self, exc: BaseException) -> None:

        failed = self.steps[-1]["step"] if self.steps else "start"
        self.verdict = "error"
        self.reasons = [f"{failed}: {exc}" if str(exc) else f"{failed}: {type(exc).__name__}"]
        if getattr(exc, "reasons", None):  # the pre-flight: each problem on its own
            self.reasons = [f"{failed}: {r}" for r in exc.reasons]
        self.error = {"step": failed, "type": type(exc).__name__, "message": str(exc),
                      "traceback": None if isinstance(exc, EolCalError)
                      else "".join(traceback.format_exception(exc, limit=8))}
        if self.preflight is not None and not self.preflight.dyno_reached and failed == "pre-flight":
            self.safe_state = "not commanded: the pre-flight did not reach the dyno (nothing was started on it)"
        else:
            self.safe_state = safe_state(self.cfg.dyno)

    def _ecu_active(self, failure: BaseException | None) -> dict[str, Any]:
        """Which block the ECU boots after this run (see :func:`eol_cal.station.run.ecu_active`)."""

        active = ecu_active({"block": self.block, "ecu_prepared": self.ecu_prepared})
        boots = getattr(failure, "ecu_boots", None)
        if boots is not None and boots["boots"] != "previous":
            # the flash failed after the new block was complete and checked (a dead link, a
            # signal): the ECU boots it at its next reset
            what = "calibrated" if self.error["step"] == "flash" else "uncompensated"
            active = {"block": what if boots["boots"] == "new" else f"{what} (if its CRC was written)",
                      "sequence": boots["sequence"], "bank": boots["bank"]}
        return active


def previous_block(report: FlashReport) -> dict[str, Any]:
    """What the ECU held before a flash (bank None: no valid bank), for the record."""
    return {"bank": report.previous.bank if report.previous.has_bank else None, "sequence": report.previous.sequence}


def run_motor(cfg: StationConfig, progress: ProgressFn | None = None) -> RunOutcome:
    """Run the whole cycle for one motor (:class:`StationCycle`); see :mod:`eol_cal.station.run`.

    Raises only :class:`InputError` for a configuration refused before anything ran (and
    :class:`~eol_cal.station.records.RecordError` if neither database nor spool can take the
    record); every failure during the run is recorded with verdict ``error``.
    """
    return StationCycle.start(cfg, progress).run()
