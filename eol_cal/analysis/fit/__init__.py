"""Per-motor torque-ripple fit: the contract's ripple model solved with optimistix in JAX.

Modules, in the order the data flows:

- :mod:`~eol_cal.analysis.fit.capture`: captures -> steady segments per motor (``MotorInput``)
- :mod:`~eol_cal.analysis.fit.model`: the model (``FitSpec``), its input (``SteadySegments``), the design matrix
- :mod:`~eol_cal.analysis.fit.compression`: each segment reduced exactly to its normal equations
- :mod:`~eol_cal.analysis.fit.solver`: the jitted one-motor solver (delay grid start, Gauss-Newton)
- :mod:`~eol_cal.analysis.fit.cache`: serialized solvers on disk (``jax.export``), pre-warming
- :mod:`~eol_cal.analysis.fit.motor_fit`: the fit as estimates with 95 % intervals (``MotorFit``)
- :mod:`~eol_cal.analysis.fit.batch`: one motor or many (``fit_segments``, ``fit_many``)
- :mod:`~eol_cal.analysis.fit.motors`: captures -> fitted, judged motors (``fit_motors``), what ``eol-cal fit`` runs
- :mod:`~eol_cal.analysis.fit.table`: a fit result -> the compensation block
- :mod:`~eol_cal.analysis.fit.plot`: plots of a fit
- :mod:`~eol_cal.analysis.fit.synth`, :mod:`~eol_cal.analysis.fit.scipy_ref`: array-level test data and
  the plain scipy fit (reference for tests and benchmarks only)

The array-level names are re-exported here (``from eol_cal.analysis.fit import FitSpec, fit_many``).
"""

from eol_cal.analysis.fit.batch import AUTO_BATCH_MIN, fit_many, fit_segments, pick_mode
from eol_cal.analysis.fit.compression import Compressed, compress, compress_segment
from eol_cal.analysis.fit.model import (
    TAU_SCALE,
    Z95,
    FitSpec,
    SteadySegments,
    check_identifiable,
    design_matrix,
    design_matrix_t,
    load_points,
    path_gain,
)
from eol_cal.analysis.fit.motor_fit import Estimate, MotorFit, shift_frame, unpack
from eol_cal.analysis.fit.solver import tau_grid

__all__ = [
    "AUTO_BATCH_MIN",
    "TAU_SCALE",
    "Z95",
    "Compressed",
    "Estimate",
    "FitSpec",
    "MotorFit",
    "SteadySegments",
    "check_identifiable",
    "compress",
    "compress_segment",
    "design_matrix",
    "design_matrix_t",
    "fit_many",
    "fit_segments",
    "load_points",
    "path_gain",
    "pick_mode",
    "shift_frame",
    "tau_grid",
    "unpack",
]
