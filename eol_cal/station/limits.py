"""Pass/fail limits of the end-of-line station, one set per product variant (TOML).

File format (``docs/station.md``)::

    default_variant = "EPS-A"        # optional; used when no variant is chosen

    [variant.EPS-A]
    max_k6 = 0.0025                  # N*m/A, largest acceptable load-proportional ripple k6
    max_pp_before_pct = 12.0         # %, p-p ripple at the operating point before compensation
    max_pp_after_pct = 2.0           # %, p-p ripple at the operating point with compensation
    min_improvement_pct = 40.0       # %, 100 * (before - after) / before
    min_r2 = 0.5                     # fit quality: coefficient of determination
    max_rms_nm = 0.02                # fit quality: residual RMS (N*m)
    max_ci_k6_rel = 0.05             # widest 95 % interval of k6, fraction of k6
    max_ci_phase_k6_deg = 3.0        # widest 95 % interval of phase_k6 (deg)
    max_ci_c6_nm = 0.002             # widest 95 % cogging phasor error (N*m)
    max_hall_deviation_deg = 3.0     # optional (default 3.0): largest hall boundary offset (deg el.)
    max_pp_after_no_mech1_pct = 1.5  # optional (default: no limit): compensated p-p without the
                                     # mechanical order 1 (the rotor's unbalance) (%)
    estimator = "best"               # optional: the estimator options the line flashes (block flags
                                     # bits 2-5): paper, best (default), names joined by "+", or 0xMASK

The keys of the first station are required (a line that forgets one would otherwise pass
motors silently); keys added since are optional with the defaults of :data:`OPTIONAL_DEFAULTS`,
so a limits file written before them still loads. Unknown keys are refused (a typo such as
``max_pp_afer_pct`` would be a limit that never applies).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from eol_cal.analysis.motor_result import MotorResult
from eol_cal.errors import InputError
from eol_cal.firmware.options import DEFAULT_PRESET, options_label, parse_options
from eol_cal.inputs import MAX_TOML_BYTES, loads_toml, read_text

if TYPE_CHECKING:
    from eol_cal.analysis.result import CiLimits

#: key -> (unit, lowest allowed value, highest allowed value)
_KEYS: dict[str, tuple[str, float, float]] = {
    "max_k6": ("N*m/A", 0.0, 1.0),
    "max_pp_before_pct": ("%", 0.0, 1000.0),
    "max_pp_after_pct": ("%", 0.0, 1000.0),
    "min_improvement_pct": ("%", -1000.0, 100.0),
    "min_r2": ("1", -1.0, 1.0),
    "max_rms_nm": ("N*m", 0.0, 100.0),
    "max_ci_k6_rel": ("1", 0.0, 10.0),
    "max_ci_phase_k6_deg": ("deg", 0.0, 180.0),
    "max_ci_c6_nm": ("N*m", 0.0, 100.0),
    "max_hall_deviation_deg": ("deg", 0.0, 180.0),
    "max_pp_after_no_mech1_pct": ("%", 0.0, 1000.0),
}
#: keys a limits file may leave out, and their value then (None: no limit, not judged)
OPTIONAL_DEFAULTS: dict[str, float | None] = {
    # added after the first station: 3 deg el. is the variants' shipped value (fixtures/limits.toml)
    "max_hall_deviation_deg": 3.0,
    # the rotor's unbalance is a mechanical reject only where a line chooses to judge it
    "max_pp_after_no_mech1_pct": None,
}


@dataclass(frozen=True)
class VariantLimits:
    """Limits of one product variant (units in the module doc)."""

    variant: str
    max_k6: float
    max_pp_before_pct: float
    max_pp_after_pct: float
    min_improvement_pct: float
    min_r2: float
    max_rms_nm: float
    max_ci_k6_rel: float
    max_ci_phase_k6_deg: float
    max_ci_c6_nm: float
    max_hall_deviation_deg: float = 3.0  # OPTIONAL_DEFAULTS
    max_pp_after_no_mech1_pct: float | None = None  # OPTIONAL_DEFAULTS: no limit
    source: str = "<memory>"
    estimator: str = DEFAULT_PRESET

    @property
    def estimator_options(self) -> int:
        """The estimator option bits (contract flags bits 2-5) the variant's blocks carry."""
        return parse_options(self.estimator, self.source, f"variant.{self.variant}.estimator")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def ci_limits(self) -> CiLimits:
        """The interval limits as the fit's own :class:`~eol_cal.analysis.result.CiLimits`."""
        from eol_cal.analysis.result import CiLimits

        return CiLimits(k6_rel=self.max_ci_k6_rel, phase_k6_deg=self.max_ci_phase_k6_deg, c6_nm=self.max_ci_c6_nm)


def parse_limits(text: str, file: str) -> dict[str, VariantLimits]:
    """All variants of a limits file's text; :class:`InputError` naming file, key and reason."""
    doc = loads_toml(text, file)
    unknown_top = set(doc) - {"variant", "default_variant"}
    if unknown_top:
        raise InputError(file, sorted(unknown_top)[0], "unknown key (expected [variant.NAME] tables and default_variant)")
    variants = doc.get("variant")
    if not isinstance(variants, dict) or not variants:
        raise InputError(file, "variant", "no [variant.NAME] table")
    out: dict[str, VariantLimits] = {}
    for name, table in variants.items():
        where = f"variant.{name}"
        if not isinstance(table, dict):
            raise InputError(file, where, "must be a table")
        unknown = set(table) - set(_KEYS) - {"estimator"}
        if unknown:
            raise InputError(file, f"{where}.{sorted(unknown)[0]}", f"unknown key; known: {', '.join(_KEYS)}, estimator")
        values: dict[str, float | None] = {}
        for key, (unit, lo, hi) in _KEYS.items():
            if key not in table and key in OPTIONAL_DEFAULTS:
                values[key] = OPTIONAL_DEFAULTS[key]
                continue
            if key not in table:
                raise InputError(file, f"{where}.{key}", f"missing ({unit})")
            v = table[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InputError(file, f"{where}.{key}", f"{v!r} is not a finite number ({unit})")
            if not lo <= v <= hi:
                raise InputError(file, f"{where}.{key}", f"{v} outside {lo:g} ... {hi:g} {unit}")
            values[key] = float(v)
        estimator = options_label(parse_options(table.get("estimator", DEFAULT_PRESET), file, f"{where}.estimator"))
        out[name] = VariantLimits(variant=name, source=file, estimator=estimator, **values)
    default = doc.get("default_variant")
    if default is not None and default not in out:
        raise InputError(file, "default_variant", f"{default!r} is not one of the variants ({', '.join(out)})")
    return out


def load_limits(path: str | Path, variant: str | None = None) -> VariantLimits:
    """The limits of ``variant`` from a limits file.

    Parameters
    ----------
    path : path
        Limits TOML file.
    variant : str, optional
        Product variant; default the file's ``default_variant``, or its only variant.

    Raises
    ------
    InputError
        Unreadable or invalid file, unknown variant, or no variant given where the file has
        several and no default.
    """
    path = Path(path)
    text = read_text(path, max_bytes=MAX_TOML_BYTES)
    variants = parse_limits(text, str(path))
    if variant is None:
        default = loads_toml(text, str(path)).get("default_variant")
        if default is None and len(variants) > 1:
            raise InputError(str(path), "variant", f"several variants ({', '.join(variants)}) and no default_variant: "
                             "choose one by name")
        variant = default or next(iter(variants))
    if variant not in variants:
        raise InputError(str(path), "variant", f"{variant!r} not in the file ({', '.join(variants)})")
    return variants[variant]


@dataclass(frozen=True)
class Measured:
    """What the cycle measured on one motor, as the limits see it.

    Attributes
    ----------
    k6 : float
        Load-proportional 6th-harmonic coefficient (N*m/A).
    ci_k6 : float
        Its 95 % interval half-width (N*m/A).
    ci_phase_k6_deg : float
        95 % interval of phase_k6 (deg).
    ci_c6_nm : float
        Cogging phasor error bound max(ci95(c6), c6 * ci95(phase_c6)) (N*m).
    r2 : float
        Fit R^2 (1).
    rms_nm : float
        Fit residual RMS (N*m).
    pp_before_pct, pp_after_pct : float
        Filtered p-p ripple at the operating point before and with compensation (%);
        NaN when not measured.
    pp_after_no_mech1_pct : float
        ``pp_after_pct`` with the mechanical order 1 (rotor unbalance) taken out (%); NaN when
        not measured.
    hall_deviation_deg : float
        Largest |measured - nominal| hall boundary angle (deg, electrical); NaN when the table
        could not be measured (``hall_source`` says why).
    hall_source : str
        The record's ``hall_angle.source``.
    """

    k6: float
    ci_k6: float
    ci_phase_k6_deg: float
    ci_c6_nm: float
    r2: float
    rms_nm: float
    pp_before_pct: float = math.nan
    pp_after_pct: float = math.nan
    hall_deviation_deg: float = math.nan
    hall_source: str = "not measured"
    pp_after_no_mech1_pct: float = math.nan

    @property
    def improvement_pct(self) -> float:
        """100 * (before - after) / before (%)."""
        if not (self.pp_before_pct > 0.0) or not math.isfinite(self.pp_after_pct):
            return math.nan
        return 100.0 * (self.pp_before_pct - self.pp_after_pct) / self.pp_before_pct


@dataclass(frozen=True)
class LimitCheck:
    """One limit of a variant against what was measured.

    Attributes
    ----------
    key : str
        The limit's key in the limits file (``max_k6``...).
    quantity : str
        What is judged, in words.
    value : float
        The measured value in ``unit`` (NaN: not measured).
    limit : float
        The limit in ``unit``.
    unit : str
        Unit of ``value``, ``limit`` and ``margin``.
    sense : {"max", "min"}
        ``max``: the value must not exceed the limit; ``min``: it must not fall below it.
    ok : bool
        The limit is met (NaN never meets one).
    reason : str
        Why it is not met (empty when it is).
    stage : {"fit", "ripple"}
        ``fit``: judged right after the fit; ``ripple``: on the compensated run.
    """

    key: str
    quantity: str
    value: float
    limit: float
    unit: str
    sense: str
    ok: bool
    reason: str
    stage: str

    @property
    def margin(self) -> float:
        """How far inside the limit the value is (``unit``; negative: outside, NaN: not measured)."""
        return self.limit - self.value if self.sense == "max" else self.value - self.limit


def _check(key: str, quantity: str, value: float, limit: float, unit: str, sense: str, stage: str,
           reason: str) -> LimitCheck:
    ok = bool(value <= limit) if sense == "max" else bool(value >= limit)
    return LimitCheck(key, quantity, float(value), float(limit), unit, sense, ok, "" if ok else reason, stage)


def limit_checks(m: Measured, lim: VariantLimits) -> list[LimitCheck]:
    """Every limit of ``lim`` against ``m``, in the limits file's order (``verdict``'s reasons
    are the failed checks' reasons); an optional limit that is off is not a check."""
    k6, imp = abs(m.k6), m.improvement_pct
    ci_k6_rel = m.ci_k6 / k6 if k6 > 0 else math.inf
    hall = m.hall_deviation_deg
    hall_reason = (f"hall table not measured: {m.hall_source}" if math.isnan(hall) else
                   f"hall boundary {hall:.3g} deg from nominal exceeds max_hall_deviation_deg = {lim.max_hall_deviation_deg:g}")
    checks = [
        _check("max_k6", "k6", m.k6, lim.max_k6, "N*m/A", "max", "fit",
               f"k6 = {m.k6:.4g} N*m/A exceeds max_k6 = {lim.max_k6:g}"),
        _check("max_pp_before_pct", "p-p ripple before", m.pp_before_pct, lim.max_pp_before_pct, "%", "max", "ripple",
               f"p-p before = {m.pp_before_pct:.3g} % exceeds max_pp_before_pct = {lim.max_pp_before_pct:g}"),
        _check("max_pp_after_pct", "p-p ripple compensated", m.pp_after_pct, lim.max_pp_after_pct, "%", "max", "ripple",
               f"p-p after = {m.pp_after_pct:.3g} % exceeds max_pp_after_pct = {lim.max_pp_after_pct:g}"),
        _check("min_improvement_pct", "improvement", imp, lim.min_improvement_pct, "%", "min", "ripple",
               f"improvement = {imp:.3g} % below min_improvement_pct = {lim.min_improvement_pct:g}"),
        _check("min_r2", "fit R^2", m.r2, lim.min_r2, "1", "min", "fit",
               f"fit R^2 = {m.r2:.4g} below min_r2 = {lim.min_r2:g}"),
        _check("max_rms_nm", "fit residual rms", m.rms_nm, lim.max_rms_nm, "N*m", "max", "fit",
               f"fit rms = {m.rms_nm:.4g} N*m exceeds max_rms_nm = {lim.max_rms_nm:g}"),
        _check("max_ci_k6_rel", "95 % interval of k6 / k6", ci_k6_rel, lim.max_ci_k6_rel, "1", "max", "fit",
               f"ci95(k6) = {m.ci_k6:.3g} N*m/A exceeds {100 * lim.max_ci_k6_rel:g} % of k6"),
        _check("max_ci_phase_k6_deg", "95 % interval of phase_k6", m.ci_phase_k6_deg, lim.max_ci_phase_k6_deg, "deg",
               "max", "fit", f"ci95(phase_k6) = {m.ci_phase_k6_deg:.3g} deg exceeds max_ci_phase_k6_deg = "
               f"{lim.max_ci_phase_k6_deg:g}"),
        _check("max_ci_c6_nm", "95 % cogging phasor error", m.ci_c6_nm, lim.max_ci_c6_nm, "N*m", "max", "fit",
               f"c6 phasor ci95 = {m.ci_c6_nm:.3g} N*m exceeds max_ci_c6_nm = {lim.max_ci_c6_nm:g}"),
        _check("max_hall_deviation_deg", "largest hall boundary offset", hall, lim.max_hall_deviation_deg, "deg", "max",
               "fit", hall_reason),
    ]
    if lim.max_pp_after_no_mech1_pct is not None:
        no1 = m.pp_after_no_mech1_pct
        checks.append(_check("max_pp_after_no_mech1_pct", "p-p compensated without mechanical order 1", no1,
                             lim.max_pp_after_no_mech1_pct, "%", "max", "ripple",
                             f"p-p after without mechanical order 1 = {no1:.3g} % exceeds max_pp_after_no_mech1_pct = "
                             f"{lim.max_pp_after_no_mech1_pct:g} (electrical ripple left: re-test, check the fit)"))
    return checks


_FIT_ORDER = ("max_k6", "min_r2", "max_rms_nm", "max_ci_k6_rel", "max_ci_phase_k6_deg", "max_ci_c6_nm",
              "max_hall_deviation_deg")
_RIPPLE_ORDER = ("max_pp_before_pct", "max_pp_after_pct", "min_improvement_pct", "max_pp_after_no_mech1_pct")


def _reasons(m: Measured, lim: VariantLimits, order: tuple[str, ...]) -> list[str]:
    by_key = {c.key: c for c in limit_checks(m, lim)}
    return [by_key[k].reason for k in order if k in by_key and not by_key[k].ok]


def fit_reasons(m: Measured, lim: VariantLimits) -> list[str]:
    """Why the fit's quality or k6 fails ``lim`` (empty: it passes)."""
    return _reasons(m, lim, _FIT_ORDER)


def ripple_reasons(m: Measured, lim: VariantLimits) -> list[str]:
    """Why the before/after ripple fails ``lim`` (empty: it passes); NaN never passes."""
    return _reasons(m, lim, _RIPPLE_ORDER)


def verdict(m: Measured, lim: VariantLimits) -> tuple[str, list[str]]:
    """``("pass", [])`` or ``("fail", reasons)`` of a fully measured motor against ``lim``."""
    reasons = fit_reasons(m, lim) + ripple_reasons(m, lim)
    return ("fail", reasons) if reasons else ("pass", [])


LIMIT_KEYS = tuple(f.name for f in fields(VariantLimits) if f.name not in ("variant", "source", "estimator"))


def measured_from_fit(rec: dict[str, Any]) -> Measured:
    """:func:`measured_from_result` of a usable motor record, read by :meth:`MotorResult.from_json`."""
    return measured_from_result(MotorResult.from_json(rec, "<run record>", "fit."))


def measured_from_result(res: MotorResult) -> Measured:
    """The fit's part of :class:`Measured` (k6 N*m/A, intervals, r2, rms N*m, hall deviation deg).

    Raises
    ------
    ValueError
        The fit is not usable (no estimates).
    TypeError
        An interval or a fit figure is null (not finite when the fit wrote it).
    """
    e = res.estimates
    if e is None:
        raise ValueError(f"motor {res.serial}: fit status {res.status!r} has no estimates")
    ci_c6 = max(float(e.c6.ci95), abs(e.c6.value) * float(e.phase_c6.ci95))
    hall = res.hall_angle or {"source": "not in the record", "deviation_deg": []}
    measured = hall["source"] == "measured"
    return Measured(
        k6=abs(float(e.k6.value)), ci_k6=float(e.k6.ci95), ci_phase_k6_deg=math.degrees(float(e.phase_k6.ci95)),
        ci_c6_nm=ci_c6, r2=float(res.fit["r2"]), rms_nm=float(res.fit["rms"]),
        hall_deviation_deg=max(abs(float(d)) for d in hall["deviation_deg"]) if measured else math.nan,
        hall_source=str(hall["source"]),
    )
