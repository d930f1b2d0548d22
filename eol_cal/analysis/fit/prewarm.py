"""Pre-warming of the fit: imports and a solver trace, run while the dyno spins (the station cycle)."""

from __future__ import annotations

from typing import Callable


def prewarm_fit(n_segments: int, prepare: Callable[[], None] | None = None) -> None:
    """Import what the fit and the plots need, and trace the fit's solver for ``n_segments``
    segments on an analytic record (JAX traces per shape; tracing costs seconds even when the
    compiled code comes from the persistent cache). Runs while the dyno spins."""
    try:
        if prepare is not None:
            prepare()
        import dataclasses

        import numpy as np

        from eol_cal.analysis.fit import FitSpec, fit_many
        from eol_cal.analysis.fit.synth import synthetic_segments
        import eol_cal.analysis.fit.capture  # noqa: F401
        import eol_cal.analysis.fit.plot  # noqa: F401
        from eol_cal.analysis.plots import _pyplot

        _pyplot()
        loads = tuple(20.0 + 10.0 * k for k in range(max(2, (n_segments + 3) // 4)))
        seg, _truth = synthetic_segments(np.random.default_rng(0), loads_a=loads, speeds_rpm=(60.0, 120.0),
                                         directions=(1, -1), seg_s=0.1, fs_hz=10000.0)
        if len(seg.theta) > n_segments:
            keep = slice(0, n_segments)
            seg = dataclasses.replace(seg, **{f.name: getattr(seg, f.name)[keep] for f in dataclasses.fields(seg)
                                              if isinstance(getattr(seg, f.name), (list, np.ndarray))})
        fit_many([seg], FitSpec(), mode="loop")
    except Exception:  # noqa: BLE001 - the step that needs it reports a real failure
        pass
