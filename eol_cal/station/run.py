"""The end-of-line cycle for one motor.

prepare ECU (flash the uncompensated block: field estimator, no compensation) -> acquire (dyno,
profile) -> fit -> table (lead auto) -> flash (ECU, key) -> acquire with the compensation the
ECU now runs -> metrics -> verdict against the variant's limits -> report + record. The first
flash makes the calibration capture independent of what the ECU ran before: a blank ECU would
run the raw encoder angle (k6 about 1.7 % low and twice the scatter on the plant lot), and a
motor being re-tested would be measured through its old compensation, whose residual would then
become its new table. Every step is timed. A fit that is not usable, or a motor whose k6 or fit quality is out
of limits, fails right after the fit (nothing is flashed). Any error ends the cycle with verdict
``error``: the dyno client has already put the drive in the safe state (speed 0, disabled); the
cycle commands it once more, best effort, and the record is written all the same.

Exit codes (:attr:`RunOutcome.exit_code`): 0 pass, 1 fail, 2 error.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import math
import time
import traceback
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from eol_cal.jsonsafe import json_safe
from eol_cal.errors import EolCalError, InputError
from eol_cal.interrupts import shielded
from eol_cal.mechanics import BenchMechanics, load_mechanics
from eol_cal.motor import MotorParams, load_motor
from eol_cal.station.limits import Measured, VariantLimits, fit_reasons, verdict
from eol_cal.station.records import RECORD_SCHEMA, SaveResult, save_record

if TYPE_CHECKING:
    from eol_cal.analysis.angle import AngleResult
    from eol_cal.capture.model import Capture

EXIT = {"pass": 0, "fail": 1, "error": 2}
STEPS = ("prepare ECU", "acquire", "fit", "table", "flash", "acquire compensated", "metrics", "report", "record")

ProgressFn = Callable[[str, str], None]  # (step, "start" | "done" | "failed" | "skipped")


@dataclass
class StationConfig:
    """Everything one cycle needs.

    Attributes
    ----------
    serial : str
        Motor serial (goes into the captures, the block and the record; the ECU must report it).
    dyno : DynoConfig
        Dyno address and timing (:mod:`eol_cal.dyno.client`).
    open_bus : callable
        Opens the tester's CAN bus (python-can); closed after the flash.
    seed_to_key : callable
        Security access algorithm (seed bytes -> key bytes).
    limits : VariantLimits
        The product variant's limits.
    db : path
        SQLite database of run records.
    report_dir : path
        Each run gets its own directory below it: captures, fit, block, plots, report.
    profile : str
        Built-in profile name or TOML file (:func:`eol_cal.plant.profile.load_profile`).
    verify : {"point", "full"}
        The compensated acquisition: ``point`` runs only the profile's segments at the
        operating point (both directions where the profile has them), ``full`` the whole
        profile again.
    spool_dir : path or None
        Where records go when the database cannot be written (default
        :func:`eol_cal.station.records.default_spool_dir`).
    rate_hz : int
        Capture sample rate (Hz).
    db_timeout_s : float
        How long a database write waits for a lock (s) before spooling.
    station : dict
        Free-form description of the station for the record (addresses, interface).
    ecu_timing : ClientTiming or None
        UDS timing (default the contract's).
    prepare : callable or None
        Called first on the helper thread while the dyno spins, e.g. to switch on JAX's
        persistent compilation cache (importing JAX costs a second).
    motor : MotorParams
        The motor type on the station (default the paper preset): poles and encoder the
        captures must show, the ECU's tick rate and kt for the blocks, the current loop for the
        lead, rotor inertia for the bench response.
    mechanics : BenchMechanics or None
        The dyno bench whose response the fit divides out (default the built-in ``paper``
        bench, which ``eol-cal dyno-sim`` simulates); ``None``: rigid coupling.
    """

    serial: str
    dyno: Any
    open_bus: Callable[[], Any]
    seed_to_key: Callable[[bytes], bytes]
    limits: VariantLimits
    db: "Path | str"
    report_dir: Path
    profile: str = "eol-default"
    verify: str = "point"
    spool_dir: Path | None = None
    rate_hz: int = 10000
    db_timeout_s: float = 5.0
    station: dict[str, Any] = field(default_factory=dict)
    ecu_timing: Any = None
    prepare: Callable[[], None] | None = None
    motor: MotorParams = field(default_factory=lambda: load_motor("paper"))
    mechanics: BenchMechanics | None = field(default_factory=lambda: load_mechanics("paper"))


@dataclass
class RunOutcome:
    """What :func:`run_motor` returns: the record, where it went, and the exit code."""

    record: dict[str, Any]
    saved: SaveResult | None
    report_html: Path | None
    exit_code: int

    @property
    def verdict(self) -> str:
        return self.record["verdict"]


class _Skip(Exception):
    """Ends the cycle early with a ``fail`` verdict (the reasons are already recorded)."""


def sha256_file(path: str | Path) -> str:
    """SHA-256 of a file's bytes, hex."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _safe_name(text: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in text)


# --------------------------------------------------------------------------- fit
def fit_motor(capture: Capture, limits: VariantLimits, tool_version: str, motor: MotorParams | None = None,
              mechanics: BenchMechanics | None = None) -> tuple[dict, dict, Any]:
    """The ripple fit of one motor's capture: :func:`eol_cal.analysis.fit_motors.fit_motors`, as
    ``eol-cal fit`` runs it (windows fitted jointly, phases in the firmware frame).

    ``motor`` (default the paper preset) and ``mechanics`` (``None``: rigid coupling) as in
    :class:`eol_cal.analysis.fit_motors.FitOptions`.

    Returns
    -------
    doc, record, extra
        The result document (schema ``eol-cal/fit-result/1``), its one motor record, and
        ``(MotorInput, MotorFit, FitSpec)`` for the plots.
    """
    from eol_cal.analysis.fit_motors import FitOptions, fit_motors

    options = FitOptions(limits=limits.ci_limits(), batch="loop", mechanics=mechanics, motor=motor)
    res = fit_motors([capture], options, tool_version)
    (rec,) = res.records
    return res.doc, rec, (res.inputs[0], res.fits[0], options.spec)


def check_motor(capture: Capture, motor: MotorParams) -> None:
    """Refuse a capture whose poles or encoder are not the station's motor type (InputError).

    The blocks the station flashes carry the motor type's poles, encoder and tick rate; a
    capture of another motor would be fitted and flashed with the wrong ones.
    """
    for key, want in (("poles", motor.poles), ("encoder_ppr", motor.N_enc)):
        got = int(capture.metadata[key])
        if got != want:
            raise InputError(capture.source, key, f"the capture says {got}, the station's motor type "
                             f"{motor.name!r} has {want}: wrong motor on the dyno, or the station is set up for another motor type")


def _previous(report) -> dict[str, Any]:
    """What the ECU held before a flash (bank None: no valid bank), for the record."""
    return {"bank": report.previous.bank if report.previous.has_bank else None, "sequence": report.previous.sequence}


def measured_from_fit(rec: dict[str, Any]) -> Measured:
    """The fit's part of :class:`Measured` from a usable motor record (units as in the record)."""
    k6, c6, pc6 = rec["k6"], rec["c6"], rec["phase_c6"]
    ci_c6 = max(c6["ci95"], abs(c6["value"]) * pc6["ci95"])
    hall = rec.get("hall_angle") or {"source": "not in the record", "deviation_deg": []}
    measured = hall["source"] == "measured"
    return Measured(
        k6=abs(float(k6["value"])), ci_k6=float(k6["ci95"]), ci_phase_k6_deg=math.degrees(rec["phase_k6"]["ci95"]),
        ci_c6_nm=float(ci_c6), r2=float(rec["fit"]["r2"]), rms_nm=float(rec["fit"]["rms"]),
        hall_deviation_deg=max(abs(float(d)) for d in hall["deviation_deg"]) if measured else math.nan,
        hall_source=str(hall["source"]),
    )


# --------------------------------------------------------------------------- metrics
@dataclass(frozen=True)
class PointRipple:
    """Ripple of one capture at the operating point.

    Attributes
    ----------
    pp_pct : float
        Filtered p-p ripple (%), median over the steady windows (``docs/metrics.md``).
    pp_raw_pct : float
        Despiked, unfiltered p-p ripple (%).
    pp_nm : float
        Filtered p-p (N*m).
    T_avg_nm : float
        Mean torque (N*m).
    amp6_nm : float
        6th-order amplitude of the order spectrum (N*m).
    span_s : (float, float)
        The capture's time span that was analysed (s).
    pp_no_mech1_pct : float
        ``pp_pct`` with the mechanical order 1 taken out (%): what the tables can act on.
    """

    pp_pct: float
    pp_raw_pct: float
    pp_nm: float
    T_avg_nm: float
    amp6_nm: float
    span_s: tuple[float, float]
    ripple: Any = None
    spectrum: Any = None
    t: Any = None
    torque: Any = None
    poles: int = 0
    pp_no_mech1_pct: float = float("nan")
    theta_r: Any = None  # electrical angle per sample (rad), for the report's torque against angle

    def to_dict(self) -> dict[str, Any]:
        return json_safe({"pp_pct": self.pp_pct, "pp_raw_pct": self.pp_raw_pct, "pp_nm": self.pp_nm,
                           "pp_no_mech1_pct": self.pp_no_mech1_pct,
                           "T_avg_nm": self.T_avg_nm, "amp6_nm": self.amp6_nm, "span_s": list(self.span_s)})


def nearest_segment(pieces: list, speed_rpm: float, i_qo_a: float) -> int:
    """Index of the piece whose mean speed (rpm) and i_qo (A) are nearest the operating point."""
    def distance(c) -> float:
        iq = float(np.mean(c.iq_ref()))
        rpm = float(np.mean(c["speed"])) if c.has("speed") else speed_rpm
        return abs(iq - i_qo_a) / max(abs(i_qo_a), 1.0) + abs(rpm - speed_rpm) / max(abs(speed_rpm), 1.0)

    return min(range(len(pieces)), key=lambda k: distance(pieces[k]))


def point_ripple(capture: Capture, angle: AngleResult) -> PointRipple:
    """p-p ripple and 6th-order amplitude of one steady capture (the operating point's window).

    Parameters
    ----------
    capture : Capture
        One window of a dyno capture (:func:`eol_cal.capture.windows.split_windows`).
    angle : AngleResult
        Its reconstructed angle.
    """
    from eol_cal.analysis.metrics import ripple_pp
    from eol_cal.analysis.spectrum import order_spectrum

    t, torque, theta = capture.t, np.asarray(capture["torque"], float), angle.theta_r
    rp = ripple_pp(t, torque, theta, poles=capture.poles, i_qo=np.asarray(capture.iq_ref(), float),
                   source=capture.source)
    sp = order_spectrum(theta, torque, capture.poles, t=t, source=capture.source)
    return PointRipple(rp.filtered_pct, rp.raw_pct, rp.filtered_pp_nm, rp.T_avg_nm, float(sp.amplitude(6)),
                       (float(t[0]), float(t[-1])), rp, sp, t, torque, capture.poles,
                       pp_no_mech1_pct=rp.no_mech1_pct, theta_r=theta)


def verify_segments(segments: list, speed_rpm: float, i_qo_a: float, rel_tol: float = 0.02) -> list:
    """The profile segments at the operating point, in either direction.

    Parameters
    ----------
    segments : list of DynoSetpoint
        The test profile as the dyno runs it.
    speed_rpm, i_qo_a : float
        Operating point: speed (rpm) and nominal q current (A); matched by magnitude within
        ``rel_tol``, so the reverse point of the same magnitude is verified too.

    Returns
    -------
    list of DynoSetpoint
        In profile order; the whole profile when no segment gives the load as i_qo or none matches.
    """
    def near(a: float, b: float) -> bool:
        return abs(abs(a) - abs(b)) <= rel_tol * max(abs(b), 1e-9)

    out = [s for s in segments if s.iq is not None and near(s.speed_rpm, speed_rpm) and near(s.iq, i_qo_a)]
    return out or list(segments)


# --------------------------------------------------------------------------- the cycle
def _new_run_dir(report_dir: Path, serial: str, started: _dt.datetime, run_id: str) -> Path:
    stamp = started.strftime("%Y%m%dT%H%M%SZ")
    d = report_dir / f"{_safe_name(serial)}_{stamp}_{run_id[:8]}"
    d.mkdir(parents=True, exist_ok=False)
    return d


def check_config(cfg: StationConfig) -> None:
    """Refuse what can be known bad before the dyno turns (no record: nothing was run)."""
    if not cfg.serial or len(cfg.serial.encode("ascii", "replace")) > 16 or not cfg.serial.isascii():
        raise InputError(None, "serial", f"{cfg.serial!r}: 1 to 16 ASCII characters (the block's serial field)")
    try:
        cfg.report_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(str(cfg.report_dir), "report-dir", f"cannot create: {exc}") from None


def run_motor(cfg: StationConfig, progress: ProgressFn | None = None) -> RunOutcome:
    """Run the whole cycle for one motor; see the module doc.

    Raises only :class:`InputError` for a configuration refused before anything ran (and
    :class:`~eol_cal.station.records.RecordError` if neither database nor spool can take the
    record); every failure during the run is recorded with verdict ``error``.
    """
    from eol_cal import __version__
    from eol_cal.dyno import client as dc
    from eol_cal.firmware.block import LAYOUT_VERSION
    from eol_cal.plant.profile import load_profile

    check_config(cfg)
    profile = load_profile(cfg.profile)
    segments = dc.setpoints_from_profile(profile)
    started = _dt.datetime.now(_dt.timezone.utc)
    run_id = uuid.uuid4().hex
    run_dir = _new_run_dir(cfg.report_dir, cfg.serial, started, run_id)
    rec: dict[str, Any] = {
        "schema": RECORD_SCHEMA, "run_id": run_id, "serial": cfg.serial,
        "started_at": started.isoformat(timespec="milliseconds"), "ended_at": None,
        "verdict": "error", "reasons": [], "error": None,
        "tool_version": __version__, "layout_version": LAYOUT_VERSION,
        "station": dict(cfg.station, profile=profile.name, verify=cfg.verify, rate_hz=cfg.rate_hz,
                        motor=cfg.motor.name, bench=cfg.mechanics.name if cfg.mechanics is not None else "rigid"),
        "limits": cfg.limits.to_dict(), "steps": [], "captures": {}, "fit": None, "block": None,
        "flash": None, "ecu_prepared": None, "metrics": {}, "report_dir": str(run_dir), "safe_state": None,
    }
    if Path(cfg.limits.source).is_file():
        rec["limits"]["sha256"] = sha256_file(cfg.limits.source)
    state: dict[str, Any] = {}
    # One helper thread: it imports JAX and matplotlib while the dyno spins the first time, and
    # draws the fit's plots while it spins the second time (the main thread mostly waits there).
    helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="eol-cal-run")
    state["prewarm"] = helper.submit(_prewarm, len(segments), cfg.prepare)

    def step(name: str, fn: Callable[[], Any]) -> Any:
        if progress:
            progress(name, "start")
        t0 = time.perf_counter()
        entry = {"step": name, "seconds": None, "ok": False}
        rec["steps"].append(entry)
        try:
            out = fn()
        except _Skip:
            entry["seconds"] = round(time.perf_counter() - t0, 4)
            entry["ok"] = True
            if progress:
                progress(name, "done")
            raise
        except BaseException:
            entry["seconds"] = round(time.perf_counter() - t0, 4)
            if progress:
                progress(name, "failed")
            raise
        entry["seconds"] = round(time.perf_counter() - t0, 4)
        entry["ok"] = True
        if progress:
            progress(name, "done")
        return out

    def acquire(which: str, segs: list) -> Any:
        path = run_dir / f"{which}.mf4"
        cap = dc.acquire(cfg.dyno, segs, path, serial=cfg.serial, rate_hz=cfg.rate_hz,
                         extra_metadata={"comment": f"eol-cal run {run_id}: {which}, profile {profile.name}"})
        rec["captures"][which] = {"path": str(path), "sha256": sha256_file(path), "samples": int(len(cap.t)),
                                  "segments": len(segs)}
        return cap

    def acquire_compensated() -> Any:
        op = rec["fit"]["operating_point"]
        segs = segments if cfg.verify == "full" else verify_segments(segments, op["speed_rpm"], op["i_qo_a"])
        # the before-capture's figures are computed meanwhile on the helper thread
        mi = state["fit_extra"][0]
        k = nearest_segment(mi.captures, op["speed_rpm"], op["i_qo_a"])
        state["pr_before"] = helper.submit(point_ripple, mi.captures[k], mi.angles[k])
        return acquire("after", segs)

    def do_fit() -> None:
        # never two fits at once: JAX tracing, the compilation cache and the fit's solver cache
        # are shared by the threads, and a cold start compiles the same solver in both
        check_motor(state["before"], cfg.motor)
        state["prewarm"].result()
        doc, frec, extra = fit_motor(state["before"], cfg.limits, __version__, cfg.motor, cfg.mechanics)
        from eol_cal.analysis.result import write_result

        write_result(doc, run_dir / "fit.json")
        rec["fit"] = frec
        state["fit_doc"], state["fit_extra"] = doc, extra
        from eol_cal.station.report import fit_plots

        state["fit_plots"] = helper.submit(fit_plots, run_dir, extra)
        if frec["status"] != "ok":
            rec["verdict"] = "fail"
            rec["reasons"] = [f"fit {frec['status']}: {r}" for r in frec["reasons"]] or [f"fit {frec['status']}"]
            raise _Skip
        m = measured_from_fit(frec)
        state["measured"] = m
        reasons = fit_reasons(m, cfg.limits)
        if reasons:
            rec["verdict"], rec["reasons"] = "fail", reasons
            raise _Skip

    def do_table() -> None:
        from eol_cal.analysis.fit_table import block_from_record, created_unix
        from eol_cal.atomic import atomic_path
        from eol_cal.firmware.block import flag_names, pack

        blk = block_from_record(rec["fit"], cfg.motor, calibrated_at=created_unix(state["fit_doc"]),
                                source=str(run_dir / "fit.json"))
        data = pack(blk)
        path = run_dir / "block.bin"
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
        state["block"] = data
        rec["block"] = {"path": str(path), "bytes": len(data), "table_len": blk.table_len,
                        "lead_s": blk.lead_s, "iqc_limit": blk.iqc_limit, "flags": flag_names(blk.flags),
                        "crc32": None, "sequence": None}

    def flash(data: bytes, source: str):
        from eol_cal.ecu.client import ClientTiming, flash_block

        bus = cfg.open_bus()
        try:
            return flash_block(bus, data, seed_to_key=cfg.seed_to_key, verify=True, source=source,
                               timing=cfg.ecu_timing or ClientTiming())
        finally:
            bus.shutdown()

    def do_prepare() -> None:
        from eol_cal.analysis.fit_table import uncompensated_block
        from eol_cal.atomic import atomic_path
        from eol_cal.firmware.block import flag_names, pack

        blk = uncompensated_block(cfg.serial, cfg.motor)
        data = pack(blk)
        path = run_dir / "block_uncompensated.bin"
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
        report = flash(data, str(path))
        rec["ecu_prepared"] = {"path": str(path), "flags": flag_names(blk.flags), "crc32": f"{report.crc32:08x}",
                               "sequence": report.sequence, "bank": report.bank, "verified": report.verified,
                               "previous": _previous(report)}

    def do_flash() -> None:
        report = flash(state["block"], rec["block"]["path"])
        rec["block"].update(crc32=f"{report.crc32:08x}", sequence=report.sequence, bank=report.bank)
        rec["flash"] = {"seconds": round(report.seconds, 4), "verified": report.verified,
                        "transfer_blocks": report.transfer_blocks, "retries": report.retries,
                        "previous": _previous(report)}

    def do_metrics() -> None:
        from eol_cal.analysis.angle import capture_angle

        op = rec["fit"]["operating_point"]
        before = state["pr_before"].result()
        from eol_cal.capture.windows import split_windows

        pieces = split_windows(state["after"])
        after_cap = pieces[nearest_segment(pieces, op["speed_rpm"], op["i_qo_a"])]
        after = point_ripple(after_cap, capture_angle(after_cap))
        state["pr"] = (before, after)
        m = state["measured"]
        m = Measured(**{**m.__dict__, "pp_before_pct": before.pp_pct, "pp_after_pct": after.pp_pct})
        rec["metrics"] = json_safe({
            "operating_point": op, "pp_before_pct": m.pp_before_pct, "pp_after_pct": m.pp_after_pct,
            "improvement_pct": m.improvement_pct, "pp_after_no_mech1_pct": after.pp_no_mech1_pct,
            "before": before.to_dict(), "after": after.to_dict(),
            "definition": "filtered p-p % (docs/metrics.md), median over the steady windows of the operating "
                          "point's segment",
        })
        rec["verdict"], rec["reasons"] = verdict(m, cfg.limits)

    failure: BaseException | None = None
    try:
        try:
            step("prepare ECU", do_prepare)
            state["before"] = step("acquire", lambda: acquire("before", segments))
            step("fit", do_fit)
            step("table", do_table)
            step("flash", do_flash)
            state["after"] = step("acquire compensated", acquire_compensated)
            step("metrics", do_metrics)
        except _Skip:
            pass
    except BaseException as exc:  # noqa: BLE001 - every failure becomes an error record
        failure = exc
    # From here on a signal waits until the record is written (eol_cal.interrupts).
    with shielded():
        if failure is not None:
            exc = failure
            failed = rec["steps"][-1]["step"] if rec["steps"] else "start"
            rec["verdict"] = "error"
            rec["reasons"] = [f"{failed}: {exc}" if str(exc) else f"{failed}: {type(exc).__name__}"]
            rec["error"] = {"step": failed, "type": type(exc).__name__, "message": str(exc),
                            "traceback": None if isinstance(exc, EolCalError)
                            else "".join(traceback.format_exception(exc, limit=8))}
            rec["safe_state"] = _safe_state(cfg.dyno)
            if not isinstance(exc, Exception):  # Ctrl-C: record first, then let it end the process
                state["reraise"] = exc
        rec["ecu_active"] = ecu_active(rec)
        boots = getattr(failure, "ecu_boots", None)
        if boots is not None and boots["boots"] != "previous":
            # the flash failed after the new block was complete and checked (a dead link, a
            # signal): the ECU boots it at its next reset
            what = "calibrated" if rec["error"]["step"] == "flash" else "uncompensated"
            rec["ecu_active"] = {"block": what if boots["boots"] == "new" else f"{what} (if its CRC was written)",
                                 "sequence": boots["sequence"], "bank": boots["bank"]}
        report_html = None
        try:
            report_html = step("report", lambda: _report(rec, run_dir, state))
        except Exception as exc:  # noqa: BLE001 - the record must still be written
            rec["steps"][-1]["error"] = f"{type(exc).__name__}: {exc}"
            rec["report_error"] = f"{type(exc).__name__}: {exc}"
            if rec["verdict"] != "error":
                rec["verdict"] = "error"
                rec["reasons"] = rec["reasons"] + [f"report: {exc}"]
        rec["ended_at"] = _now()
        helper.shutdown(wait=True)
        rec = json_safe(rec)
        try:
            from eol_cal.station.report import write_record_json

            write_record_json(rec, run_dir)
        except Exception as exc:  # noqa: BLE001 - the database still gets it
            rec["report_error"] = f"report.json: {type(exc).__name__}: {exc}"
        saved = _save(cfg, rec, progress)
    if "reraise" in state:
        raise state["reraise"]
    return RunOutcome(rec, saved, report_html, EXIT[rec["verdict"]])


def ecu_active(rec: dict[str, Any]) -> dict[str, Any]:
    """Which block the ECU boots after this run, from what the run flashed (for the record).

    ``calibrated``: this run's block; ``uncompensated``: the prepare step's block (the cycle
    ended before the calibrated one was written: the motor runs without compensation, and a
    calibration it had before is superseded); ``unchanged``: nothing was written.
    """
    for key, what in (("block", "calibrated"), ("ecu_prepared", "uncompensated")):
        done = rec.get(key) or {}
        if done.get("sequence") is not None:
            return {"block": what, "sequence": done["sequence"], "bank": done.get("bank")}
    return {"block": "unchanged", "sequence": None, "bank": None}


def _save(cfg: StationConfig, rec: dict[str, Any], progress: ProgressFn | None) -> SaveResult:
    if progress:
        progress("record", "start")
    saved = save_record(rec, cfg.db, cfg.spool_dir, cfg.db_timeout_s)
    if progress:
        progress("record", "done")
    return saved


def _safe_state(dyno_cfg: Any) -> str:
    """Command the dyno's safe state once more (best effort); say whether it was confirmed."""
    from eol_cal.dyno.client import DynoClient

    client = DynoClient(dyno_cfg)
    try:
        why = client.safe_state()
    except Exception as exc:  # noqa: BLE001
        why = str(exc)
    finally:
        client.close()
    return "speed 0, drive disabled (confirmed)" if why is None else f"not confirmed: {why}"


def _report(rec: dict[str, Any], run_dir: Path, state: dict[str, Any]) -> Path:
    from eol_cal.station.report import write_report

    figures = state["fit_plots"].result() if "fit_plots" in state else []
    return write_report(rec, run_dir, figures=figures, fit_extra=state.get("fit_extra"), point_ripple=state.get("pr"))


def _prewarm(n_segments: int, prepare: Callable[[], None] | None = None) -> None:
    """Import what the fit and the plots need, and trace the fit's solver for ``n_segments``
    segments on an analytic record (JAX traces per shape; tracing costs seconds even when the
    compiled code comes from the persistent cache). Runs while the dyno spins."""
    try:
        if prepare is not None:
            prepare()
        import dataclasses

        import numpy as np

        from eol_cal.analysis.fit import FitSpec, fit_many
        from eol_cal.analysis.fit_synth import synthetic_segments
        import eol_cal.analysis.fit_capture  # noqa: F401
        import eol_cal.analysis.fit_plot  # noqa: F401
        from eol_cal.analysis.plots import _pyplot

        _pyplot()
        loads = tuple(20.0 + 10.0 * k for k in range(max(2, (n_segments + 3) // 4)))
        seg, _truth = synthetic_segments(np.random.default_rng(0), loads_a=loads, speeds_rpm=(60.0, 120.0),
                                         directions=(1, -1), seg_s=0.1, fs_hz=10000.0)
        if len(seg.theta) > n_segments:
            keep = slice(0, n_segments)
            seg = dataclasses.replace(seg, **{f.name: getattr(seg, f.name)[keep] for f in dataclasses.fields(seg)
                                              if isinstance(getattr(seg, f.name), (list, np.ndarray))})
        fit_many([seg], FitSpec(), mode="loop")
    except Exception:  # noqa: BLE001 - the step that needs it reports a real failure
        pass
