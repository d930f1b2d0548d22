"""Pass/fail limits of the end-of-line station: one table, one set of values per product variant.

:data:`LIMITS` is the one table of the limits: per row the key a limits file sets, the measured
quantity it bounds (a :class:`Measured` field, and the lot's column of the same name where
there is one), what it checks in words, its unit, its sense (``max``: the value must not exceed
the limit; ``min``: not fall below it), the stage of the cycle that judges it (``fit``: right
after the fit, before anything calibrated is flashed; ``ripple``: on the compensated capture),
the values a file may give it, and whether a file may leave it out. Adding a limit on a quantity
the cycle already measures is one row here (and its line in ``docs/station.md``); everything
else (the limits file's checks, the record's checks, the report, the lot page, ``lot stats``)
follows the table.

A limits file (``docs/station.md``, "Limits") holds ``[variant.NAME]`` tables of these keys, an
optional ``default_variant`` and per variant an optional ``estimator`` (the estimator options the
line flashes). Rows without a default are required (a line that forgets one would otherwise pass
motors silently); rows added since the first station have a default (``None``: not judged unless
set), so a limits file written before them still loads. Unknown keys are refused (a typo would
be a limit that never applies).

The cycle judges each stage once (:func:`judge`); the run record carries every check
(:class:`LimitCheck`: value, limit, margin, pass) and whoever shows a verdict reads those.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Mapping

from eol_cal.analysis.intervals import CiLimits, ci_phasor, ci_rel, within
from eol_cal.errors import InputError
from eol_cal.firmware.options import DEFAULT_PRESET, options_label, parse_options
from eol_cal.infra.inputs import MAX_TOML_BYTES, loads_toml, read_text

if TYPE_CHECKING:
    from eol_cal.analysis.motor_result import MotorResult

#: a row's ``default`` when a limits file must set it
REQUIRED = "required"
STAGES = ("fit", "ripple")


@dataclass(frozen=True)
class Limit:
    """One row of :data:`LIMITS`.

    Attributes
    ----------
    key : str
        The key in a limits file.
    quantity : str
        The :class:`Measured` field it bounds (the lot's column where the lot has one).
    title : str
        What is judged, in words.
    unit : str
        Unit of the quantity and the limit (stored units; people read :mod:`eol_cal.rendering.display`'s).
    sense : {"max", "min"}
        ``max``: the value must not exceed the limit; ``min``: it must not fall below it.
    stage : {"fit", "ripple"}
        ``fit``: judged right after the fit; ``ripple``: on the compensated capture.
    bounds : (float, float)
        The values a limits file may give it.
    default : float, None or REQUIRED
        Its value when a limits file leaves it out (None: off, not judged).
    ci : str or None
        The fit's :class:`~eol_cal.analysis.intervals.CiLimits` field it also sets (the interval
        limits: the fit's status judges the same quantity, :mod:`eol_cal.analysis.intervals`).
    missing : str
        The reason when the quantity was not measured (``str.format`` of the :class:`Measured` fields).
    fails : str or None
        The reason when the limit is not met, where the value and the limit alone would not tell the
        engineer what to do (``str.format`` of the :class:`Measured` fields); None: value against limit.
    """

    key: str
    quantity: str
    title: str
    unit: str
    sense: str
    stage: str
    bounds: tuple[float, float]
    default: float | None | str = REQUIRED
    ci: str | None = None
    missing: str = "{title} not measured ({key} is not met)"
    fails: str | None = None


#: the limits, in the order the report and the record list them
LIMITS: tuple[Limit, ...] = (
    Limit("max_k6", "k6", "k6", "N*m/A", "max", "fit", (0.0, 1.0)),
    Limit("max_pp_before_pct", "pp_before_pct", "p-p ripple before", "%", "max", "ripple", (0.0, 1000.0)),
    Limit("max_pp_after_pct", "pp_after_pct", "p-p ripple compensated", "%", "max", "ripple", (0.0, 1000.0)),
    Limit("min_improvement_pct", "improvement_pct", "improvement", "%", "min", "ripple", (-1000.0, 100.0)),
    Limit("min_r2", "fit_r2", "fit R^2", "1", "min", "fit", (-1.0, 1.0)),
    Limit("max_rms_nm", "fit_rms_nm", "fit residual rms", "N*m", "max", "fit", (0.0, 100.0)),
    Limit("max_ci_k6_rel", "ci_k6_rel", "95 % interval of k6 / k6", "1", "max", "fit", (0.0, 10.0), ci="k6_rel"),
    Limit("max_ci_phase_k6_deg", "ci_phase_k6_deg", "95 % interval of phase_k6", "deg", "max", "fit", (0.0, 180.0),
          ci="phase_k6_deg"),
    Limit("max_ci_c6_nm", "ci_c6_nm", "95 % cogging phasor error", "N*m", "max", "fit", (0.0, 100.0), ci="c6_nm"),
    # added after the first station: 3 deg el. is the variants' shipped value (fixtures/limits.toml)
    Limit("max_hall_deviation_deg", "hall_deviation_deg", "largest hall boundary offset", "deg", "max", "fit",
          (0.0, 180.0), default=3.0, missing="hall table not measured: {hall_source}"),
    # the rotor's unbalance is a mechanical reject only where a line chooses to judge it
    Limit("max_pp_after_no_mech1_pct", "pp_after_no_mech1_pct", "p-p compensated without mechanical order 1", "%",
          "max", "ripple", (0.0, 1000.0), default=None),
    # revision 1.2: with a layout-2 block the mechanical orders are compensated too (the compensated
    # p-p above then judges every order); this judges what the compensation left of order 1
    Limit("max_mech1_after_nm", "mech1_after_nm", "mechanical order 1 left compensated", "N*m", "max", "ripple",
          (0.0, 10.0), default=None),
    # issue 34: the fit checks its own model (k6/c6 per speed band); the fit judges it with its own
    # CiLimits.model_p (0.001) when a limits file leaves this out, so a mismatch is never a silent ok
    Limit("min_model_check_p", "model_check_p", "agreement of the speed bands (model check p-value)", "1", "min", "fit",
          (0.0, 1.0), default=None, ci="model_p", missing="model not checked: {model_check_note}"),
    # issue 34: a bench file nobody identified on this dyno (the built-in paper) biases k6 by up to
    # ~1 % unseen where the speed bands cannot see the torque path's resonance: judged by default (1
    # accepts the assumption); the simulated plant's own bench and identified files are not assumed
    Limit("max_bench_assumed", "bench_assumed", "bench file assumed (not identified on this bench)", "1", "max",
          "fit", (0.0, 1.0), default=0.0,
          fails="the bench file {bench_source} is an assumption about this bench that the fit could not verify "
                "({model_check_note}): identify the bench (eol-cal bench identify, docs/bench-identify.md) and "
                "fit with the file it writes, or set {key} = 1 to accept the assumption"),
)
BY_KEY: dict[str, Limit] = {lim.key: lim for lim in LIMITS}
#: the limit keys, in table order
LIMIT_KEYS: tuple[str, ...] = tuple(BY_KEY)
#: keys a limits file may leave out, and their value then (None: no limit, not judged)
OPTIONAL_DEFAULTS: dict[str, float | None] = {lim.key: lim.default for lim in LIMITS  # type: ignore[misc]
                                              if lim.default != REQUIRED}


def limit_on(quantity: str) -> Limit | None:
    """The row that bounds ``quantity`` (a :class:`Measured` field or lot column), None without one."""
    return next((lim for lim in LIMITS if lim.quantity == quantity), None)


@dataclass(frozen=True)
class VariantLimits:
    """The limits of one product variant.

    Attributes
    ----------
    variant : str
    values : mapping of limit key -> float or None
        Every key of :data:`LIMITS` (None: off); the limits file's units.
    source : str
        The limits file.
    estimator : str
        The estimator options the variant's blocks carry (a label: ``best``, ``paper``, names).
    """

    variant: str
    values: Mapping[str, float | None]
    source: str = "<memory>"
    estimator: str = DEFAULT_PRESET

    @classmethod
    def of(cls, variant: str, *, source: str = "<memory>", estimator: str = DEFAULT_PRESET,
           **values: float | None) -> VariantLimits:
        """Limits from keyword values (missing optional keys take their default; a missing required
        key or an unknown one is a :class:`ValueError`)."""
        unknown = set(values) - set(BY_KEY)
        if unknown:
            raise ValueError(f"unknown limit keys {sorted(unknown)}")
        missing = [lim.key for lim in LIMITS if lim.key not in values and lim.default == REQUIRED]
        if missing:
            raise ValueError(f"missing limit keys {missing}")
        full = {lim.key: values.get(lim.key, lim.default) for lim in LIMITS}
        return cls(variant, {k: None if v is None else float(v) for k, v in full.items()}, source, estimator)

    def __getattr__(self, name: str) -> float | None:
        # lim.KEY: the value of a limit key (tests and interactive use)
        values = self.__dict__.get("values")
        if values is not None and name in values:
            return values[name]
        raise AttributeError(name)

    def value(self, key: str) -> float | None:
        """The limit's value (None: off, or not recorded)."""
        return self.values.get(key)

    @property
    def estimator_options(self) -> int:
        """The estimator option bits (contract flags bits 2-5) the variant's blocks carry."""
        return parse_options(self.estimator, self.source, f"variant.{self.variant}.estimator")

    def to_dict(self) -> dict[str, Any]:
        """``variant``, every limit key, ``source``, ``estimator`` (the record's ``limits``)."""
        return {"variant": self.variant, **self.values, "source": self.source, "estimator": self.estimator}

    def ci_limits(self) -> CiLimits:
        """The interval limits as the fit's own :class:`~eol_cal.analysis.intervals.CiLimits`."""
        # a limit that is off keeps the fit's own default (the model check's p-value: judged all the same)
        return CiLimits(**{lim.ci: v for lim in LIMITS if lim.ci and (v := self.values[lim.key]) is not None})


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
        unknown = set(table) - set(BY_KEY) - {"estimator"}
        if unknown:
            raise InputError(file, f"{where}.{sorted(unknown)[0]}", f"unknown key; known: {', '.join(BY_KEY)}, estimator")
        values: dict[str, float | None] = {}
        for lim in LIMITS:
            if lim.key not in table:
                if lim.default == REQUIRED:
                    raise InputError(file, f"{where}.{lim.key}", f"missing ({lim.unit})")
                values[lim.key] = lim.default  # type: ignore[assignment]
                continue
            v = table[lim.key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InputError(file, f"{where}.{lim.key}", f"{v!r} is not a finite number ({lim.unit})")
            lo, hi = lim.bounds
            if not lo <= v <= hi:
                raise InputError(file, f"{where}.{lim.key}", f"{v} outside {lo:g} ... {hi:g} {lim.unit}")
            values[lim.key] = float(v)
        estimator = options_label(parse_options(table.get("estimator", DEFAULT_PRESET), file, f"{where}.estimator"))
        out[name] = VariantLimits(variant=name, values=values, source=file, estimator=estimator)
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
    """What the cycle measured on one motor, as the limits see it (NaN: not measured).

    Attributes
    ----------
    k6 : float
        Load-proportional 6th-harmonic coefficient, magnitude (N*m/A).
    ci_k6 : float
        Its 95 % interval half-width (N*m/A).
    ci_phase_k6_deg : float
        95 % interval of phase_k6 (deg).
    ci_c6_nm : float
        Cogging phasor error bound max(ci95(c6), c6 * ci95(phase_c6)) (N*m).
    fit_r2 : float
        Fit R^2 (1).
    fit_rms_nm : float
        Fit residual RMS (N*m).
    pp_before_pct, pp_after_pct : float
        Filtered p-p ripple at the operating point before and with compensation (%).
    hall_deviation_deg : float
        Largest |measured - nominal| hall boundary angle (deg, electrical); NaN when the table
        could not be measured (``hall_source`` says why).
    hall_source : str
        The fit's ``hall_angle.source``.
    pp_after_no_mech1_pct : float
        ``pp_after_pct`` with the mechanical order 1 (rotor unbalance) taken out (%).
    mech1_after_nm : float
        Amplitude of the mechanical order 1 in the compensated capture (N*m).
    model_check_p : float
        The fit's model check: p-value of the speed bands' agreement (1; NaN: not checked,
        ``model_check_note`` says why).
    model_check_note : str
        The model check's note.
    bench_assumed : float
        1 when the fit's bench file was an assumption the data could not verify
        (:func:`bench_assumed`), else 0 (1).
    bench_source : str
        Where the fit's bench file was read from.
    """

    k6: float = math.nan
    ci_k6: float = math.nan
    ci_phase_k6_deg: float = math.nan
    ci_c6_nm: float = math.nan
    fit_r2: float = math.nan
    fit_rms_nm: float = math.nan
    pp_before_pct: float = math.nan
    pp_after_pct: float = math.nan
    hall_deviation_deg: float = math.nan
    hall_source: str = "not measured"
    pp_after_no_mech1_pct: float = math.nan
    mech1_after_nm: float = math.nan
    model_check_p: float = math.nan
    model_check_note: str = "not in the record"
    bench_assumed: float = 0.0
    bench_source: str = "not in the record"

    @property
    def improvement_pct(self) -> float:
        """100 * (before - after) / before (%)."""
        if not (self.pp_before_pct > 0.0) or not math.isfinite(self.pp_after_pct):
            return math.nan
        return 100.0 * (self.pp_before_pct - self.pp_after_pct) / self.pp_before_pct

    @property
    def ci_k6_rel(self) -> float:
        """The 95 % interval of k6 as a fraction of k6 (1; infinite for k6 0)."""
        return ci_rel(self.ci_k6, self.k6)

    @classmethod
    def of_fit(cls, res: MotorResult) -> Measured:
        """The fit's part (k6, intervals, R^2, RMS, hall deviation) of a usable fit.

        Raises
        ------
        ValueError
            The fit is not usable (no estimates).
        """
        e = res.estimates
        if e is None:
            raise ValueError(f"motor {res.serial}: fit status {res.status!r} has no estimates")
        ci_c6 = ci_phasor(float(e.c6.ci95), e.c6.value, float(e.phase_c6.ci95))
        hall = res.hall_angle or {"source": "not in the record", "deviation_deg": []}
        measured = hall["source"] == "measured"
        return cls(
            k6=abs(float(e.k6.value)), ci_k6=float(e.k6.ci95),
            # no phase interval (c6 left out on one load point, analysis.result.unseparated): unbounded
            ci_phase_k6_deg=math.degrees(math.inf if e.phase_k6.ci95 is None else e.phase_k6.ci95),
            ci_c6_nm=ci_c6, fit_r2=float(res.fit["r2"]), fit_rms_nm=float(res.fit["rms"]),
            hall_deviation_deg=max(abs(float(d)) for d in hall["deviation_deg"]) if measured else math.nan,
            hall_source=str(hall["source"]),
            **_model_check_of(res.model_check),
            bench_assumed=float(bench_assumed(res.model_check)),
            bench_source=_bench_source(res.model.get("bench")),
        )

    def with_ripple(self, pp_before_pct: float, pp_after_pct: float, pp_after_no_mech1_pct: float,
                    mech1_after_nm: float = math.nan) -> Measured:
        """These values and the ripple at the operating point (%, the order-1 amplitude N*m)."""
        return dataclasses.replace(self, pp_before_pct=pp_before_pct, pp_after_pct=pp_after_pct,
                                   pp_after_no_mech1_pct=pp_after_no_mech1_pct, mech1_after_nm=mech1_after_nm)


def _model_check_of(check: Mapping[str, Any] | None) -> dict[str, Any]:
    """``model_check_p`` and ``model_check_note`` of a fit's ``model_check`` object."""
    if check is None:
        return {}
    p = check.get("p_value")
    # bands that agree but could not have seen a resonance, on a bench file nobody identified: no
    # p-value that the model check's minimum p-value limit could pass on (its message gives the note)
    if p is None or check.get("status") == "insensitive":
        return {"model_check_p": math.nan, "model_check_note": str(check.get("note", ""))}
    return {"model_check_p": float(p), "model_check_note": str(check.get("note", ""))}


def bench_assumed(check: Mapping[str, Any] | None) -> bool:
    """The fit's bench file was an assumption the data could not verify: neither identified on the
    bench nor the simulated plant's own (the check's ``bench`` is ``assumed``,
    :func:`eol_cal.analysis.fit.model_check.bench_provenance`), and the speed bands could not vouch
    for it (``insensitive``, ``not checked``). A check without ``bench`` (results before it) counts
    only when ``insensitive``."""
    if check is None:
        return False
    status = check.get("status")
    if "bench" not in check:
        return status == "insensitive"
    return check["bench"] == "assumed" and status in ("insensitive", "not checked")


def _bench_source(bench: Any) -> str:
    """Where the fit's bench file (its result's ``model.bench``) was read from, in words."""
    if isinstance(bench, Mapping):
        return str(bench.get("source") or bench.get("name") or "unnamed")
    return "none (rigid coupling)" if bench == "rigid" else str(bench)


@dataclass(frozen=True)
class LimitCheck:
    """One limit against what was measured, as the run record keeps it.

    Attributes
    ----------
    key, quantity, title, unit, sense, stage
        As the :class:`Limit` row (kept in the record: it renders without the table of its time).
    value : float
        The measured value in ``unit`` (NaN: not measured).
    limit : float
        The limit in ``unit``.
    passed : bool or None
        The limit is met; None: not judged (the cycle ended before the check's stage).
    reason : str
        Why it is not met (empty when it is, or when not judged).
    """

    key: str
    quantity: str
    title: str
    unit: str
    sense: str
    stage: str
    value: float
    limit: float
    passed: bool | None
    reason: str = ""

    @property
    def margin(self) -> float:
        """How far inside the limit the value is (``unit``; negative: outside, NaN: not measured)."""
        return self.limit - self.value if self.sense == "max" else self.value - self.limit

    @property
    def status(self) -> str:
        """``pass``, ``fail`` or ``not judged``."""
        return "not judged" if self.passed is None else ("pass" if self.passed else "fail")


def _reason(lim: Limit, value: float, limit: float, m: Measured) -> str:
    from eol_cal.rendering.display import display_unit

    if math.isnan(value):
        return lim.missing.format(title=lim.title, key=lim.key, **dataclasses.asdict(m))
    if lim.fails is not None:
        return lim.fails.format(title=lim.title, key=lim.key, **dataclasses.asdict(m))
    unit, factor = display_unit(lim.unit)
    unit_text = "" if unit == "1" else f" {unit}"
    word = "exceeds" if lim.sense == "max" else "below"
    return f"{lim.title} = {value * factor:.4g}{unit_text} {word} {lim.key} = {limit * factor:g}{unit_text}"


def check(lim: Limit, limit: float, m: Measured | None) -> LimitCheck:
    """One limit row at ``limit`` against ``m`` (None: not judged). NaN never meets a limit."""
    if m is None:
        return LimitCheck(lim.key, lim.quantity, lim.title, lim.unit, lim.sense, lim.stage, math.nan, float(limit), None)
    value = float(getattr(m, lim.quantity))
    ok = within(value, limit, lim.sense)
    return LimitCheck(lim.key, lim.quantity, lim.title, lim.unit, lim.sense, lim.stage, value, float(limit), ok,
                      "" if ok else _reason(lim, value, limit, m))


def judge(m: Measured | None, lim: VariantLimits, stage: str) -> list[LimitCheck]:
    """Every limit of ``stage`` that ``lim`` sets, against ``m`` (None: not judged), table order;
    a limit that is off is no check."""
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}")
    return [check(row, v, m) for row in LIMITS if row.stage == stage and (v := lim.value(row.key)) is not None]


def all_checks(judged: Mapping[str, list[LimitCheck]], lim: VariantLimits) -> list[LimitCheck]:
    """The checks of every stage in table order: those ``judged`` (by stage), the others not judged."""
    by_key = {c.key: c for stage in STAGES for c in (judged.get(stage) or judge(None, lim, stage))}
    return [by_key[row.key] for row in LIMITS if row.key in by_key]


def failed(checks: list[LimitCheck]) -> list[str]:
    """The reasons of the checks that failed, in their order."""
    return [c.reason for c in checks if c.passed is False]


def verdict(m: Measured, lim: VariantLimits) -> tuple[str, list[str]]:
    """``("pass", [])`` or ``("fail", reasons)`` of a fully measured motor against ``lim`` (every stage)."""
    reasons = [r for stage in STAGES for r in failed(judge(m, lim, stage))]
    return ("fail", reasons) if reasons else ("pass", [])
