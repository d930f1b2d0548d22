"""The end-of-line cycle for one motor.

pre-flight (dyno ready, ECU answering and accepting the key, serials agreeing; nothing written,
:mod:`eol_cal.station.preflight`) -> prepare ECU (flash the uncompensated block: field estimator,
no compensation) -> acquire (dyno, profile) -> fit -> table (lead auto) -> flash (ECU, key) -> acquire with the compensation the
ECU now runs -> metrics -> verdict against the variant's limits -> report + record. The first
flash makes the calibration capture independent of what the ECU ran before: a blank ECU would
run the raw encoder angle (k6 about 1.7 % low and twice the scatter on the plant lot), and a
motor being re-tested would be measured through its old compensation, whose residual would then
become its new table. Every step is timed. A fit that is not usable, or a motor whose k6 or fit quality is out
of limits, fails right after the fit (nothing is flashed). Any error ends the cycle with verdict
``error``: the dyno client has already put the drive in the safe state (speed 0, disabled); the
cycle commands it once more, best effort, and the record is written all the same.

Exit codes (:attr:`RunOutcome.exit_code`): 0 pass, 1 fail, 2 error (a refusal too).
"""

from __future__ import annotations

import datetime as dt
import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable

from eol_cal.errors import InputError
from eol_cal.domain.bench_mechanics import BenchMechanics, load_mechanics
from eol_cal.domain.motor_params import MotorParams, load_motor
from eol_cal.records.limits import VariantLimits

if TYPE_CHECKING:
    from concurrent.futures import Future

    from eol_cal.analysis.fit.capture import PreparedWindows
    from eol_cal.analysis.fit.motors import MotorsFit
    from eol_cal.report.motor_page import FitExtra
    from eol_cal.dyno.transfer import DynoConfig
    from eol_cal.ecu.session import ClientTiming
    from eol_cal.msa.master import MasterSettings
    from eol_cal.records.spool import SaveResult
    from eol_cal.analysis.motor_result import MotorResult
    from eol_cal.capture.data import Capture
    from eol_cal.records.record import RunRecord

EXIT = {"pass": 0, "fail": 1, "error": 2}
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
        :func:`eol_cal.records.spool.default_spool_dir`).
    rate_hz : int
        Capture sample rate (Hz).
    db_timeout_s : float
        How long a database write waits for a lock (s) before spooling.
    station : dict
        Free-form description of the station for the record (addresses, interface).
    ecu_timing : ClientTiming or None
        UDS timing (default the contract's).
    cache_dir : Path or None
        The fit's cache directory (JAX's persistent compilation cache and the serialized solvers,
        :func:`eol_cal.analysis.fit.cache.default_cache_dir`), switched on by the pre-warming on
        the helper thread while the dyno spins (importing JAX costs a second); ``None``: no cache.
    motor : MotorParams
        The motor type on the station (default the paper preset): poles and encoder the
        captures must show, the ECU's tick rate and kt for the blocks, the current loop for the
        lead, rotor inertia for the bench response.
    mechanics : BenchMechanics or None
        The dyno bench whose response the fit divides out (default the built-in ``paper``
        bench, which ``eol-cal dyno-sim`` simulates); ``None``: rigid coupling.
    estimator : str or None
        The estimator options the line flashes (contract flags bits 2-5: ``paper``, ``best``,
        names joined by ``+`` or a hex mask, :mod:`eol_cal.firmware.options`); ``None``: the
        variant's (``limits.estimator``, default ``best``). The uncompensated block of the
        "prepare ECU" step carries the same options as the calibrated one, and the fit measures
        its frame under that estimator.
    kind : str
        The record's kind when the cycle gets past its pre-flight (``production`` on a line;
        :data:`eol_cal.records.record.KINDS`); a cycle that ends before is a ``refusal``.
    read_back : bool
        Read each block this cycle flashes back before its CRC is written (settings key
        ``flash.read_back``: ``before-crc``); False leaves the check to the ECU's CRC routine
        (the contract's read-back is optional; the record's blocks say ``verified`` false).
    lead_in : str
        Turn the shaft for the ECU's settling after the reset before an acquisition's capture
        counts (settings key ``dyno.lead_in``): ``settle``, as
        :func:`eol_cal.firmware.settling.lead_in_plan` says for the block the cycle flashed (an
        identifying ECU at its own speed first); ``at-point``, all of it at the acquisition's
        first point; ``off``, capture at once.
    report_plots : bool
        Draw the report page's plots (residual, angle, spectrum); False: the page and
        ``report.json`` without them (a what-if lot, whose run directories are removed when its
        batch ends: the plots were half a motor's CPU and nobody saw them).
    master : MasterSettings or None
        The station's master motor (:mod:`eol_cal.msa.master`): a ``production`` run is refused
        while its check is due or last failed; a run of kind ``master`` is judged against its
        references too.
    """

    serial: str
    dyno: DynoConfig
    open_bus: Callable[[], Any]
    seed_to_key: Callable[[bytes], bytes]
    limits: VariantLimits
    db: Path | str
    report_dir: Path
    profile: str = "eol-default"
    verify: str = "point"
    spool_dir: Path | None = None
    rate_hz: int = 10000
    db_timeout_s: float = 5.0
    station: dict[str, Any] = field(default_factory=dict)
    ecu_timing: ClientTiming | None = None
    cache_dir: Path | None = None
    motor: MotorParams = field(default_factory=lambda: load_motor("paper"))
    mechanics: BenchMechanics | None = field(default_factory=lambda: load_mechanics("paper"))
    estimator: str | None = None
    kind: str = "production"
    master: MasterSettings | None = None
    read_back: bool = True
    lead_in: str = "settle"
    report_plots: bool = True

    @property
    def estimator_options(self) -> int:
        """The estimator option bits this station's blocks carry (this config's, else the variant's)."""
        from eol_cal.firmware.options import parse_options

        if self.estimator is None:
            return self.limits.estimator_options
        return parse_options(self.estimator, None, "estimator")


@dataclass
class RunOutcome:
    """What :func:`run_motor` returns: the record, where it went, and the exit code.

    ``pending``: the report and the record's database write still on the report thread
    (:mod:`eol_cal.station.report_behind`); then ``record`` is the one journaled at the verdict,
    ``saved`` its place in the spool, and :meth:`final` waits for the run's last outcome.
    """

    record: RunRecord
    saved: SaveResult | None
    report_html: Path | None
    exit_code: int
    pending: Future[RunOutcome] | None = None

    @property
    def verdict(self) -> str:
        return self.record.verdict

    def final(self) -> RunOutcome:
        """The outcome once the report and the record are written (raises what writing the record raised)."""
        return self if self.pending is None else self.pending.result()


def sha256_file(path: str | Path) -> str:
    """SHA-256 of a file's bytes, hex."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _now() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")


def _safe_name(text: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in text)


# --------------------------------------------------------------------------- fit
def fit_motor(capture: Capture, limits: VariantLimits, tool_version: str, motor: MotorParams | None = None,
              mechanics: BenchMechanics | None = None, cache_dir: Path | None = None,
              estimator_options: int = 0, prepared: PreparedWindows | None = None
              ) -> tuple[MotorsFit, MotorResult, FitExtra]:
    """The ripple fit of one motor's capture: :func:`eol_cal.analysis.fit.motors.fit_motors`, as
    ``eol-cal fit`` runs it (windows fitted jointly, phases in the firmware frame).

    ``motor`` (default the paper preset), ``mechanics`` (``None``: rigid coupling) and
    ``cache_dir`` (the serialized solvers; ``None``: none) and ``estimator_options`` (what the
    ECU ran during the capture) as in :class:`eol_cal.analysis.fit.motors.FitOptions`;
    ``prepared``: the windows' work done while the dyno turned (:mod:`eol_cal.station.early`).

    Returns
    -------
    fitted, result, extra
        The fit (:class:`~eol_cal.analysis.fit.motors.MotorsFit`: its ``to_json`` is the result
        file), its one motor's typed :class:`~eol_cal.analysis.motor_result.MotorResult`, and
        ``(MotorInput, MotorFit, FitSpec)`` for the plots.
    """
    from eol_cal.analysis.fit.motors import FitOptions, fit_motors

    options = FitOptions(limits=limits.ci_limits(), batch="loop", mechanics=mechanics, motor=motor, cache_dir=cache_dir,
                         estimator_options=estimator_options)
    fitted = fit_motors([capture], options, tool_version, prepared=prepared)
    (result,) = fitted.results
    return fitted, result, (fitted.inputs[0], fitted.fits[0], options.spec)


def check_motor(capture: Capture, motor: MotorParams) -> None:
    """Refuse a capture whose poles or encoder are not the station's motor type (InputError).

    The blocks the station flashes carry the motor type's poles, encoder and tick rate; a
    capture of another motor would be fitted and flashed with the wrong ones.
    """
    for key, want in (("poles", motor.poles), ("encoder_ppr", motor.N_enc)):
        got = int(capture.metadata[key])
        if got != want:
            raise InputError(capture.source, key, f"the capture says {got}, the station's motor type "
                             f"{motor.name!r} has {want}: wrong motor on the dyno, or the station is set up for "
                             "another motor type")


# --------------------------------------------------------------------------- the cycle
def new_run_dir(report_dir: Path, serial: str, started: dt.datetime, run_id: str) -> Path:
    """A new directory for one run under ``report_dir``, as an absolute path: records of every kind
    (production, restore) keep where their files are whatever directory the command ran in."""
    stamp = started.strftime("%Y%m%dT%H%M%SZ")
    d = Path(report_dir).absolute() / f"{_safe_name(serial)}_{stamp}_{run_id[:8]}"
    try:
        d.mkdir(parents=True, exist_ok=False)
    except (OSError, ValueError) as exc:  # /proc/self, a read-only mount, a name too long: before the dyno turns
        raise InputError(str(report_dir), "report_dir", f"cannot make the run's directory there: "
                                                        f"{getattr(exc, 'strerror', None) or exc}") from None
    return d


def check_config(cfg: StationConfig) -> None:
    """Refuse what can be known bad before the dyno turns (no record: nothing was run)."""
    from eol_cal.firmware.block import serial_problem

    why = serial_problem(cfg.serial)
    if why is not None:
        raise InputError(None, "serial", f"{cfg.serial!r}: {why} (the block's serial field: 1 to 16 ASCII characters, "
                                         "printable)")
    try:
        cfg.report_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(str(cfg.report_dir), "report-dir", f"cannot create: {exc}") from None


def safe_state(dyno_cfg: Any) -> str:
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
