"""Pre-warming of the fit: imports and a solver trace, run while the dyno spins (the station cycle).

It sits beside the fit's caches (:mod:`eol_cal.analysis.fit.cache`): it switches JAX's compilation
cache on for the directory it is given and reads (or writes) the serialized solver there.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from eol_cal.analysis.fit.batch import fit_many
from eol_cal.analysis.fit.cache import enable_compile_cache
from eol_cal.analysis.fit.model import FitSpec
from eol_cal.analysis.fit.synth import synthetic_segments


def prewarm_fit(n_segments: int, cache_dir: str | os.PathLike[str] | None = None, plots: bool = True) -> None:
    """Make the fit's first run in this process fast; never raises.

    Switches on JAX's persistent compilation cache in ``cache_dir``, imports what the fit and the
    plots need (JAX, the angle, matplotlib), and traces the fit's solver for ``n_segments``
    segments on an analytic record (JAX traces per shape; tracing costs seconds even when the
    compiled code comes from the persistent cache), reading or writing the serialized solver in
    ``cache_dir``. Runs on a helper thread while the dyno spins.

    Parameters
    ----------
    n_segments : int
        Segments of the capture the fit will see (the profile's setpoints).
    cache_dir : path, optional
        The fit's cache directory (:func:`eol_cal.analysis.fit.cache.default_cache_dir`); ``None``:
        no cache.
    plots : bool
        Import matplotlib and the fit's plots too (False: a caller that draws them only later).
    """
    try:
        enable_compile_cache(cache_dir)
        # imported here on purpose: loading them is the work this function does ahead of time
        import eol_cal.analysis.fit.capture
        if plots:
            import eol_cal.analysis.fit.plot  # noqa: F401
            from eol_cal.rendering.figures import pyplot

            pyplot()
        loads = tuple(20.0 + 10.0 * k for k in range(max(2, (n_segments + 3) // 4)))
        seg, _truth = synthetic_segments(np.random.default_rng(0), loads_a=loads, speeds_rpm=(60.0, 120.0),
                                         directions=(1, -1), seg_s=0.1, fs_hz=10000.0)
        if len(seg.theta) > n_segments:
            keep = slice(0, n_segments)
            seg = dataclasses.replace(seg, **{f.name: getattr(seg, f.name)[keep] for f in dataclasses.fields(seg)
                                              if isinstance(getattr(seg, f.name), (list, np.ndarray))})
        fit_many([seg], FitSpec(), mode="loop", cache_dir=cache_dir)
    except Exception:  # noqa: BLE001 - the step that needs it reports a real failure
        pass
