"""The one place a station run's record is built: from whatever its steps left in the
:class:`~eol_cal.station.context.CycleContext` (:func:`to_record`), the failure that ended it
turned into the record's error, refusal codes and safe state, and which block the ECU boots
afterwards; an ``ecu restore`` run's (:func:`restore_record`) beside it. A what-if lot's motor
runs the cycle itself (:mod:`eol_cal.station.whatif`): its record is :func:`to_record`'s.

Kind ``refusal`` when the cycle ended before the prepare step (nothing written to the ECU,
nothing measured), else the configuration's kind (``production`` on a line). Each limit was
judged once, at its stage, by the step that measured it (:func:`eol_cal.records.limits.judge`);
the record carries those checks.
"""

from __future__ import annotations

import traceback
from typing import TYPE_CHECKING

from eol_cal import __version__
from eol_cal.errors import EolCalError, InputError
from eol_cal.firmware.block import LAYOUT_VERSION
from eol_cal.records.limits import all_checks
from eol_cal.records.record import EcuActive, ErrorInfo, RunRecord
from eol_cal.station.context import CycleContext, RestoreContext, now_iso

if TYPE_CHECKING:
    from eol_cal.dyno.transfer import DynoConfig


def to_record(ctx: CycleContext) -> RunRecord:
    """The run record, from whatever the steps produced."""
    lim = ctx.cfg.limits
    layout = LAYOUT_VERSION
    if ctx.calibrated is not None and ctx.calibrated.layout_version is not None:  # (never None once made)
        layout = ctx.calibrated.layout_version
    return RunRecord(
        kind=ctx.kind, run_id=ctx.run_id, serial=ctx.cfg.serial,
        started_at=ctx.started.isoformat(timespec="milliseconds"), ended_at=ctx.ended_at, verdict=ctx.verdict,
        reasons=tuple(ctx.reasons), refusal_codes=ctx.refusal_codes if ctx.kind == "refusal" else (),
        error=ctx.error, tool_version=__version__, station=ctx.station,
        layout_version=layout,
        limits=lim, limits_sha256=ctx.limits_sha256, checks=tuple(all_checks(ctx.judged, lim)),
        steps=tuple(ctx.steps), preflight=ctx.preflight, captures=dict(ctx.captures), fit=ctx.result,
        blocks=tuple(ctx.blocks), metrics=ctx.metrics, report_dir=str(ctx.run_dir), safe_state=ctx.safe_state,
        ecu_active=ctx.ecu_active or ecu_active_of(ctx, None), report_error=ctx.report_error, gate=ctx.gate_info)


def record_failure(ctx: CycleContext, exc: BaseException) -> None:
    """The failure that ended the cycle, into the context: verdict ``error``, its reasons (the
    pre-flight's problems each on its own), the error, a refusal's codes, the dyno's safe state."""
    failed_step = ctx.steps[-1].step if ctx.steps else "start"
    ctx.verdict = "error"
    ctx.reasons = [f"{failed_step}: {exc}" if str(exc) else f"{failed_step}: {type(exc).__name__}"]
    problems = getattr(exc, "problems", None)
    if problems:  # the pre-flight: each problem on its own
        ctx.reasons = [f"{failed_step}: {p.text}" for p in problems]
    ctx.error = ErrorInfo(failed_step, type(exc).__name__, str(exc),
                          None if isinstance(exc, EolCalError) else "".join(traceback.format_exception(exc, limit=8)))
    if not ctx.touched:
        if problems:
            ctx.refusal_codes = tuple(dict.fromkeys(p.code for p in problems))
        else:
            ctx.refusal_codes = ("interrupted",) if isinstance(exc, KeyboardInterrupt) else (
                ("settings",) if isinstance(exc, InputError) else ("station_error",))
    if ctx.preflight is not None and ctx.preflight.dyno is None and failed_step == "pre-flight":
        ctx.safe_state = "not commanded: the pre-flight did not reach the dyno (nothing was started on it)"
    else:
        ctx.safe_state = ctx.instruments.safe_state()


def ecu_active_of(ctx: CycleContext, failure: BaseException | None) -> EcuActive:
    """Which block the ECU boots after this run.

    ``calibrated``: this run's block; ``uncompensated``: the prepare step's block (the cycle
    ended before the calibrated one was written: the motor runs without compensation, and a
    calibration it had before is superseded); ``unchanged``: nothing was written.
    """
    active = EcuActive("unchanged")
    for role, word in (("calibrated", "calibrated"), ("prepare", "uncompensated")):
        b = ctx.last_block(role)
        if b is not None and b.confirmed:
            active = EcuActive(word, b.sequence, b.bank)
            break
    boots = getattr(failure, "ecu_boots", None)
    if boots is not None and boots["boots"] != "previous":
        # the flash failed after the new block was complete and checked (a dead link, a
        # signal): the ECU boots it at its next reset
        what = "calibrated" if ctx.error is not None and ctx.error.step == "flash" else "uncompensated"
        active = EcuActive(what if boots["boots"] == "new" else f"{what} (if its CRC was written)",
                           boots["sequence"], boots["bank"])
    return active


def uncalibrated(active: EcuActive, step: str, dyno: DynoConfig) -> str:
    """The record's reason for a motor left with the prepare step's uncompensated block (a dyno
    fault after prepare, a failed fit...): what the ECU runs, why, and how it is recovered."""
    return (f"motor not calibrated: the ECU boots the uncompensated block (sequence {active.sequence}, bank "
            f"{active.bank}) since the cycle ended at {step}; run the motor again (a latched dyno fault: eol-cal "
            f"dyno-clear --dyno {dyno.host}:{dyno.port} first), or bring back the block before it with eol-cal ecu "
            "restore --bank previous")


def restore_record(ctx: RestoreContext) -> RunRecord:
    """The record of an ``ecu restore`` run (kind ``restore``): ``pass`` with the restored block
    active, or ``error`` with what the ECU boots after the failed flash."""
    failure = ctx.failure
    reasons: tuple[str, ...]
    if failure is None:
        assert ctx.report is not None  # the restore step returned: its flash report is set
        verdict, reasons, error = "pass", (), None
        active = EcuActive("restored", ctx.report.sequence, ctx.report.bank)
    else:
        verdict, reasons = "error", (f"restore: {failure}",)
        error = ErrorInfo("restore", type(failure).__name__, str(failure))
        boots = getattr(failure, "ecu_boots", None) or {"boots": "previous"}
        active = (EcuActive("unchanged") if boots["boots"] == "previous" else
                  EcuActive("restored" if boots["boots"] == "new" else "restored (if its CRC was written)",
                            boots.get("sequence"), boots.get("bank")))
    return RunRecord(kind="restore", run_id=ctx.run_id, serial=ctx.serial,
                     started_at=ctx.started.isoformat(timespec="milliseconds"), ended_at=now_iso(), verdict=verdict,
                     reasons=reasons, tool_version=__version__, layout_version=LAYOUT_VERSION, station=ctx.station,
                     error=error, steps=tuple(ctx.steps), blocks=tuple(ctx.blocks), report_dir=str(ctx.run_dir),
                     ecu_active=active, restored_from=ctx.restored_from)
