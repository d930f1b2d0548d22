"""Pre-warming of the fit: imports and the solvers' traces, run while the dyno spins (the station cycle).

It sits beside the fit's caches (:mod:`eol_cal.analysis.fit.cache`): it switches JAX's compilation
cache on for the directory it is given and reads (or writes) the serialized solver there.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from eol_cal.analysis.fit.batch import fit_many
from eol_cal.analysis.fit.cache import enable_compile_cache
from eol_cal.analysis.fit.model import FitSpec, SteadySegments
from eol_cal.analysis.fit.synth import synthetic_segments

#: the p-value the pre-warming's model check is run at (its verdict is thrown away)
_P_MIN = 0.05


def prewarm_fit(n_segments: int, cache_dir: str | os.PathLike[str] | None = None, plots: bool = True,
                points: Sequence[tuple[float, float]] | None = None) -> None:
    """Make the fit's first run in this process fast; never raises.

    Switches on JAX's persistent compilation cache in ``cache_dir``, imports what the fit and the
    plots need (JAX, the angle, matplotlib), and traces the fit's solver for ``n_segments``
    segments on an analytic record (JAX traces per shape; tracing costs seconds even when the
    compiled code comes from the persistent cache), reading or writing the serialized solver in
    ``cache_dir``. Given the profile's ``points``, the analytic record has their speeds and loads,
    one segment each, and the model check runs on it too: its speed bands' solver (the size of the
    profile's largest band, traced in the process: about 0.6 CPU s that the first fit of an
    `eol-cal run` paid) is then ready when the capture's fit asks for it. Runs on a helper thread
    while the dyno spins.

    Parameters
    ----------
    n_segments : int
        Segments of the capture the fit will see (the profile's setpoints).
    cache_dir : path, optional
        The fit's cache directory (:func:`eol_cal.analysis.fit.cache.default_cache_dir`); ``None``:
        no cache.
    plots : bool
        Import matplotlib and the fit's plots too (False: a caller that draws them only later).
    points : sequence of (float, float), optional
        Each setpoint's mechanical speed (rpm, signed) and q current (A, signed), in the profile's
        order (``len(points) == n_segments``); ``None``: a grid of loads and speeds, no model check.
    """
    try:
        enable_compile_cache(cache_dir)
        # imported here on purpose: loading them is the work this function does ahead of time
        import eol_cal.analysis.fit.capture
        if plots:
            import eol_cal.analysis.fit.plot  # noqa: F401
            from eol_cal.rendering.figures import pyplot

            pyplot()
        seg = _record(n_segments, points)
        (fit,) = fit_many([seg], FitSpec(), mode="loop", cache_dir=cache_dir)
        if points is not None:
            from eol_cal.analysis.fit.model_check import check_model

            check_model(seg, fit, FitSpec(), _P_MIN, cache_dir=cache_dir)
    except Exception:  # noqa: BLE001 - the step that needs it reports a real failure
        pass


def _record(n_segments: int, points: Sequence[tuple[float, float]] | None) -> SteadySegments:
    """An analytic record of ``n_segments`` segments: one per point (speed rpm, i_qo A) when given,
    else loads x speeds x directions cut to ``n_segments``."""
    rng = np.random.default_rng(0)
    if points is not None and len(points) == n_segments and all(math.isfinite(v) for p in points for v in p):
        loads = tuple(sorted({float(i) for _w, i in points}))
        speeds = tuple(sorted({abs(float(w)) for w, _i in points}))
        seg, _truth = synthetic_segments(rng, loads_a=loads, speeds_rpm=speeds, directions=(1, -1), seg_s=0.1,
                                         fs_hz=10000.0)
        # the grid's order: direction, speed, load (synthetic_segments)
        grid = [(d, w, i) for d in (1, -1) for w in speeds for i in loads]
        keep = [grid.index((1 if w >= 0 else -1, abs(float(w)), float(i))) for w, i in points]
    else:
        loads = tuple(20.0 + 10.0 * k for k in range(max(2, (n_segments + 3) // 4)))
        seg, _truth = synthetic_segments(rng, loads_a=loads, speeds_rpm=(60.0, 120.0), directions=(1, -1),
                                         seg_s=0.1, fs_hz=10000.0)
        keep = list(range(min(n_segments, len(seg.theta))))
    return dataclasses.replace(seg, **{f.name: _take(getattr(seg, f.name), keep) for f in dataclasses.fields(seg)
                                       if isinstance(getattr(seg, f.name), (list, np.ndarray))})


def _take(values: Any, keep: list[int]) -> Any:
    return values[keep] if isinstance(values, np.ndarray) else [values[k] for k in keep]
