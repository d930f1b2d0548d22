"""Step ``acquire``: the calibration capture over the whole profile; each window's angle and p-p
figure are worked out on the helper thread as the dyno hands it over (:mod:`eol_cal.station.early`),
behind the fit's pre-warming (imports, the solver's trace), while the shaft turns on. The
calibrated flash's first half opens as the last window is in, its first requests the ECU's state
after the capture (:meth:`~eol_cal.station.context.CycleContext.acquire`, ``flash_after``)."""

from __future__ import annotations

import eol_cal.capture.mdf4_io  # noqa: F401 - the MDF4 writer's module; asammdf, which it loads, on the helper
from eol_cal.analysis.fit.prewarm import prewarm_fit
from eol_cal.station.context import CycleContext
# without scipy or JAX (the analysis imports them inside its functions): the shaft is not kept waiting
# for them; the helper below imports them beside the stream (tests/test_station_steps.py)
from eol_cal.station.early import EarlyWindows

NAME = "acquire"


def run(ctx: CycleContext) -> None:
    assert ctx.helper is not None  # start_context made the pool
    ctx.helper.submit(preload_analysis)
    ctx.helper.submit(preload_writers)
    # the plots are drawn after the verdict: matplotlib is not imported while the dyno turns
    # the profile's speeds and loads: the model check's band solver is traced for the capture's bands too
    points = [(s.speed_rpm, float("nan") if s.iq is None else s.iq) for s in ctx.segments]
    ctx.prewarm = ctx.helper.submit(prewarm_fit, len(ctx.segments), ctx.cfg.cache_dir, False, points)
    ctx.early = EarlyWindows(ctx.cfg.motor.poles, ctx.cfg.motor.N_enc, ctx.cfg.estimator_options,
                             pool=ctx.helper, cache_dir=ctx.cfg.cache_dir, n_windows=len(ctx.segments))
    ctx.before = ctx.acquire("before", ctx.segments, on_window=ctx.early.on_window, hold_write=True, flash_after=True)


def preload_analysis() -> None:
    """Import the parts of scipy the windows' work and the fit import inside their functions
    (heavy: not at `eol-cal run`'s start): linalg (the fingerprint's and the noise's factors, BLAS)
    and special (the intervals' and the model check's distributions), while the shaft ramps to the
    first segment, not when the first window is in. Not scipy's signal, interpolate, ndimage or
    stats, which the analysis no longer uses (numpy's own filter, PCHIP and median:
    :mod:`eol_cal.numerics`): they were ~1.5 CPU s of every cycle's start, beside the capture's
    stream."""
    import scipy.linalg  # its blas and lapack with it
    import scipy.special  # noqa: F401


def preload_writers() -> None:
    """Import what writes the captures (asammdf, pandas), the record (the database library) and
    the report while the dyno turns, not when the capture is in or the verdict is known."""
    import asammdf  # noqa: F401 - the MDF4 writer imports it where it writes (heavy): here, not beside the fit

    import eol_cal.station.report_files
    import eol_cal.records.spool  # noqa: F401
