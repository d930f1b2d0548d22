"""The type-1 gauge study: one reference part (the master motor) measured ``n`` times.

Definitions (VDA 5 / Bosch booklet 10 convention; ``docs/spc.md``):

- ``bias = mean - x_ref``; ``s`` the sample standard deviation (ddof 1): the repeatability.
- ``Cg = (K T) / (L s)`` and ``Cgk = (K T / 2 - |bias|) / (L s / 2)`` with the tolerance width
  ``T = USL - LSL``, ``K = 0.2`` (20 % of the tolerance) and ``L = 4`` (four standard
  deviations: the study variation +-2 s): ``Cg = 0.2 T / (4 s)``,
  ``Cgk = (0.1 T - |bias|) / (2 s)``. Minitab's default is ``L = 6`` (+-3 s); ``l`` chooses.
  The usual acceptance is ``Cg >= 1.33`` and ``Cgk >= 1.33``.
- ``%Var(repeatability) = 100 L s / T``: the share of the tolerance the study variation spans.
- The bias's t-test: ``t = bias / (s / sqrt(n))``, two-sided p-value from Student's t with
  ``n - 1`` degrees of freedom (H0: bias = 0).
- A phase (rad) is measured on the circle: each value is taken as ``x_ref + wrap_pi(x - x_ref)``
  (its wrapped deviation from the reference) before the linear figures above.

Fewer than ``min_n`` measurements (default 25) give no Cg/Cgk, with the reason
(:func:`eol_cal.lot.spc.gate`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Sequence

import numpy as np

from eol_cal.lot.spc import DEFAULT_MIN_N, Gated, circular_mean, gate, n_reason, wrapped_deviation

#: share of the tolerance the study variation may take (20 %)
K_DEFAULT = 0.2
#: study variation in standard deviations (4: +-2 s; some use 6)
L_DEFAULT = 4.0
#: Cg and Cgk at or above this: the measurement is capable
CAPABLE = 1.33


@dataclass(frozen=True)
class Type1Study:
    """A type-1 gauge study of one quantity (the quantity's units throughout).

    Attributes
    ----------
    quantity, unit : str
        What was measured, and its unit.
    values : tuple of float
        The measurements in run order (a phase: reference + wrapped deviation).
    n : int
        Finite measurements.
    reference : float or None
        ``x_ref``, the reference value (None: no bias, no Cgk).
    reference_source : str
        Where it came from (``"given"``, ``"run RUN_ID"``, ``"none"``).
    tolerance : float or None
        ``T`` (None: no tolerance, no Cg/Cgk).
    k, l : float
        The convention (``K`` share of ``T``, ``L`` standard deviations).
    mean, sd, bias : float
        Mean, sample sd (repeatability), ``mean - reference``; NaN with fewer than 2 values (the
        bias: without a reference).
    t, p_value : float
        The bias's t statistic and two-sided p-value (NaN when ``sd`` is 0, n < 2 or there is no
        reference).
    cg, cgk : Gated
        The indices, or None with the reason.
    var_repeatability_pct : Gated
        ``100 L s / T``.
    circular : bool
        The quantity is a phase.
    """

    quantity: str
    unit: str
    values: tuple[float, ...]
    n: int
    reference: float | None
    reference_source: str
    tolerance: float | None
    k: float
    l: float
    mean: float
    sd: float
    bias: float
    t: float
    p_value: float
    cg: Gated
    cgk: Gated
    var_repeatability_pct: Gated
    circular: bool = False

    @property
    def capable(self) -> bool | None:
        """``Cg >= 1.33 and Cgk >= 1.33``; None when either is not given."""
        if self.cg.value is None or self.cgk.value is None:
            return None
        return self.cg.value >= CAPABLE and self.cgk.value >= CAPABLE

    @property
    def band(self) -> tuple[float, float] | None:
        """``x_ref -+ K T / 2``: where the measurements of a capable gauge lie (the run chart's lines)."""
        if self.tolerance is None or self.reference is None:
            return None
        half = self.k * self.tolerance / 2.0
        return self.reference - half, self.reference + half


def type1_study(x: Sequence[float] | np.ndarray, reference: float | None, tolerance: float | None, *, quantity: str = "",
                unit: str = "", reference_source: str = "given", k: float = K_DEFAULT, l: float = L_DEFAULT,
                min_n: int = DEFAULT_MIN_N, circular: bool = False) -> Type1Study:
    """The :class:`Type1Study` of the measurements ``x`` (run order) of one reference part.

    Parameters
    ----------
    x : array of float
        The measurements (NaN: a run without the value, left out).
    reference : float or None
        ``x_ref``; for a phase in rad (None: repeatability and Cg only; a phase is then taken
        around its circular mean).
    tolerance : float or None
        ``T = USL - LSL`` (> 0); None gives bias and repeatability only.
    k, l : float
        Share of the tolerance (0.2) and study variation in sd (4; Minitab 6).
    min_n : int
        Fewer finite measurements give no indices.
    circular : bool
        ``x`` and ``reference`` are angles (rad).
    """
    if tolerance is not None and not (math.isfinite(tolerance) and tolerance > 0.0):
        raise ValueError(f"tolerance must be a positive number (got {tolerance})")
    if not (0.0 < k <= 1.0 and l > 0.0):
        raise ValueError(f"K must be in (0, 1] and L > 0 (got {k}, {l})")
    a = np.asarray(x, dtype=float)
    a = a[np.isfinite(a)]
    if circular and len(a):
        centre = reference if reference is not None else circular_mean(a)
        a = centre + wrapped_deviation(a, centre)
    n = int(len(a))
    nan = math.nan
    mean = float(a.mean()) if n else nan
    sd = float(a.std(ddof=1)) if n > 1 else nan
    bias = mean - reference if reference is not None else nan
    t = p = nan
    if n > 1 and sd > 0.0 and reference is not None:
        from scipy.stats import t as student_t

        t = bias / (sd / math.sqrt(n))
        p = float(2.0 * student_t.sf(abs(t), n - 1))
    why = _why_not(n, sd, tolerance, min_n)
    why_k = why or (None if reference is not None else "no reference")
    cg = cgk = var = nan
    if why is None:
        cg = k * tolerance / (l * sd)  # type: ignore[operator]
        var = 100.0 * l * sd / tolerance  # type: ignore[operator]
        if why_k is None:
            cgk = (k * tolerance / 2.0 - abs(bias)) / (l * sd / 2.0)  # type: ignore[operator]
    return Type1Study(quantity, unit, tuple(float(v) for v in a), n, None if reference is None else float(reference),
                      reference_source if reference is not None else "none",
                      None if tolerance is None else float(tolerance), k, l, mean, sd, bias, t, p,
                      _gated(cg, n, min_n, why), _gated(cgk, n, min_n, why_k), _gated(var, n, min_n, why), circular)


def _why_not(n: int, sd: float, tolerance: float | None, min_n: int) -> str | None:
    if (reason := n_reason(n, min_n)) is not None:
        return reason
    if tolerance is None:
        return "no tolerance"
    if not sd > 0.0:
        return "no spread (all measurements equal)"
    return None


def _gated(value: float, n: int, min_n: int, why: str | None) -> Gated:
    return Gated(None, n, why) if why else gate(value, n, min_n)
