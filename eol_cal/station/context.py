"""What one motor's cycle knows: the typed context every step of :mod:`eol_cal.station.steps`
reads and fills, and the instrument work of this run that several steps share (a traced
acquisition with its capture file written aside, a block flashed and archived, the calibrated
flash's first half opened ahead).

:func:`start_context` checks the configuration, makes the run directory and starts the helper
thread; :mod:`eol_cal.station.executor` runs the steps over the context and
:mod:`eol_cal.station.outcome` builds the record from it.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import functools
import uuid
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable

from eol_cal.analysis.point_metrics import PointRipple
from eol_cal import capture
from eol_cal.capture.ecu_state import check_trace
from eol_cal.dyno.profile_run import DEFAULT_CHANNELS
from eol_cal.dyno.setpoints import setpoints_from_profile
from eol_cal.errors import EolCalError
from eol_cal.firmware.settling import block_settle_s, lead_in_plan
from eol_cal.plant.profile import load_profile
from eol_cal.records.limits import LimitCheck, Measured
from eol_cal.records.record import (CaptureRef, EcuActive, ErrorInfo, FlashedBlock, GateInfo, PointFigures,
                                    PreflightResult, RestoredFrom, RippleMetrics, StationInfo, Step)
from eol_cal.station.acquisition import expect_block
from eol_cal.station.archive import keep_flashed
from eol_cal.station.instruments import Instruments, OpenFlash, bench_instruments
from eol_cal.station.run import ProgressFn, StationConfig, check_config, new_run_dir, sha256_file

if TYPE_CHECKING:
    from eol_cal.analysis.fit.motors import MotorsFit
    from eol_cal.capture.ecu_state import EcuState
    from eol_cal.analysis.motor_result import MotorResult
    from eol_cal.report.motor_page import FitExtra
    from eol_cal.capture.data import Capture
    from eol_cal.ecu.sequence import FlashReport
    from eol_cal.firmware.block import ParamBlock
    from eol_cal.records.spool import InFlight
    from eol_cal.station.early import EarlyWindows

#: the archive files of a run's directory, by the block's role
ARCHIVE_NAMES = {"prepare": "block_uncompensated.bin", "calibrated": "block.bin"}


@dataclass(frozen=True)
class StepVerdict:
    """A step's finding that ends the cycle early: ``fail`` and why (``pass``: the verdict step's)."""

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
class CycleContext:
    """One motor's cycle on the station: its configuration, and a field for what each step produced."""

    cfg: StationConfig
    run_id: str
    started: dt.datetime
    run_dir: Path
    profile_name: str
    segments: list
    station: StationInfo
    limits_sha256: str | None
    instruments: Instruments  # the dyno and the ECU the steps call (eol_cal.station.instruments)
    # what the steps produced
    steps: list[Step] = field(default_factory=list)
    preflight: PreflightResult | None = None
    touched: bool = False  # the prepare step began: from here the run is a measured attempt
    captures: dict[str, CaptureRef] = field(default_factory=dict)
    blocks: list[FlashedBlock] = field(default_factory=list)
    before: Capture | None = None
    fitted: MotorsFit | None = None
    result: MotorResult | None = None
    fit_extra: FitExtra | None = None
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
    failure: BaseException | None = None  # what ended the cycle (None: its steps ran to their verdict)
    safe_state: str | None = None
    ecu_active: EcuActive | None = None
    report_html: Path | None = None
    report_error: str | None = None
    ended_at: str | None = None
    gate: Any = None  # the master gate in force (eol_cal.msa.gate.Gate), None: none
    gate_info: GateInfo | None = None  # the record's gate: rules, and the master run that admitted the run
    # work on the helper thread
    helper: ThreadPoolExecutor | None = None
    prewarm: Future | None = None
    early: EarlyWindows | None = None
    verify: EarlyWindows | None = None
    writes: dict[str, Future] = field(default_factory=dict)  # capture files being written aside
    held: dict[str, Callable[[], None]] = field(default_factory=dict)  # writes :meth:`start_writes` starts
    ahead: OpenFlash | None = None  # the calibrated flash's first half, opened during the fit
    pr_before: Future | None = None
    journal: Path | None = None  # the record at the verdict, in the spool until the database has it
    journal_held: InFlight | None = None  # a flush leaves the journal alone while this is held

    @property
    def serial(self) -> str:
        return self.cfg.serial

    @property
    def kind(self) -> str:
        """``refusal`` when the cycle ended before the prepare step, else the configuration's kind."""
        return self.cfg.kind if self.touched else "refusal"

    # ------------------------------------------------------------------ acquisition
    def acquire(self, which: str, segs: list, on_window: Callable | None = None, hold_write: bool = False,
                flash_after: bool = False) -> Capture:
        """One acquisition with the ECU's state before and after (in the capture and the record);
        the ECU must have run the block this cycle flashed, unchanged, all along. ``on_window``:
        the dyno client's hook for each window as it is read. ``hold_write``: the capture file is
        written on a thread of its own from :meth:`start_writes` on (the calibrated flash's
        download: the writer's ~0.1 CPU s competes neither with the fit nor with the flash's first
        half), not before this returns; :meth:`settle_writes` waits for it (the flash does, before
        the block's CRC makes it count, and the verdict). The flash before reset the ECU: the shaft
        turns for its settling first (the lead-in, ``cfg.lead_in``). ``flash_after``: the calibrated
        flash's first half opens as the last window is in, its first requests the ECU's state after
        it (:meth:`open_flash_ahead`)."""
        path = self.run_dir / f"{which}.mf4"
        booted = self.uncompensated if which == "before" else self.calibrated
        speed, lead_point, lead_in_s = float(segs[0].speed_rpm), None, 0.0
        if self.cfg.lead_in == "at-point":
            lead_in_s = block_settle_s(booted, speed)
        elif self.cfg.lead_in == "settle":
            point_rpm, point_s, lead_in_s = lead_in_plan(booted, speed)
            if point_rpm is not None:
                lead_point = dataclasses.replace(segs[0], speed_rpm=point_rpm, seconds=point_s)
        # the calibration capture carries the ECU's measured q current where the dyno has it: the fit
        # takes kt * iq as known torque, so the current loop's own ripple is not read as the motor's k6
        channels = DEFAULT_CHANNELS + (("iq",) if which == "before" and "iq" in self.instruments.channels else ())
        cap, trace = self.instruments.acquire(segs, serial=self.cfg.serial, rate_hz=self.cfg.rate_hz, channels=channels,
                                              comment=f"eol-cal run {self.run_id}: {which}, profile {self.profile_name}",
                                              on_window=on_window, lead_in_s=lead_in_s, lead_in_point=lead_point,
                                              read_after=self._flash_ahead_traced if flash_after else None)
        if hold_write:
            self.held[which] = functools.partial(self.store, which, cap, trace, path, len(segs))
        else:
            self.store(which, cap, trace, path, len(segs))
        # a capture whose ECU state is not the expected one is kept all the same (its file and record)
        expect_block(trace, which, self.last_block("prepare" if which == "before" else "calibrated"))
        if which == "before":
            check_trace(trace, str(path))  # the calibration capture: never under compensation
        return cap

    def store(self, which: str, cap: Capture, trace: Any, path: Path, n_segments: int) -> None:
        """Write a capture file (atomically) and keep its reference for the record."""
        capture.write_capture(cap, path)
        point = ((float(cap.metadata["lead_in_point_rpm"]), float(cap.metadata["lead_in_point_s"]))
                 if "lead_in_point_rpm" in cap.metadata else None)
        self.captures[which] = CaptureRef(str(path), sha256_file(path), int(len(cap.t)), n_segments, trace.before,
                                          trace.after, float(cap.metadata.get("lead_in_s", 0.0)), point)

    def start_writes(self) -> None:
        """Start writing the capture files held (:meth:`acquire`), each on a thread of its own."""
        while self.held:
            which, job = self.held.popitem()
            writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="capture-writer")
            self.writes[which] = writer.submit(job)
            writer.shutdown(wait=False)

    def settle_writes(self) -> None:
        """Wait for the capture files written aside (those still held are started first); a write
        that failed ends the cycle here."""
        self.start_writes()
        while self.writes:
            which, job = self.writes.popitem()
            try:
                job.result()
            except Exception as exc:
                raise EolCalError(f"the {which} capture was not written to {self.run_dir / (which + '.mf4')}: "
                                  f"{type(exc).__name__}: {exc}") from exc

    # ------------------------------------------------------------------ flashing
    def last_block(self, role: str) -> FlashedBlock | None:
        return next((b for b in reversed(self.blocks) if b.role == role), None)

    def open_flash_ahead(self) -> None:
        """The calibrated flash's first half (sessions, identification, the erase of an empty
        inactive bank) on a thread of its own while the fit computes the block
        (:mod:`eol_cal.station.flash_ahead`), unless the calibration capture opened it already;
        closed by the flash or at the cycle's end."""
        if self.ahead is None:
            self.ahead = self.instruments.flash_ahead()

    def _flash_ahead_traced(self) -> Future[EcuState]:
        # the acquisition's read after its last window (acquire(flash_after=True))
        self.ahead = self.instruments.flash_ahead(traced=True)
        assert self.ahead.state is not None
        return self.ahead.state

    def close_flash_ahead(self) -> None:
        if self.ahead is not None:
            self.ahead.close()

    def flash(self, data: bytes, role: str, before_commit: Callable[[], None] | None = None,
              ahead: OpenFlash | None = None, writes_from: str | None = None) -> None:
        """Flash a block of this run (read back as ``cfg.read_back`` says), on a session of its own
        or the one opened ``ahead``, and archive it as it went in. ``writes_from``: the step of the
        flash ahead (:class:`~eol_cal.ecu.aftermath.FlashProgress`'s names, ``download``) from which
        the capture files held (:meth:`acquire`) are written; without a flash ahead, at once."""
        path, source = self.run_dir / ARCHIVE_NAMES[role], f"{role} block of run {self.run_id[:8]}"
        if ahead is None:
            if writes_from is not None:
                self.start_writes()
            keep_flashed(self.blocks, lambda: self.instruments.flash(
                data, role=role, path=path, source=source, before_commit=before_commit, read_back=self.cfg.read_back))
            return

        def step(name: str) -> None:
            if name == writes_from:
                self.start_writes()

        keep_flashed(self.blocks, lambda: ahead.flash(data, role=role, path=path, source=source, progress=step,
                                                      before_commit=before_commit, read_back=self.cfg.read_back))


@dataclass
class RestoreContext:
    """One ``ecu restore`` run (:func:`eol_cal.station.restore.restore_run`): an earlier block flashed
    again as a new sequence, archived in the run's directory, recorded as a run of kind ``restore``."""

    serial: str
    run_id: str
    started: dt.datetime
    run_dir: Path
    data: bytes  # the block's image, as it goes into the ECU
    source: str
    open_bus: Callable[[], Any]
    seed_to_key: Callable[[bytes], bytes]
    timing: Any
    motor: Any
    restored_from: RestoredFrom
    station: StationInfo
    progress: Callable[[str], None] | None = None
    steps: list[Step] = field(default_factory=list)
    blocks: list[FlashedBlock] = field(default_factory=list)
    report: FlashReport | None = None
    failure: BaseException | None = None


def start_context(cfg: StationConfig, instruments: Instruments | None = None, run_id: str | None = None
                  ) -> CycleContext:
    """Check the configuration, make the run directory, start the helper thread. ``instruments``:
    the dyno and ECU the steps call (default the configuration's, :func:`bench_instruments`);
    ``run_id``: the run's id when the caller names it (a what-if lot's motor), else a new one."""
    check_config(cfg)
    profile = load_profile(cfg.profile)
    segments = setpoints_from_profile(profile)
    started = dt.datetime.now(dt.UTC)
    run_id = uuid.uuid4().hex if run_id is None else run_id
    sha = sha256_file(cfg.limits.source) if Path(cfg.limits.source).is_file() else None
    ctx = CycleContext(cfg=cfg, run_id=run_id, started=started,
                       run_dir=new_run_dir(cfg.report_dir, cfg.serial, started, run_id), profile_name=profile.name,
                       segments=segments, station=station_info(cfg, profile.name), limits_sha256=sha,
                       instruments=bench_instruments(cfg) if instruments is None else instruments)
    # One helper thread: while the dyno spins the first time it imports JAX and matplotlib,
    # traces the fit's solver and works on each window as it arrives; while it spins the second
    # time it measures the calibration capture at the operating point (the main thread mostly
    # waits on the dyno there).
    ctx.helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="eol-cal-run")
    return ctx


__all__ = ["ARCHIVE_NAMES", "CycleContext", "ProgressFn", "RestoreContext", "StepVerdict", "now_iso", "point_figures",
           "start_context", "station_info"]
