"""Lot statistics of run records: summaries, process capability, control limits, yield, Pareto.

Pure functions over numbers in time order and over run records
(:class:`~eol_cal.records.record.RunRecord`). Definitions (the usual ones of statistical process
control, for individual measurements; the run kinds in ``docs/records.md``):

- ``sd``: sample standard deviation (ddof 1); percentiles by linear interpolation.
- Capability: ``sigma_within = mean(|x[i] - x[i-1]|) / d2`` with ``d2 = 1.128`` (the moving
  range of two, in time order) gives ``Cp = (USL - LSL) / (6 sigma_within)`` (both limits only)
  and ``Cpk = min((USL - mean) / (3 sigma_within), (mean - LSL) / (3 sigma_within))`` over the
  limits there are; ``Ppk`` is the same with the overall ``sd``. A one-sided limit (the
  variants' ``max_...`` / ``min_...``) gives the one-sided index.
- Individuals / moving-range chart: centre ``mean``, ``UCL/LCL = mean +- 2.66 MRbar``; the
  moving range's centre ``MRbar`` and ``UCL = 3.267 MRbar`` (``2.66 = 3 / d2``, ``3.267 = D4``).
- First-pass yield: serials whose first *measured* (``production``) run passed / serials with a
  measured run (a first measured run that ended in a station error is not a first pass: the
  motor had to be run again; a refusal before it measured nothing and does not count).
- Pareto: failed and error runs by cause, most frequent first, with the cumulative share.
  The causes of a run are :meth:`RunRecord.causes`: each limit key its failed checks name (or
  the fit's status), ``error in STEP`` for an error run; refusals have their own Pareto of
  refusal codes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING
from collections.abc import Iterable, Sequence

import numpy as np

from eol_cal.records.record import MEASURED_KIND

if TYPE_CHECKING:
    from eol_cal.records.record import RunRecord

D2 = 1.128  # E[moving range of two] / sigma
E2 = 3.0 / D2  # 2.66: individuals' limits from MRbar
D4 = 3.267  # moving range's upper limit from MRbar
PERCENTILES = (5.0, 50.0, 95.0)


@dataclass(frozen=True)
class Summary:
    """Count, mean, sample sd, min, max and :data:`PERCENTILES` of one quantity (its units)."""

    count: int
    mean: float
    sd: float
    minimum: float
    maximum: float
    percentiles: dict[float, float]


@dataclass(frozen=True)
class Capability:
    """Process capability against the limits there are (NaN: not defined).

    Attributes
    ----------
    lsl, usl : float or None
        Lower and upper specification limits (the quantity's units).
    sigma_within : float
        ``MRbar / 1.128`` (short-term sigma, time order).
    sigma_overall : float
        Sample standard deviation.
    cp, cpk, ppk : float
        See the module doc.
    """

    lsl: float | None
    usl: float | None
    sigma_within: float
    sigma_overall: float
    cp: float
    cpk: float
    ppk: float


@dataclass(frozen=True)
class ControlLimits:
    """Individuals and moving-range chart limits (the quantity's units)."""

    center: float
    ucl: float
    lcl: float
    mr_center: float
    mr_ucl: float

    def beyond(self, x: Sequence[float] | np.ndarray) -> list[int]:
        """Indices of the individuals outside ``[lcl, ucl]``."""
        return [i for i, v in enumerate(x) if v > self.ucl or v < self.lcl]


def _finite(x: Iterable[float]) -> np.ndarray:
    a = np.asarray(x if isinstance(x, np.ndarray) else list(x), dtype=float)
    return a[np.isfinite(a)]


def summary(x: Iterable[float]) -> Summary:
    """:class:`Summary` of the finite values of ``x`` (NaN figures when there are none)."""
    a = _finite(x)
    nan = math.nan
    if not len(a):
        return Summary(0, nan, nan, nan, nan, {p: nan for p in PERCENTILES})
    return Summary(int(len(a)), float(a.mean()), float(a.std(ddof=1)) if len(a) > 1 else nan, float(a.min()),
                   float(a.max()), {p: float(np.percentile(a, p)) for p in PERCENTILES})


def moving_ranges(x: Iterable[float]) -> np.ndarray:
    """``|x[i] - x[i-1]|`` of the finite values of ``x`` in their order."""
    return np.abs(np.diff(_finite(x)))


def capability(x: Iterable[float], lsl: float | None = None, usl: float | None = None) -> Capability:
    """:class:`Capability` of ``x`` (finite values, in time order) against ``lsl`` / ``usl``."""
    a = _finite(x)
    nan = math.nan
    mr = moving_ranges(a)
    s_w = float(mr.mean()) / D2 if len(mr) else nan
    s_o = float(a.std(ddof=1)) if len(a) > 1 else nan
    mean = float(a.mean()) if len(a) else nan

    def index(sigma: float) -> float:
        if not (sigma > 0.0):  # constant values (or fewer than two): no spread to compare with
            return nan
        sides = []
        if usl is not None:
            sides.append((usl - mean) / (3.0 * sigma))
        if lsl is not None:
            sides.append((mean - lsl) / (3.0 * sigma))
        return float(min(sides)) if sides else nan

    cp = (usl - lsl) / (6.0 * s_w) if (usl is not None and lsl is not None and s_w > 0.0) else nan
    return Capability(lsl, usl, s_w, s_o, float(cp), index(s_w), index(s_o))


def imr_limits(x: Iterable[float]) -> ControlLimits:
    """Individuals / moving-range chart limits of ``x`` (finite values, time order)."""
    a = _finite(x)
    mr = moving_ranges(a)
    nan = math.nan
    center = float(a.mean()) if len(a) else nan
    mr_bar = float(mr.mean()) if len(mr) else nan
    return ControlLimits(center, center + E2 * mr_bar, center - E2 * mr_bar, mr_bar, D4 * mr_bar)


# --------------------------------------------------------------------------- records
def first_pass_yield(records: Sequence[RunRecord]) -> tuple[float, int]:
    """(serials whose first production run passed / serials with one, serials); NaN without any."""
    recs = sorted((r for r in records if r.kind == MEASURED_KIND), key=lambda r: (r.started_at, r.run_id))
    return first_pass_yield_of(np.array([r.serial for r in recs], dtype=object),
                               np.array([r.verdict for r in recs], dtype=object))


def first_pass_yield_of(serial: np.ndarray, verdict: np.ndarray) -> tuple[float, int]:
    """:func:`first_pass_yield` of runs given as arrays of serials and verdicts in time order."""
    if not len(serial):
        return math.nan, 0
    n = len(serial)
    # each serial's first run: built from the last run back, so the earliest index stays
    first_of = dict(zip(np.asarray(serial)[::-1].tolist(), range(n - 1, -1, -1), strict=True))
    first = np.fromiter(first_of.values(), dtype=np.intp, count=len(first_of))
    return float(np.count_nonzero(np.asarray(verdict)[first] == "pass") / len(first)), len(first)


def pareto(records: Sequence[RunRecord]) -> list[tuple[str, int, float]]:
    """``(cause, runs, cumulative share of all causes)`` of the records' causes, most frequent first."""
    return pareto_of(r.causes() for r in records)


def pareto_of(causes: Iterable[Sequence[str]]) -> list[tuple[str, int, float]]:
    """A Pareto by runs of the runs' causes (one list per run): per cause the runs that name it
    (a cause named twice by one run counts once), most first, ties by name; and the cumulative
    share of the runs (with a cause) that the causes so far account for (a run that names two of
    them counts once), so the last is 1.0 and each bar and the line are runs, not codes."""
    runs = [set(c) for c in causes if c]
    counts: dict[str, int] = {}
    for run in runs:
        for c in run:
            counts[c] = counts.get(c, 0) + 1
    out = []
    covered = [False] * len(runs)
    for cause, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])):
        covered = [done or cause in run for done, run in zip(covered, runs, strict=True)]
        out.append((cause, n, sum(covered) / len(runs)))
    return out
