"""The station cycle as an object: one method per step, a field for what each step produced.

:class:`StationCycle` runs pre-flight -> prepare ECU -> acquire -> fit -> table -> flash -> acquire
compensated -> metrics (verdict) -> report -> record (see :mod:`eol_cal.station.run`). A step
that finds the motor failing returns a :class:`StepVerdict` and the cycle stops there; an
exception ends it with verdict ``error``. Each limit is judged once, at its stage
(:func:`eol_cal.records.limits.judge`). Whatever happened, :meth:`StationCycle.to_record` builds
the one :class:`~eol_cal.records.record.RunRecord`: kind ``refusal`` when the cycle ended before
the prepare step (nothing written to the ECU, nothing measured), else the configuration's kind
(``production`` on a line).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import sys
import time
import traceback
import uuid
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable

from eol_cal.analysis.point_metrics import PointRipple, nearest_segment, point_ripple, verify_segments
from eol_cal.errors import EolCalError, InputError
from eol_cal.interrupts import emergency, raise_if_received, shielded
from eol_cal.records.limits import LimitCheck, Measured, all_checks, failed, judge
from eol_cal.records.record import (CaptureRef, EcuActive, ErrorInfo, FlashedBlock, GateInfo, PointFigures,
                                    PreflightResult, RippleMetrics, RunRecord, StationInfo, Step)
from eol_cal.station.run import (EXIT, ProgressFn, RunOutcome, StationConfig, check_config, check_motor, fit_motor,
                                 new_run_dir, safe_state, sha256_file)

if TYPE_CHECKING:
    from eol_cal.analysis.motor_result import MotorResult
    from eol_cal.capture.model import Capture
    from eol_cal.dyno.transfer import DynoConfig
    from eol_cal.firmware.block import ParamBlock
    from eol_cal.station.early import EarlyWindows
    from eol_cal.station.flash_ahead import FlashAhead
    from eol_cal.records.spool import SaveResult

#: the interpreter's thread switch interval while a cycle runs (s; Python's default 0.005)
SWITCH_INTERVAL_S = 0.0005
#: the archive files of a run's directory, by the block's role
ARCHIVE_NAMES = {"prepare": "block_uncompensated.bin", "calibrated": "block.bin"}
RIPPLE_DEFINITION = ("filtered p-p % (docs/metrics.md), median over the steady windows of the operating point's "
                     "segment")


@dataclass(frozen=True)
class StepVerdict:
    """A step's finding that ends the cycle early: ``fail`` and why."""

    verdict: str
    reasons: tuple[str, ...]


def now_iso() -> str:
    """UTC now, ISO 8601 with milliseconds (the record's time stamps)."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")


def station_info(cfg: StationConfig, profile_name: str) -> StationInfo:
    """The record's station: the configuration's description of itself and what the cycle runs."""
    st = dict(cfg.station)
    typed = {k: st.pop(k, None) for k in ("id", "operator", "settings")}
    return StationInfo(**typed, profile=profile_name, verify=cfg.verify, rate_hz=cfg.rate_hz, motor=cfg.motor.name,
                       bench=cfg.mechanics.name if cfg.mechanics is not None else "rigid",
                       dyno_register_map=cfg.dyno.regmap.name, extra=st)


def point_figures(pr: PointRipple) -> PointFigures:
    """The record's figures of a capture's ripple at the operating point."""
    return PointFigures(pr.pp_pct, pr.pp_raw_pct, pr.pp_nm, pr.pp_no_mech1_pct, pr.T_avg_nm, pr.amp6_nm,
                        (float(pr.span_s[0]), float(pr.span_s[1])), pr.mech1_nm)


@dataclass
class StationCycle:
    """One motor's cycle on the station.

    Create it with :meth:`start` (makes the run directory and starts the helper thread), then
    :meth:`run`. Each step method fills its fields; :meth:`to_record` reads them.
    """

    cfg: StationConfig
    progress: ProgressFn | None
    run_id: str
    started: dt.datetime
    run_dir: Path
    profile_name: str
    segments: list
    station: StationInfo
    limits_sha256: str | None
    # what the steps produced
    steps: list[Step] = field(default_factory=list)
    preflight: PreflightResult | None = None
    touched: bool = False  # the prepare step began: from here the run is a measured attempt
    captures: dict[str, CaptureRef] = field(default_factory=dict)
    blocks: list[FlashedBlock] = field(default_factory=list)
    before: Capture | None = None
    fit_doc: dict[str, Any] | None = None
    result: MotorResult | None = None
    fit_extra: Any = None
    measured: Measured | None = None
    judged: dict[str, list[LimitCheck]] = field(default_factory=dict)
    uncompensated: ParamBlock | None = None  # what the prepare step flashes
    calibrated: ParamBlock | None = None
    after: Capture | None = None
    point_ripples: tuple[PointRipple, PointRipple] | None = None
    metrics: RippleMetrics | None = None
    verdict: str = "error"
    reasons: list[str] = field(default_factory=list)
    refusal_codes: tuple[str, ...] = ()
    error: ErrorInfo | None = None
    safe_state: str | None = None
    ecu_active: EcuActive | None = None
    report_html: Path | None = None
    report_error: str | None = None
    ended_at: str | None = None
    gate: Any = None  # the master gate in force (eol_cal.msa.gate.Gate), None: none
    gate_info: GateInfo | None = None  # the record's gate: rules, and the master run that admitted the run
    # work on the helper thread
    _helper: ThreadPoolExecutor | None = None
    _prewarm: Future | None = None
    _early: EarlyWindows | None = None
    _verify: EarlyWindows | None = None
    _writes: dict[str, Future] = field(default_factory=dict)  # capture files being written aside
    _ahead: FlashAhead | None = None  # the calibrated flash's first half, opened during the fit
    _pr_before: Future | None = None

    @classmethod
    def start(cls, cfg: StationConfig, progress: ProgressFn | None = None) -> StationCycle:
        """Check the configuration, make the run directory, start the helper thread."""
        from eol_cal.dyno.setpoints import setpoints_from_profile
        from eol_cal.plant.profile import load_profile

        check_config(cfg)
        profile = load_profile(cfg.profile)
        segments = setpoints_from_profile(profile)
        started = dt.datetime.now(dt.UTC)
        run_id = uuid.uuid4().hex
        sha = sha256_file(cfg.limits.source) if Path(cfg.limits.source).is_file() else None
        cycle = cls(cfg=cfg, progress=progress, run_id=run_id, started=started,
                    run_dir=new_run_dir(cfg.report_dir, cfg.serial, started, run_id), profile_name=profile.name,
                    segments=segments, station=station_info(cfg, profile.name), limits_sha256=sha)
        # One helper thread: while the dyno spins the first time it imports JAX and matplotlib,
        # traces the fit's solver and works on each window as it arrives; while it spins the second
        # time it measures the calibration capture at the operating point (the main thread mostly
        # waits on the dyno there).
        cycle._helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="eol-cal-run")
        return cycle

    # ------------------------------------------------------------------ the steps
    def gate_steps(self) -> tuple[tuple[str, Callable[[], Any]], ...]:
        """The master gate of a production or master run: the station's rules in force (the records
        database's, :func:`eol_cal.msa.gate.gate_in_force`), found before any step; the step
        ``master check`` when there are rules (or they cannot be read: it refuses). The master
        serial runs as kind ``master``, judged against the rules."""
        if self.cfg.kind not in ("production", "master") or (self.cfg.master is None and not self.station.id):
            return ()
        from eol_cal.msa.gate import gate_in_force

        try:
            self.gate = gate_in_force(self.cfg.db, self.station.id, self.cfg.master, timeout_s=self.cfg.db_timeout_s)
        except EolCalError as exc:
            failure = exc

            def refuse() -> None:
                raise failure

            return (("master check", refuse),)
        if self.gate is None:
            return ()
        is_master = self.cfg.serial == self.gate.master.serial
        self.cfg = dataclasses.replace(self.cfg, master=self.gate.master, kind="master" if is_master else "production")
        self.gate_info = self.gate.info()  # a refusal records the rules it was refused under
        return () if is_master else (("master check", self.master_check),)

    def master_check(self) -> None:
        """A production motor on a station with a master gate: refused, before anything is
        touched, while the master check is due or the last one failed (:mod:`eol_cal.msa.gate`);
        else the master run that admitted it goes into the record."""
        from eol_cal.msa.gate import admitted_info, check_gate

        assert self.gate is not None  # gate_steps runs this step only on a station with rules
        last = check_gate(self.cfg.db, self.gate, self.station.id, timeout_s=self.cfg.db_timeout_s)
        assert last is not None  # an open gate has its master run
        self.gate_info = admitted_info(self.gate, last)

    def pre_flight(self) -> None:
        """The settings the cycle will flash with, then dyno ready, ECU answering and accepting the
        key, serials agreeing: before anything is written to the ECU
        (:mod:`eol_cal.station.preflight`); any problem stops the cycle here."""
        from eol_cal.ecu.client import ClientTiming
        from eol_cal.station.preflight import PreflightFailed, preflight

        self.cfg.estimator_options  # noqa: B018 - refuses options that cannot be flashed (a settings refusal)
        self.preflight = preflight(self.cfg.serial, self.cfg.dyno, self.cfg.open_bus, self.cfg.seed_to_key,
                                   self.cfg.ecu_timing or ClientTiming())
        if self.preflight.problems:
            raise PreflightFailed(self.preflight.problems)

    def prepare_ecu(self) -> None:
        """Flash the uncompensated block, so the calibration capture sees the field estimator alone:
        the same estimator options as the calibrated block will carry."""
        from eol_cal.analysis.fit.table import uncompensated_block
        from eol_cal.firmware.block import pack

        self.touched = True
        self.uncompensated = uncompensated_block(self.cfg.serial, self.cfg.motor, options=self.cfg.estimator_options)
        self._flash(pack(self.uncompensated), "prepare")

    def acquire(self) -> None:
        """The calibration capture over the whole profile; each window's angle and p-p figure are
        worked out on the helper thread as the dyno hands it over (:mod:`eol_cal.station.early`),
        behind the fit's pre-warming (imports, the solver's trace), while the shaft turns on."""
        from eol_cal.analysis.fit.prewarm import prewarm_fit
        from eol_cal.station.early import EarlyWindows

        assert self._helper is not None  # start() made the pool
        self._helper.submit(_preload_analysis)
        self._helper.submit(_preload_writers)
        # the plots are drawn after the verdict: matplotlib is not imported while the dyno turns
        self._prewarm = self._helper.submit(prewarm_fit, len(self.segments), self.cfg.cache_dir, False)
        self._early = EarlyWindows(self.cfg.motor.poles, self.cfg.motor.N_enc, self.cfg.estimator_options,
                                   pool=self._helper, cache_dir=self.cfg.cache_dir, n_windows=len(self.segments))
        self.before = self._acquire("before", self.segments, on_window=self._early.on_window, write_aside=True)

    def fit(self) -> StepVerdict | None:
        """Fit the capture; a fit that is not usable or out of the fit's limits fails the motor here.

        What is left when the capture is in: the hall table, the firmware frame (on threads) and
        the joint solve (its solver traced during the capture)."""
        from eol_cal import __version__
        from eol_cal.analysis.result import write_result

        # never two fits at once: JAX tracing, the compilation cache and the fit's solver cache
        # are shared by the threads, and a cold start compiles the same solver in both
        assert self.before is not None  # the acquire step, run before, captured it
        check_motor(self.before, self.cfg.motor)
        self._open_flash_ahead()
        assert self._prewarm is not None  # the acquire step, run before, started it
        self._prewarm.result()
        doc, res, extra = fit_motor(self.before, self.cfg.limits, __version__, self.cfg.motor, self.cfg.mechanics,
                                    self.cfg.cache_dir, self.cfg.estimator_options, prepared=self._early)
        write_result(doc, self.run_dir / "fit.json")
        self.fit_doc, self.result, self.fit_extra = doc, res, extra
        if not res.usable:
            return StepVerdict("fail", tuple(f"fit {res.status}: {r}" for r in res.reasons) or (f"fit {res.status}",))
        self.measured = Measured.of_fit(res)
        self.judged["fit"] = judge(self.measured, self.cfg.limits, "fit")
        reasons = failed(self.judged["fit"])
        return StepVerdict("fail", tuple(reasons)) if reasons else None

    def table(self) -> None:
        """The calibrated block from the fit (lead automatic)."""
        from eol_cal.analysis.fit.table import block_from_result, created_unix

        assert self.result is not None and self.fit_doc is not None  # the fit step, run before, passed
        self.calibrated = block_from_result(self.result, self.cfg.motor, calibrated_at=created_unix(self.fit_doc),
                                            source=str(self.run_dir / "fit.json"), options=self.cfg.estimator_options)

    def flash(self) -> None:
        """Write the calibrated block into the ECU's inactive bank (read back before its CRC unless
        the settings say not, ``flash.read_back``); the calibration capture's file, written beside
        the fit, must be on disk before the block's CRC makes it count (a write that failed aborts
        the flash there: the CRC is never written, the previous block stays active)."""
        from eol_cal.firmware.block import pack

        assert self.calibrated is not None  # the table step, run before, made it
        self._flash(pack(self.calibrated), "calibrated", before_commit=self._settle_writes, ahead=self._ahead)

    def acquire_compensated(self) -> None:
        """The capture with the compensation the ECU now runs (the operating point, or everything)."""
        # the steps run in order and stop at the first that fails: the fit gave a result, start() made the pool
        assert self.result is not None and self._helper is not None
        op = self.result.operating_point
        segs = self.segments if self.cfg.verify == "full" else verify_segments(self.segments, op.speed_rpm, op.i_qo_a)
        # the before-capture's figures are computed meanwhile on the helper thread, and each
        # verification window's as it arrives
        from eol_cal.station.early import EarlyWindows

        mi = self.fit_extra[0]
        k = nearest_segment(mi.captures, op.speed_rpm, op.i_qo_a)
        self._pr_before = self._helper.submit(point_ripple, mi.captures[k], mi.angles[k])
        self._verify = EarlyWindows(self.cfg.motor.poles, self.cfg.motor.N_enc, pool=self._helper, measure=point_ripple)
        self.after = self._acquire("after", segs, on_window=self._verify.on_window)

    def judge(self) -> StepVerdict:
        """Ripple before and after at the operating point, judged against the ripple's limits."""
        from eol_cal.capture.windows import split_windows

        # the steps before this one gave them (the cycle stops at the first step that fails)
        assert self.result is not None and self.measured is not None
        assert self._pr_before is not None and self._verify is not None and self.after is not None
        op = self.result.operating_point
        before = self._pr_before.result()
        pieces = split_windows(self.after)
        after = self._verify.measured(pieces[nearest_segment(pieces, op.speed_rpm, op.i_qo_a)])
        self.point_ripples = (before, after)
        self.metrics = RippleMetrics(float(op.speed_rpm), float(op.i_qo_a), point_figures(before), point_figures(after),
                                     RIPPLE_DEFINITION)
        self.measured = self.measured.with_ripple(before.pp_pct, after.pp_pct, after.pp_no_mech1_pct, after.mech1_nm)
        self.judged["ripple"] = judge(self.measured, self.cfg.limits, "ripple")
        reasons = failed(self.judged["ripple"])
        if self.cfg.kind == "master" and self.cfg.master is not None:  # the master check: within its references
            from eol_cal.msa.gate import judge_master

            e = self.result.estimates
            assert e is not None  # the fit step passed: its result is usable (it has estimates)
            checks = judge_master({"k6": e.k6.value, "phase_k6": e.phase_k6.value, "c6": e.c6.value,
                                   "pp_before_pct": before.pp_pct, "pp_after_pct": after.pp_pct}, self.cfg.master)
            reasons += [c.reason for c in checks if c.reason is not None]
            if self.gate_info is not None:
                self.gate_info = dataclasses.replace(self.gate_info, checks=tuple(checks))
        return StepVerdict("fail" if reasons else "pass", tuple(reasons))

    def report(self) -> Path:
        """The per-motor HTML report with the fit's plots (drawn now: after the verdict is shown)."""
        from eol_cal.station.report import fit_plots, write_report

        figures = fit_plots(self.run_dir, self.fit_extra) if self.fit_extra is not None else []
        return write_report(self.to_record(), self.run_dir, figures=figures, fit_extra=self.fit_extra,
                            point_ripple=self.point_ripples)

    def _journal(self, rec: RunRecord) -> Path | None:
        """The record at the verdict, into the spool before anyone sees the verdict; None when the
        spool cannot be written (the database is tried all the same after the report)."""
        from eol_cal.records.spool import default_spool_dir, spool_record

        try:
            return spool_record(rec, self.cfg.db, self.cfg.spool_dir or default_spool_dir(),
                                "written at the verdict, before the report; the run's process ended before "
                                "it wrote the record into the database")
        except OSError:
            return None

    def _spool_now(self, rec: RunRecord) -> None:
        """The emergency path of :meth:`record` (the watchdog's thread): straight into the spool."""
        from eol_cal.records.spool import default_spool_dir, spool_record

        spool_record(rec, self.cfg.db, self.cfg.spool_dir or default_spool_dir(), "the process was ended by a signal "
                     "while it wrote the database")

    def _dyno_safe_now(self) -> None:
        """The emergency path of the cycle (the watchdog's thread): the dyno's safe state, once."""
        safe_state(self.cfg.dyno)

    def record(self, rec: RunRecord) -> SaveResult:
        """Save the record: database, or the spool when the database cannot take it."""
        from eol_cal.records.spool import save_record

        self._progress("record", "start")
        saved = save_record(rec, self.cfg.db, self.cfg.spool_dir, self.cfg.db_timeout_s)
        self._progress("record", "done")
        return saved

    # ------------------------------------------------------------------ the cycle
    def run(self, on_verdict: Callable[[RunRecord], None] | None = None) -> RunOutcome:
        """Every step in order; the record is written whether the motor passed, failed or the cycle erred.

        The verdict comes first: as soon as it is known the record goes into the spool (durable:
        a station killed from then on loses nothing, the next start writes it into the database),
        ``on_verdict(record)`` shows it, and only then are the report drawn and the record written
        into the database (and its spool file removed).
        """
        previous = sys.getswitchinterval()
        # The main thread waits on the dyno and the ECU (a status poll, a chunk of the buffer, a
        # frame) while the helper thread computes (imports, the windows, the frame): with
        # Python's default 5 ms turns each of those answers waited for the interpreter that long.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        try:
            return self._run(on_verdict)
        finally:
            sys.setswitchinterval(previous)

    def _run(self, on_verdict: Callable[[RunRecord], None] | None) -> RunOutcome:
        failure: BaseException | None = None
        try:
            gate = self.gate_steps()
            for name, method in (*gate, ("pre-flight", self.pre_flight), ("prepare ECU", self.prepare_ecu),
                                 ("acquire", self.acquire), ("fit", self.fit), ("table", self.table), ("flash", self.flash),
                                 ("acquire compensated", self.acquire_compensated), ("metrics", self.judge)):
                # a signal whose exception a finalizer swallowed (JAX's gc callback, during the
                # fit) stops the cycle here: nothing is flashed after it (eol_cal.interrupts)
                raise_if_received(name)
                found = self._step(name, method)
                if found is not None:
                    self.verdict, self.reasons = found.verdict, list(found.reasons)
                    if found.verdict != "pass":
                        break
        except BaseException as exc:  # noqa: BLE001 - every failure becomes an error record
            failure = exc
        # From here on a signal waits until the record is written (eol_cal.interrupts).
        with shielded():
            self._close_flash_ahead()  # a cycle that ended before its flash: the session is left
            try:
                self._settle_writes()  # the cycle ended before the flash waited for them
            except EolCalError as exc:
                failure = failure or exc
            if failure is not None:
                self._record_failure(failure)
            self.ecu_active = self._ecu_active(failure)
            if failure is not None and self.ecu_active.block.startswith("uncompensated"):
                # the calibration state is part of the outcome: said in the record, not only on screen
                self.reasons = [*self.reasons, _uncalibrated(self.ecu_active, self.steps[-1].step if self.steps else "start",
                                                             self.cfg.dyno)]
            self.ended_at = now_iso()
            verdict_rec = self.to_record()
            journal = self._journal(verdict_rec)
            if on_verdict is not None:
                with contextlib.suppress(Exception):  # a display that fails must not cost the record
                    on_verdict(verdict_rec)
            try:
                self.report_html = self._step("report", self.report)
            except Exception as exc:  # noqa: BLE001 - the record must still be written
                self.steps[-1] = dataclasses.replace(self.steps[-1], error=f"{type(exc).__name__}: {exc}")
                self.report_error = f"{type(exc).__name__}: {exc}"
                if self.verdict != "error":
                    self.verdict = "error"
                    self.reasons = self.reasons + [f"report: {exc}"]
            self.ended_at = now_iso()
            assert self._helper is not None  # start() made the pool
            self._helper.shutdown(wait=True)
            # imported after the verdict (the lot page's modules: 0.2 s at `eol-cal run`'s start),
            # by the helper while the dyno turned (_preload_writers)
            from eol_cal.station.report import write_record_json

            rec = self.to_record()
            try:
                write_record_json(rec, self.run_dir)
            except Exception as exc:  # noqa: BLE001 - the database still gets it
                rec = dataclasses.replace(rec, report_error=f"report.json: {type(exc).__name__}: {exc}")
            # a main thread stuck in the database write (a share that hangs) still leaves the
            # record in the spool when the watchdog ends the process
            with emergency(lambda: self._spool_now(rec)):
                saved = self.record(rec)
            if journal is not None and saved.where == "db":
                journal.unlink(missing_ok=True)
        if failure is not None and not isinstance(failure, Exception):  # Ctrl-C: recorded; now end the process
            raise failure
        return RunOutcome(rec, saved, self.report_html, EXIT[rec.verdict])

    @property
    def kind(self) -> str:
        """``refusal`` when the cycle ended before the prepare step, else the configuration's kind."""
        return self.cfg.kind if self.touched else "refusal"

    def to_record(self) -> RunRecord:
        """The run record, from whatever the steps produced."""
        from eol_cal import __version__
        from eol_cal.firmware.block import LAYOUT_VERSION

        lim = self.cfg.limits
        layout = LAYOUT_VERSION
        if self.calibrated is not None and self.calibrated.layout_version is not None:  # (never None once made)
            layout = self.calibrated.layout_version
        return RunRecord(
            kind=self.kind, run_id=self.run_id, serial=self.cfg.serial,
            started_at=self.started.isoformat(timespec="milliseconds"), ended_at=self.ended_at, verdict=self.verdict,
            reasons=tuple(self.reasons), refusal_codes=self.refusal_codes if self.kind == "refusal" else (),
            error=self.error, tool_version=__version__, station=self.station,
            layout_version=layout,
            limits=lim, limits_sha256=self.limits_sha256, checks=tuple(all_checks(self.judged, lim)),
            steps=tuple(self.steps), preflight=self.preflight, captures=dict(self.captures), fit=self.result,
            blocks=tuple(self.blocks), metrics=self.metrics, report_dir=str(self.run_dir), safe_state=self.safe_state,
            ecu_active=self.ecu_active or self._ecu_active(None), report_error=self.report_error, gate=self.gate_info)

    # ------------------------------------------------------------------ helpers
    def _progress(self, name: str, what: str) -> None:
        if self.progress:
            self.progress(name, what)

    def _step(self, name: str, fn: Callable[[], Any]) -> Any:
        """Run one step, timed into ``steps``; a returned :class:`StepVerdict` still counts as done."""
        self._progress(name, "start")
        t0 = time.perf_counter()
        self.steps.append(Step(name, None, False))
        try:
            out = fn()
        except BaseException:
            self.steps[-1] = Step(name, round(time.perf_counter() - t0, 4), False)
            self._progress(name, "failed")
            raise
        self.steps[-1] = Step(name, round(time.perf_counter() - t0, 4), True)
        self._progress(name, "done")
        return out

    def _acquire(self, which: str, segs: list, on_window: Callable | None = None, write_aside: bool = False) -> Capture:
        """One acquisition with the ECU's state before and after (in the capture and the record);
        the ECU must have run the block this cycle flashed, unchanged, all along. ``on_window``:
        the dyno client's hook for each window as it is read. ``write_aside``: the capture file is
        written on a thread of its own, beside the fit and the download; :meth:`_settle_writes` waits
        for it (the flash does, before the block's CRC makes it count). The flash before reset
        the ECU: the shaft turns for its settling first (the lead-in, ``cfg.lead_in``)."""
        from eol_cal.capture.ecu_state import check_trace
        from eol_cal.ecu.client import ClientTiming
        from eol_cal.firmware.settling import block_settle_s, lead_in_plan
        from eol_cal.station.acquisition import acquire_traced, expect_block, read_ecu_with

        path = self.run_dir / f"{which}.mf4"
        booted = self.uncompensated if which == "before" else self.calibrated
        speed, lead_point, lead_in_s = float(segs[0].speed_rpm), None, 0.0
        if self.cfg.lead_in == "at-point":
            lead_in_s = block_settle_s(booted, speed)
        elif self.cfg.lead_in == "settle":
            point_rpm, point_s, lead_in_s = lead_in_plan(booted, speed)
            if point_rpm is not None:
                lead_point = dataclasses.replace(segs[0], speed_rpm=point_rpm, seconds=point_s)
        cap, trace = acquire_traced(read_ecu_with(self.cfg.open_bus, self.cfg.ecu_timing or ClientTiming()),
                                    self.cfg.dyno, segs, None, serial=self.cfg.serial, rate_hz=self.cfg.rate_hz,
                                    extra_metadata={"comment": f"eol-cal run {self.run_id}: {which}, "
                                                               f"profile {self.profile_name}"}, on_window=on_window,
                                    lead_in_s=lead_in_s, lead_in_point=lead_point)
        if write_aside:
            writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="capture-writer")
            self._writes[which] = writer.submit(self._store, which, cap, trace, path, len(segs))
            writer.shutdown(wait=False)
        else:
            self._store(which, cap, trace, path, len(segs))
        # a capture whose ECU state is not the expected one is kept all the same (its file and record)
        expect_block(trace, which, self._last_block("prepare" if which == "before" else "calibrated"))
        if which == "before":
            check_trace(trace, str(path))  # the calibration capture: never under compensation
        return cap

    def _store(self, which: str, cap: Capture, trace: Any, path: Path, n_segments: int) -> None:
        """Write a capture file (atomically) and keep its reference for the record."""
        from eol_cal.capture import write_capture

        write_capture(cap, path)
        point = ((float(cap.metadata["lead_in_point_rpm"]), float(cap.metadata["lead_in_point_s"]))
                 if "lead_in_point_rpm" in cap.metadata else None)
        self.captures[which] = CaptureRef(str(path), sha256_file(path), int(len(cap.t)), n_segments, trace.before,
                                          trace.after, float(cap.metadata.get("lead_in_s", 0.0)), point)

    def _settle_writes(self) -> None:
        """Wait for the capture files written aside; a write that failed ends the cycle here."""
        while self._writes:
            which, job = self._writes.popitem()
            try:
                job.result()
            except Exception as exc:
                raise EolCalError(f"the {which} capture was not written to {self.run_dir / (which + '.mf4')}: "
                                  f"{type(exc).__name__}: {exc}") from exc

    def _last_block(self, role: str) -> FlashedBlock | None:
        return next((b for b in reversed(self.blocks) if b.role == role), None)

    def _open_flash_ahead(self) -> None:
        """The calibrated flash's first half (sessions, identification, the erase of an empty
        inactive bank) on a thread of its own while the fit computes the block
        (:mod:`eol_cal.station.flash_ahead`); closed by the flash or at the cycle's end."""
        from eol_cal.ecu.client import ClientTiming
        from eol_cal.station.flash_ahead import FlashAhead

        self._ahead = FlashAhead(self.cfg.open_bus, seed_to_key=self.cfg.seed_to_key,
                                 timing=self.cfg.ecu_timing or ClientTiming(), motor=self.cfg.motor)

    def _close_flash_ahead(self) -> None:
        if self._ahead is not None:
            self._ahead.close()

    def _flash(self, data: bytes, role: str, before_commit: Callable[[], None] | None = None,
               ahead: FlashAhead | None = None) -> None:
        """Flash a block of this run (read back as ``cfg.read_back`` says), on a session of its own
        or the one opened ``ahead``, and archive it as it went in."""
        from eol_cal.ecu.client import ClientTiming
        from eol_cal.station.archive import flash_archived

        path, source = self.run_dir / ARCHIVE_NAMES[role], f"{role} block of run {self.run_id[:8]}"
        try:
            if ahead is not None:
                _report, done = ahead.flash(data, role=role, path=path, source=source, before_commit=before_commit,
                                            read_back=self.cfg.read_back)
            else:
                _report, done = flash_archived(self.cfg.open_bus, data, role=role, path=path,
                                               seed_to_key=self.cfg.seed_to_key,
                                               timing=self.cfg.ecu_timing or ClientTiming(), motor=self.cfg.motor,
                                               source=source, before_commit=before_commit,
                                               read_back=self.cfg.read_back)
        except BaseException as exc:
            flashed = getattr(exc, "flashed_block", None)
            if flashed is not None:
                self.blocks.append(flashed)
            raise
        self.blocks.append(done)

    def _record_failure(self, exc: BaseException) -> None:
        failed_step = self.steps[-1].step if self.steps else "start"
        self.verdict = "error"
        self.reasons = [f"{failed_step}: {exc}" if str(exc) else f"{failed_step}: {type(exc).__name__}"]
        problems = getattr(exc, "problems", None)
        if problems:  # the pre-flight: each problem on its own
            self.reasons = [f"{failed_step}: {p.text}" for p in problems]
        self.error = ErrorInfo(failed_step, type(exc).__name__, str(exc),
                               None if isinstance(exc, EolCalError) else "".join(traceback.format_exception(exc, limit=8)))
        if not self.touched:
            if problems:
                self.refusal_codes = tuple(dict.fromkeys(p.code for p in problems))
            else:
                self.refusal_codes = ("interrupted",) if isinstance(exc, KeyboardInterrupt) else (
                    ("settings",) if isinstance(exc, InputError) else ("station_error",))
        if self.preflight is not None and self.preflight.dyno is None and failed_step == "pre-flight":
            self.safe_state = "not commanded: the pre-flight did not reach the dyno (nothing was started on it)"
        else:
            self.safe_state = safe_state(self.cfg.dyno)

    def _ecu_active(self, failure: BaseException | None) -> EcuActive:
        """Which block the ECU boots after this run.

        ``calibrated``: this run's block; ``uncompensated``: the prepare step's block (the cycle
        ended before the calibrated one was written: the motor runs without compensation, and a
        calibration it had before is superseded); ``unchanged``: nothing was written.
        """
        active = EcuActive("unchanged")
        for role, word in (("calibrated", "calibrated"), ("prepare", "uncompensated")):
            b = self._last_block(role)
            if b is not None and b.confirmed:
                active = EcuActive(word, b.sequence, b.bank)
                break
        boots = getattr(failure, "ecu_boots", None)
        if boots is not None and boots["boots"] != "previous":
            # the flash failed after the new block was complete and checked (a dead link, a
            # signal): the ECU boots it at its next reset
            what = "calibrated" if self.error is not None and self.error.step == "flash" else "uncompensated"
            active = EcuActive(what if boots["boots"] == "new" else f"{what} (if its CRC was written)",
                               boots["sequence"], boots["bank"])
        return active


def _uncalibrated(active: EcuActive, step: str, dyno: DynoConfig) -> str:
    """The record's reason for a motor left with the prepare step's uncompensated block (a dyno
    fault after prepare, a failed fit...): what the ECU runs, why, and how it is recovered."""
    return (f"motor not calibrated: the ECU boots the uncompensated block (sequence {active.sequence}, bank "
            f"{active.bank}) since the cycle ended at {step}; run the motor again (a latched dyno fault: eol-cal "
            f"dyno-clear --dyno {dyno.host}:{dyno.port} first), or bring back the block before it with eol-cal ecu "
            "restore --bank previous")


def _preload_analysis() -> None:
    """Import what each window's angle and figures need (scipy's interpolate, signal, ndimage and
    BLAS: heavy, so imported inside the functions) while the shaft ramps to the first segment,
    not at `eol-cal run`'s start nor when the first window is in."""
    import scipy.interpolate
    import scipy.linalg.blas
    import scipy.ndimage
    import scipy.signal  # noqa: F401


def _preload_writers() -> None:
    """Import what writes the captures (asammdf, pandas), the record (the database library) and
    the report while the dyno turns, not when the capture is in or the verdict is known."""
    import asammdf  # noqa: F401 - the MDF4 writer imports it where it writes (heavy): here, not beside the fit

    import eol_cal.capture.mdf4_io
    import eol_cal.station.report
    import eol_cal.records.spool  # noqa: F401


def run_motor(cfg: StationConfig, progress: ProgressFn | None = None,
              on_verdict: Callable[[RunRecord], None] | None = None) -> RunOutcome:
    """Run the whole cycle for one motor (:class:`StationCycle`); see :mod:`eol_cal.station.run`.

    ``on_verdict(record)`` shows the verdict as soon as it is known and safe in the spool, before
    the report and the database (:meth:`StationCycle.run`).

    Raises only :class:`InputError` for a configuration refused before anything ran (and
    :class:`~eol_cal.records.connect.RecordError` if neither database nor spool can take the
    record); every failure during the run is recorded (kind ``refusal`` before anything was
    written, else verdict ``error``).
    """
    cycle = StationCycle.start(cfg, progress)
    with emergency(cycle._dyno_safe_now):  # the watchdog's last resort if the main thread is stuck
        return cycle.run(on_verdict)
