"""The interval limits of a fit: their values (:class:`CiLimits`), the quantities they bound and
the comparison, each written once.

The fit judges its status by them (:func:`eol_cal.analysis.result.judge`: ``ci_too_wide``), and
the station's limits table judges the same quantities by its rows that set them
(:data:`eol_cal.records.limits.LIMITS`, ``ci=``; :meth:`~eol_cal.records.limits.VariantLimits.ci_limits`
hands a variant's values to the fit): both measure with :func:`ci_rel` and :func:`ci_phasor`
and compare with :func:`within`. A light module: ``eol-cal fit`` shows the defaults in its help.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class CiLimits:
    """Widest 95 % intervals a usable fit may have.

    Attributes
    ----------
    k6_rel : float
        ci95(k6) / k6 (fraction, :func:`ci_rel`).
    phase_k6_deg : float
        ci95(phase_k6) (deg).
    c6_nm : float
        Cogging phasor error bound max(ci95(c6), c6 * ci95(phase_c6)) (N*m, :func:`ci_phasor`); used
        when c6 is fitted.
    model_p : float
        The least p-value of the speed bands' agreement (:mod:`eol_cal.analysis.fit.model_check`):
        below it the data contradict the model and the motor's status is ``model_mismatch``.
    """

    k6_rel: float = 0.05
    phase_k6_deg: float = 3.0
    c6_nm: float = 0.002
    model_p: float = 0.001

    def to_dict(self) -> dict[str, float]:
        return {"k6_rel": self.k6_rel, "phase_k6_deg": self.phase_k6_deg, "c6_nm": self.c6_nm, "model_p": self.model_p}


def ci_rel(ci95: float, value: float) -> float:
    """An amplitude's 95 % interval relative to it: ``ci95 / |value|`` (1; infinite for a value of
    0, NaN for an unknown one)."""
    amp = abs(value)
    return ci95 / amp if amp > 0 else (math.nan if math.isnan(amp) else math.inf)


def ci_phasor(ci95: float, value: float, phase_ci95: float) -> float:
    """The error bound of a phasor ``value * exp(i phase)`` from its amplitude's and phase's 95 %
    intervals: ``max(ci95, |value| * phase_ci95)`` (the amplitude's unit; phase in rad)."""
    return max(ci95, abs(value) * phase_ci95)


def within(value: float, limit: float, sense: str = "max") -> bool:
    """``value`` meets ``limit``: at most it (``max``) or at least it (``min``); NaN meets none."""
    return bool(value <= limit) if sense == "max" else bool(value >= limit)
