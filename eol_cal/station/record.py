"""The run record: one typed object per station run, and the one place its JSON is spelled.

:class:`RunRecord` is what the station cycle fills (:mod:`eol_cal.station.cycle`), what the
records database and the spool store, and what the reports, the lot page, ``lot stats``,
``lot diff`` and ``refit`` read. :meth:`RunRecord.to_json` writes schema ``eol-cal/run-record/2``
(``eol_cal/schemas/run-record.schema.json``, keys in ``docs/json.md``); :meth:`RunRecord.from_json`
reads it and, through :mod:`eol_cal.station.record_v1`, every record written before it
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
from typing import Any, Mapping

from eol_cal.analysis.motor_result import MotorResult
from eol_cal.capture.ecu_state import EcuState
from eol_cal.errors import InputError
from eol_cal.station.limits import LimitCheck, VariantLimits

SCHEMA = "eol-cal/run-record/2"
SCHEMA_V1 = "eol-cal/run-record/1"
KINDS = ("production", "refusal", "restore", "master", "simulated")
#: the kind lot statistics, first-pass yield, latest status, ``lot diff`` and ``refit`` take by default
MEASURED_KIND = "production"
VERDICTS = ("pass", "fail", "error")
#: why a run was refused (nothing written to the ECU, nothing measured): code -> meaning
REFUSAL_CODES: dict[str, str] = {
    "wrong_serial": "the serial given is not the ECU's (F18C) or the dyno's motor's",
    "dyno_unreachable": "the dyno did not answer",
    "dyno_fault": "the dyno has latched faults",
    "dyno_tripped": "the dyno's drive is tripped",
    "dyno_interlocks": "the dyno's interlocks are not met",
    "ecu_bus": "the ECU's CAN bus could not be opened",
    "ecu_silent": "the ECU did not answer",
    "key_refused": "the ECU refused the security key",
    "settings": "the station's settings were refused (profile, estimator options)",
    "interrupted": "the operator stopped the run before anything was written",
    "station_error": "the station failed before anything was written",
}
BLOCK_ROLES = ("prepare", "calibrated", "restore")


class RecordFormatError(InputError, ValueError):
    """A run record that does not hold what its schema says (names the source, field, reason)."""


@dataclass(frozen=True)
class StationInfo:
    """The station a run was made on (the record's ``station``); ``extra``: what else the station
    recorded about itself (addresses, CAN interface), as given."""

    id: str | None = None
    operator: str | None = None
    settings: str | None = None
    profile: str | None = None
    verify: str | None = None
    rate_hz: int | None = None
    motor: str | None = None
    bench: str | None = None
    dyno_register_map: str | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class CaptureRef:
    """A capture the run made: its file, SHA-256, size, and the ECU's state around it."""

    path: str
    sha256: str
    samples: int
    segments: int
    ecu_before: EcuState | None = None
    ecu_after: EcuState | None = None


@dataclass(frozen=True)
class PreviousBlock:
    """What the ECU booted before a flash (``bank`` None: no valid bank)."""

    bank: int | None
    sequence: int


@dataclass(frozen=True)
class FlashedBlock:
    """A block written into the ECU by the run, archived in the run's directory as it went in.

    Attributes
    ----------
    role : {"prepare", "calibrated", "restore"}
        The uncompensated block the cycle flashes before the calibration capture, the calibrated
        block, or an earlier calibration flashed again.
    path : str
        The archive file: the block's bytes as flashed (sequence and CRC set).
    sha256 : str or None
        SHA-256 of those bytes (None in records older than the archive: their file is the block
        before the flash set its sequence and CRC).
    bytes : int or None
    bank, sequence, crc32
        Where it went, its sequence and CRC (8 hex digits) as flashed.
    flags, estimator : str or None
        The block's flags by name and the estimator options they select.
    table_len, lead_s, iqc_limit
        The block's table length, compensation lead (s) and current limit (A); None where not recorded.
    verified : bool
        Read back equal before its CRC was written.
    confirmed : bool
        The ECU reported it active after the reset (FD01); False: the flash failed after its CRC
        was written and the ECU boots it at its next reset.
    previous : PreviousBlock or None
        What the ECU booted before.
    seconds, transfer_blocks, retries
        The flash's wall time (s), TransferData requests and repeated requests; None where not recorded.
    """

    role: str
    path: str | None
    sha256: str | None
    bytes: int | None
    bank: int | None
    sequence: int | None
    crc32: str | None
    flags: str | None = None
    estimator: str | None = None
    table_len: int | None = None
    lead_s: float | None = None
    iqc_limit: float | None = None
    verified: bool = False
    confirmed: bool = True
    previous: PreviousBlock | None = None
    seconds: float | None = None
    transfer_blocks: int | None = None
    retries: int | None = None


@dataclass(frozen=True)
class Problem:
    """One reason the pre-flight found the station not ready: a :data:`REFUSAL_CODES` code and the text."""

    code: str
    text: str


@dataclass(frozen=True)
class DynoStatus:
    """The dyno as the pre-flight read it (nothing commanded)."""

    map_version: int
    dut_serial: str
    faults: int
    interlocks: int
    drive_state: int


@dataclass(frozen=True)
class EcuFound:
    """The ECU as the pre-flight found it: its state (None: it did not answer), whether it accepted
    the key (None: not tried), its problems."""

    state: EcuState | None
    key_accepted: bool | None
    problems: tuple[str, ...] = ()


@dataclass(frozen=True)
class PreflightResult:
    """What the pre-flight found (None parts: not reached)."""

    dyno: DynoStatus | None
    ecu: EcuFound | None
    problems: tuple[Problem, ...] = ()

    @property
    def codes(self) -> tuple[str, ...]:
        """The problems' codes, each once, in order."""
        return tuple(dict.fromkeys(p.code for p in self.problems))


@dataclass(frozen=True)
class PointFigures:
    """The ripple at the operating point of one capture (``docs/metrics.md``): filtered and raw
    p-p (%), p-p (N*m), p-p without the mechanical order 1 (%), mean torque (N*m), 6th-order
    amplitude (N*m), the time span analysed (s)."""

    pp_pct: float
    pp_raw_pct: float
    pp_nm: float
    pp_no_mech1_pct: float
    T_avg_nm: float
    amp6_nm: float
    span_s: tuple[float, float]


@dataclass(frozen=True)
class RippleMetrics:
    """The ripple at the operating point before and with the compensation."""

    speed_rpm: float
    i_qo_a: float
    before: PointFigures
    after: PointFigures
    definition: str

    @property
    def improvement_pct(self) -> float:
        b, a = self.before.pp_pct, self.after.pp_pct
        return 100.0 * (b - a) / b if b > 0.0 and math.isfinite(a) else math.nan


@dataclass(frozen=True)
class Step:
    """One step of the run: its name, wall time (s; None: not finished), whether it completed, and
    the error that ended it (None: none)."""

    step: str
    seconds: float | None
    ok: bool
    error: str | None = None


@dataclass(frozen=True)
class ErrorInfo:
    """The exception that ended a run: the step, its type, message and (for a program error) traceback."""

    step: str
    type: str
    message: str
    traceback: str | None = None


@dataclass(frozen=True)
class EcuActive:
    """Which block the ECU boots after the run: ``calibrated``, ``uncompensated``, ``restored``,
    ``unchanged`` (nothing written), or such a word with a qualification; its sequence and bank."""

    block: str
    sequence: int | None = None
    bank: int | None = None


@dataclass(frozen=True)
class RestoredFrom:
    """The calibration a restore flashed again: the run that archived it, its archive file and
    SHA-256, and its sequence and CRC as that run flashed them."""

    run_id: str | None
    path: str
    sha256: str | None
    sequence: int | None
    crc32: str | None


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
        """The record as JSON (schema :data:`SCHEMA`; non-finite numbers as null)."""
        from eol_cal.station.record_json import record_to_json

        return record_to_json(self)

    @classmethod
    def from_json(cls, doc: Any, source: str = "<record>") -> RunRecord:
        """A record of schema :data:`SCHEMA` or :data:`SCHEMA_V1` (migrated);
        :class:`RecordFormatError` names ``source``, the field and the reason."""
        from eol_cal.station.record_json import record_from_json

        return record_from_json(doc, source)


def record_kind(doc: Any) -> str | None:
    """The kind of a record's JSON without reading the rest (None: not a record): a v1 record that
    ended in the pre-flight is a refusal, any other v1 record production."""
    if not isinstance(doc, dict):
        return None
    if doc.get("schema") == SCHEMA:
        return doc.get("kind")
    if doc.get("schema") == SCHEMA_V1:
        from eol_cal.station.record_v1 import kind_v1

        return kind_v1(doc)
    return None
