"""Statistical process control that states its n: the minimum-n rule, circular statistics of
phases, frozen control lines and Nelson's run rules.

Pure functions, arrays in, numbers out; the definitions are written out in ``docs/spc.md``.

- **Minimum n.** A capability index or a control limit from a handful of values is noise that
  looks like a number. :func:`gate` gives a figure only when ``n >= min_n``
  (:data:`DEFAULT_MIN_N` = 25 by default), else ``None`` with the reason ``"n = 7 < 25"``.
- **Circular quantities** (the phases ``phase_k6``, ``phase_c6``: angles, rad). The mean
  resultant ``R e^{i mu} = mean(e^{i theta})`` gives the circular mean ``mu`` and the circular
  standard deviation ``sqrt(-2 ln R)`` (Mardia's definition, the one ``scipy.stats.circstd``
  uses; for a tight set it tends to the linear sd). Capability of a phase needs a two-sided
  limit around a nominal and is taken on the wrapped deviation ``wrap_pi(theta - nominal)``.
- **Frozen control lines.** :func:`freeze_line` takes a centre line and a sigma from a baseline
  period (individuals chart: ``sigma = MRbar / d2``, d2 = 1.128; for a phase the moving ranges
  are of the wrapped differences and the centre is the circular mean) once, so later runs are
  judged against it and a drifting process cannot move its own limits.
- **Run rules**: Nelson's rules 1, 2, 3 (the trend), 5 and 6 (:data:`RULES`, his numbers),
  each on one side of the centre line (the trend: rising or falling).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Iterable, Sequence

import numpy as np

from eol_cal.lot.stats import D2, D4, Capability, capability
from eol_cal.numerics.wrap import wrap_pi

#: the smallest n that gives a capability index or a control limit (``lot stats --min-n``)
DEFAULT_MIN_N = 25
#: the lot's quantities that are angles (rad): circular statistics, frozen and judged on the circle
CIRCULAR = frozenset({"phase_k6", "phase_c6"})
#: the lot's quantities that are amplitudes (magnitudes, never below zero): an LCL below zero is
#: drawn and judged at zero, and says so
NATURAL_ZERO = frozenset({"k6", "c6", "pp_before_pct", "pp_after_pct", "fit_rms_nm"})
#: the least mean resultant length R of a phase's baseline that gets control limits: below it the
#: angles spread over so much of the circle (circular sd > 38 deg) that centre +- 3 sigma would
#: wrap onto itself; the line says so instead of giving limits
MIN_RESULTANT = 0.8


def natural_floor(key: str) -> float | None:
    """The natural lower bound of a lot quantity (0 for an amplitude; None: none)."""
    return 0.0 if key in NATURAL_ZERO else None

# --------------------------------------------------------------------------- minimum n


@dataclass(frozen=True)
class Gated:
    """A figure with the n it came from: ``value``, or ``None`` and the ``reason`` why not."""

    value: float | None
    n: int
    reason: str | None = None

    def text(self, digits: int = 3) -> str:
        """The value (``digits`` significant figures), or the reason (``"n = 7 < 25"``)."""
        return f"{self.value:.{digits}g}" if self.value is not None else str(self.reason)


def n_reason(n: int, min_n: int = DEFAULT_MIN_N) -> str | None:
    """Why ``n`` values are too few (``"n = 7 < 25"``), or None when ``n >= min_n``."""
    return None if n >= min_n else f"n = {n} < {min_n}"


def gate(value: float | None, n: int, min_n: int = DEFAULT_MIN_N, undefined: str = "not defined") -> Gated:
    """``value`` when ``n >= min_n`` and it is a finite number; else None with the reason (too
    few values first, then ``undefined``: no spread, no limit...)."""
    reason = n_reason(n, min_n)
    if reason is None and (value is None or not math.isfinite(value)):
        reason = undefined
    return Gated(None if reason else float(value), n, reason)  # type: ignore[arg-type]


def gated_capability(x: Sequence[float] | np.ndarray, lsl: float | None, usl: float | None,
                     min_n: int = DEFAULT_MIN_N) -> dict[str, Gated]:
    """``cp``, ``cpk``, ``ppk`` of the finite values of ``x`` (time order) against the limits,
    each gated by :func:`gate` (:func:`eol_cal.lot.stats.capability` gives the numbers)."""
    a = _finite(x)
    c = capability(a, lsl=lsl, usl=usl)
    if len(a) > 1 and not c.sigma_overall > 1e-12 * float(np.abs(a).max()):
        # equal values: the sd is rounding noise (1e-16 of the mean), not a spread to divide by
        c = Capability(lsl, usl, math.nan, math.nan, math.nan, math.nan, math.nan)
    return _gated_indices(c, len(a), min_n)


def _gated_indices(c: Capability, n: int, min_n: int) -> dict[str, Gated]:
    flat = "no spread (all values equal)" if n > 1 and not c.sigma_overall > 0 else "not defined"
    return {"cp": gate(c.cp, n, min_n, "needs both limits" if c.lsl is None or c.usl is None else flat),
            "cpk": gate(c.cpk, n, min_n, "no limit" if c.lsl is None and c.usl is None else flat),
            "ppk": gate(c.ppk, n, min_n, "no limit" if c.lsl is None and c.usl is None else flat)}


def _finite(x: Iterable[float]) -> np.ndarray:
    a = np.asarray(x if isinstance(x, np.ndarray) else list(x), dtype=float)
    return a[np.isfinite(a)]


# --------------------------------------------------------------------------- circular


@dataclass(frozen=True)
class CircularSummary:
    """Circular statistics of angles (rad).

    Attributes
    ----------
    count : int
        Finite angles.
    mean : float
        Circular mean in (-pi, pi] (rad); NaN when there are none or they cancel (R = 0).
    resultant : float
        Mean resultant length R in [0, 1] (1: all equal).
    sd : float
        Circular standard deviation ``sqrt(-2 ln R)`` (rad); infinite for R = 0.
    """

    count: int
    mean: float
    resultant: float
    sd: float


def circular_summary(theta: Iterable[float]) -> CircularSummary:
    """:class:`CircularSummary` of the finite angles ``theta`` (rad)."""
    a = _finite(theta)
    if not len(a):
        return CircularSummary(0, math.nan, math.nan, math.nan)
    c, s = float(np.cos(a).mean()), float(np.sin(a).mean())
    r = min(1.0, math.hypot(c, s))  # rounding may put R of equal angles a hair above 1
    if r <= 1e-12:  # the vectors cancel (to rounding): no direction
        return CircularSummary(int(len(a)), math.nan, 0.0, math.inf)
    mean, sd = math.atan2(s, c), math.sqrt(max(0.0, -2.0 * math.log(r)))
    return CircularSummary(int(len(a)), float(wrap_pi(mean)), r, sd)


def circular_mean(theta: Iterable[float]) -> float:
    """Circular mean ``atan2(mean(sin), mean(cos))`` of the angles (rad, in (-pi, pi])."""
    return circular_summary(theta).mean


def circular_sd(theta: Iterable[float]) -> float:
    """Circular standard deviation ``sqrt(-2 ln R)`` of the angles (rad)."""
    return circular_summary(theta).sd


def circular_histogram(theta: Iterable[float], bins: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Counts of the angles in ``bins`` equal sectors of the circle, and the sector edges (rad,
    ``bins + 1`` of them from -pi to pi; an angle is counted once, after wrapping into
    [-pi, pi))."""
    a = _finite(theta)
    edges = np.linspace(-math.pi, math.pi, bins + 1)
    w = np.asarray(wrap_pi(a), dtype=float)
    w = np.where(w >= math.pi, -math.pi, w)  # pi and -pi are one angle: the first sector
    idx = np.clip(np.floor((w + math.pi) / (2.0 * math.pi) * bins).astype(int), 0, bins - 1)
    return np.bincount(idx, minlength=bins), edges


def wrapped_deviation(theta: Sequence[float] | np.ndarray, nominal: float) -> np.ndarray:
    """``wrap_pi(theta - nominal)``: each angle's signed deviation from ``nominal`` (rad, in
    (-pi, pi]); NaN stays NaN."""
    return np.asarray(wrap_pi(np.asarray(theta, dtype=float) - nominal), dtype=float)


def circular_capability(theta: Sequence[float] | np.ndarray, nominal: float, lower: float, upper: float) -> Capability:
    """Cp, Cpk, Ppk of angles (rad, time order) against the two-sided limit
    ``nominal - lower .. nominal + upper`` (``lower``, ``upper`` > 0, rad): the linear indices of
    :func:`eol_cal.lot.stats.capability` on :func:`wrapped_deviation` (the limits ``-lower`` and
    ``+upper``). A phase has no capability against a one-sided limit."""
    if not (lower > 0.0 and upper > 0.0 and lower + upper < 2.0 * math.pi):
        raise ValueError(f"a phase limit needs 0 < lower, upper and lower + upper < 2 pi (got {lower}, {upper})")
    return capability(wrapped_deviation(theta, nominal), lsl=-lower, usl=upper)


# --------------------------------------------------------------------------- frozen lines


@dataclass(frozen=True)
class ControlLine:
    """A frozen individuals chart of one quantity (units of the values it was made from).

    Attributes
    ----------
    n : int
        Values it was made from.
    center : float or None
        Centre line (mean; circular mean for a phase); None with ``reason`` when not made.
    sigma : float or None
        ``MRbar / d2`` (short-term sigma).
    mr_center : float or None
        ``MRbar``, the mean moving range (of the wrapped differences for a phase).
    circular : bool
        The values are angles (rad): judged on the wrapped deviation from ``center``.
    reason : str or None
        Why there are no limits (``"n = 7 < 25"``, no spread).
    lower_bound : float or None
        The quantity's natural lower bound (0 for an amplitude, :data:`NATURAL_ZERO`): the LCL is
        never below it (:attr:`note` says when it is held there).
    """

    n: int
    center: float | None
    sigma: float | None
    mr_center: float | None
    circular: bool = False
    reason: str | None = None
    lower_bound: float | None = None

    @property
    def ucl(self) -> float | None:
        """``center + 3 sigma``."""
        return None if self.center is None or self.sigma is None else self.center + 3.0 * self.sigma

    @property
    def lcl(self) -> float | None:
        """``center - 3 sigma``, held at the natural lower bound when it would lie below it."""
        if self.center is None or self.sigma is None:
            return None
        x = self.center - 3.0 * self.sigma
        return x if self.lower_bound is None else max(self.lower_bound, x)

    @property
    def note(self) -> str | None:
        """What a reader must know about the limits (the LCL held at the natural zero), or None."""
        if self.center is None or self.sigma is None or self.lower_bound is None:
            return None
        if self.center - 3.0 * self.sigma < self.lower_bound:
            return (f"LCL at the natural zero: centre - 3 sigma = {self.center - 3.0 * self.sigma:.4g} lies below "
                    f"{self.lower_bound:g}, which the quantity cannot take")
        return None

    @property
    def mr_ucl(self) -> float | None:
        """``D4 MRbar`` (3.267 MRbar): the moving range's upper limit."""
        return None if self.mr_center is None else D4 * self.mr_center

    def deviation(self, x: Sequence[float] | np.ndarray) -> np.ndarray:
        """``x - center`` (wrapped into (-pi, pi] for a phase); NaN stays NaN."""
        if self.center is None:
            raise ValueError(f"no control line: {self.reason}")
        if self.circular:
            return wrapped_deviation(x, self.center)
        return np.asarray(x, dtype=float) - self.center


def freeze_line(x: Sequence[float] | np.ndarray, circular: bool = False, min_n: int = DEFAULT_MIN_N,
                lower_bound: float | None = None) -> ControlLine:
    """The :class:`ControlLine` of the finite values of ``x`` (time order): centre the mean (a
    phase: the circular mean), ``sigma = MRbar / 1.128`` with the moving ranges ``|x[i] - x[i-1]|``
    (a phase: of the wrapped differences). Fewer than ``min_n`` values, or no spread, give a line
    without limits and the reason; so does a phase whose angles spread round the circle (mean
    resultant length below :data:`MIN_RESULTANT`, or ``3 sigma`` of 180 deg or more: the limits
    would overlap on the circle). ``lower_bound``: the quantity's natural bound (the LCL's floor)."""
    a = _finite(x)
    n = int(len(a))
    reason = n_reason(n, min_n)
    if reason is None and n < 2:
        reason = f"n = {n}: no moving range"
    if reason is not None:
        return ControlLine(n, None, None, None, circular, reason, lower_bound)
    d = np.diff(a)
    mr = np.abs(np.asarray(wrap_pi(d), dtype=float) if circular else d)
    mr_bar = float(mr.mean())
    if not mr_bar > 0.0:
        return ControlLine(n, None, None, None, circular, "no spread (all values equal)", lower_bound)
    center = circular_mean(a) if circular else float(a.mean())
    if not math.isfinite(center):
        return ControlLine(n, None, None, None, circular, "no circular mean (the angles cancel)", lower_bound)
    if circular:
        r = circular_summary(a).resultant
        if r < MIN_RESULTANT:
            return ControlLine(n, None, None, None, circular, f"the angles spread round the circle (R = {r:.2f} < "
                                                              f"{MIN_RESULTANT}): no control limits", lower_bound)
        if 3.0 * mr_bar / D2 >= math.pi:
            return ControlLine(n, None, None, None, circular, f"3 sigma = {math.degrees(3 * mr_bar / D2):.0f} deg "
                                                              ">= 180 deg: limits would overlap on the circle",
                               lower_bound)
    return ControlLine(n, center, mr_bar / D2, mr_bar, circular, None, lower_bound)


# --------------------------------------------------------------------------- run rules

#: Nelson's rules judged (his numbers): rule -> (points that must lie beyond, window, beyond how
#: many sigma, the rule in words). Rule 3 (the trend) has no zone: ``window`` points in a row
#: each higher (or lower) than the one before.
RULES: dict[int, tuple[int, int, float, str]] = {
    1: (1, 1, 3.0, "1 point beyond 3 sigma"),
    2: (9, 9, 0.0, "9 points in a row on one side of the centre line"),
    3: (6, 6, math.nan, "6 points in a row steadily rising or falling (a trend)"),
    5: (2, 3, 2.0, "2 of 3 points beyond 2 sigma on one side"),
    6: (4, 5, 1.0, "4 of 5 points beyond 1 sigma on one side"),
}
#: the rules judged unless asked (all of :data:`RULES`)
DEFAULT_RULES = tuple(RULES)
TREND = 3


@dataclass(frozen=True)
class Violation:
    """A run rule that fired.

    Attributes
    ----------
    rule : int
        Nelson's rule (:data:`RULES`).
    side : int
        +1 above the centre line (the trend: rising), -1 below (falling).
    runs : tuple of int
        Indices (into the series judged) of the points that make the pattern: the points beyond
        the rule's zone in every window where it fired (the trend: every point of the run),
        overlapping or adjacent windows merged (two points in a row beyond 3 sigma are one
        violation of rule 1).
    quantity : str or None
        What was judged.
    """

    rule: int
    side: int
    runs: tuple[int, ...]
    quantity: str | None = None

    @property
    def side_word(self) -> str:
        """``above``/``below`` the centre line; the trend's ``rising``/``falling``."""
        if self.rule == TREND:
            return "rising" if self.side > 0 else "falling"
        return "above" if self.side > 0 else "below"

    @property
    def text(self) -> str:
        """The rule in words, with the side."""
        return f"rule {self.rule}: {RULES[self.rule][3]} ({self.side_word})"


def _windows(beyond: np.ndarray, need: int, window: int, span: int = 0) -> list[set[int]]:
    """The points of each run of windows (``window`` long) holding ``need`` points ``beyond``,
    overlapping or adjacent windows merged; ``span`` widens each window back (the trend's first
    point, which starts the first rise)."""
    counts = np.convolve(beyond.astype(np.intp), np.ones(window, dtype=np.intp), mode="valid")
    ends = np.flatnonzero(counts >= need) + window - 1
    groups: list[tuple[int, set[int]]] = []  # (last window end, points)
    for e in ends.tolist():
        pts = {int(i) for i in range(e - window + 1, e + 1) if beyond[i]}
        pts |= {int(i) - k for i in pts for k in range(1, span + 1)}
        if groups and e - window + 1 <= groups[-1][0] + 1:
            groups[-1] = (e, groups[-1][1] | pts)
        else:
            groups.append((e, pts))
    return [pts for _e, pts in groups]


def run_rules(x: Sequence[float] | np.ndarray, center: float, sigma: float, quantity: str | None = None,
              rules: Iterable[int] = DEFAULT_RULES) -> list[Violation]:
    """Nelson's rules (:data:`RULES`) that ``x`` (time order) breaks against a frozen centre line
    and sigma (the values' units).

    Non-finite values (runs without the quantity) are left out of the windows; the indices in
    each :class:`Violation` are positions in ``x``. A point exactly on a zone's edge is not
    beyond it; two equal points in a row break a trend. Violations come sorted by first run,
    then rule.
    """
    if not (math.isfinite(center) and math.isfinite(sigma) and sigma > 0.0):
        raise ValueError(f"run rules need a finite centre and sigma > 0 (got {center}, {sigma})")
    xa = np.asarray(x, dtype=float)
    where = np.flatnonzero(np.isfinite(xa))
    z = (xa[where] - center) / sigma
    out: list[Violation] = []
    for rule in rules:
        need, window, zone, _text = RULES[rule]
        for side in (1, -1):
            if rule == TREND:  # window - 1 steps in a row the same way: the points from the first
                steps = np.concatenate(([False], side * np.diff(z) > 0))
                groups = _windows(steps, window - 1, window - 1, span=1)
            else:
                groups = _windows(side * z > zone, need, window)
            out.extend(Violation(rule, side, tuple(int(where[i]) for i in sorted(pts)), quantity) for pts in groups)
    return sorted(out, key=lambda v: (v.runs[0], v.rule, -v.side))


def judge(x: Sequence[float] | np.ndarray, line: ControlLine, quantity: str | None = None,
          rules: Iterable[int] = DEFAULT_RULES) -> list[Violation]:
    """:func:`run_rules` of ``x`` against a frozen :class:`ControlLine` (a phase on its wrapped
    deviation from the centre). A line without limits judges nothing (empty list)."""
    if line.center is None or line.sigma is None:
        return []
    return run_rules(line.deviation(x), 0.0, line.sigma, quantity, rules)
