"""The parts of a run record (:class:`eol_cal.records.record.RunRecord`): the station, captures,
flashed blocks, pre-flight, ripple, steps, error, ECU state after the run, restore source, and
the run kinds and refusal codes. Typed and frozen; their JSON is :mod:`eol_cal.records.parts_json`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Mapping

from eol_cal.capture.ecu_state import EcuState
from eol_cal.errors import InputError

SCHEMA = "eol-cal/run-record/2"
SCHEMA_V1 = "eol-cal/run-record/1"
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
    "master_due": "the station's master motor check is due (none within its period)",
    "master_failed": "the station's last master motor check failed",
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
    """A capture the run made: its file, SHA-256, size, the ECU's state around it, and the lead-in
    (s) the shaft turned at its first point before its samples (:func:`eol_cal.dyno.profile_run.run_profile`;
    None in a record written before the station turned one), after ``lead_in_point`` (speed rpm,
    s) when it turned at another speed first."""

    path: str
    sha256: str
    samples: int
    segments: int
    ecu_before: EcuState | None = None
    ecu_after: EcuState | None = None
    lead_in_s: float | None = None
    lead_in_point: tuple[float, float] | None = None


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
    layout_version : int or None
        The block's layout (1, or 2 with the mechanical orders of revision 1.2); None where not recorded.
    mech : str or None
        Layout 2: ``"on"`` when its ``MECH_COMP_ENABLE`` is honoured (the ECU identifies the rotor's
        mechanical angle and compensates the mechanical orders), ``"off"`` (the reasons are the
        fit's ``mech.reasons``); None for layout 1.
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
    layout_version: int | None = None
    mech: str | None = None


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
    amplitude (N*m), the time span analysed (s), the mechanical order 1's amplitude (N*m; NaN in
    records older than revision 1.2)."""

    pp_pct: float
    pp_raw_pct: float
    pp_nm: float
    pp_no_mech1_pct: float
    T_avg_nm: float
    amp6_nm: float
    span_s: tuple[float, float]
    mech1_nm: float = float("nan")


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
class MasterCheck:
    """One quantity of a master run against its reference (display units: mN*m/A, deg, mN*m, %):
    the value measured (None: not measured), the reference, the tolerance (+-), the deviation
    (a phase's on the circle) and whether it lies within."""

    quantity: str
    unit: str
    value: float | None
    reference: float
    tolerance: float
    deviation: float | None
    passed: bool

    @property
    def reason(self) -> str | None:
        """Why it failed (None: it passed)."""
        if self.passed:
            return None
        if self.value is None or self.deviation is None:
            return f"master {self.quantity}: not measured"
        return (f"master {self.quantity} = {self.value:.4g} {self.unit} deviates {self.deviation:+.3g} from its "
                f"reference {self.reference:.4g} (tolerance +-{self.tolerance:g})")


@dataclass(frozen=True)
class GateInfo:
    """The master gate a run went through (the record's ``gate``).

    Attributes
    ----------
    rules : mapping
        The rules in force (``serial``, ``reference``, ``tolerance`` in display units,
        ``every_h`` or ``shifts`` and ``timezone``).
    source : str
        Where they came from: ``records database`` (``eol-cal gate set``) or the settings.
    station, seq, set_at : str or None, int or None, str or None
        The change of the station's rules in the records database that set them (None: not there).
    master_run, master_started_at, master_verdict : str or None
        A production run: the master run that admitted it (its run id, start, verdict).
    checks : tuple of MasterCheck
        A master run: its own checks against the references; a production run: those of the
        master run that admitted it.
    """

    rules: Mapping[str, Any]
    source: str
    station: str | None = None
    seq: int | None = None
    set_at: str | None = None
    master_run: str | None = None
    master_started_at: str | None = None
    master_verdict: str | None = None
    checks: tuple[MasterCheck, ...] = ()
