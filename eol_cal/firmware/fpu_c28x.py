"""Division and square root as the F28335's C28x FPU computes them, in binary32 (a model).

The C28x FPU has no divide or square-root instruction. It has estimates, ``EINVF32`` (1/x) and
``EISQRTF32`` (1/sqrt(x)), each about 8 bits accurate, and TI's runtime library and compiler
refine them with two Newton-Raphson steps (TMS320C28x FPU Instruction Set, SPRUEO2, "EINVF32",
"EISQRTF32" and their example sequences). The result is within a few units in the last place of
the correctly rounded one, not equal to it, so a target cannot match the golden vectors bit for
bit where a division or square root feeds an output. This module models that path so that the
bound is measured (the golden vectors' tolerance classes, ``mech_golden``), not guessed:

* the estimate is the correctly rounded reciprocal (square root: reciprocal of the square root)
  with its significand cut to 8 bits, the coarsest estimate the instruction promises;
* two Newton steps in binary32, each operation rounded once: ``y = y * (2 - x*y)`` for 1/x,
  ``y = y * (1.5 - (0.5*x*y)*y)`` for 1/sqrt(x);
* ``a / b = a * (1/b)``, ``sqrt(x) = x * (1/sqrt(x))`` (0 for x = 0).

The C reference does the same when built with ``-DEOL_FPU_C28X`` (``firmware_params/c/eol_fp.h``),
bit for bit with this model, which is how the harness checks the classes.
"""

from __future__ import annotations

import numpy as np

F32 = np.float32
#: significand bits kept by the estimate instructions (of 23)
ESTIMATE_BITS = 8
_CUT = np.uint32((0xFFFFFFFF << (23 - ESTIMATE_BITS)) & 0xFFFFFFFF)


def _estimate(x: np.ndarray) -> np.ndarray:
    """``x`` (binary32) with its significand cut to ESTIMATE_BITS bits."""
    bits = np.asarray(x, F32).view(np.uint32) & _CUT
    return bits.view(F32)


def recip(b: np.ndarray | float) -> np.ndarray:
    """1/b as EINVF32 plus two Newton steps (binary32)."""
    b = np.asarray(b, F32)
    with np.errstate(divide="ignore", invalid="ignore"):
        y = _estimate(F32(1.0) / b)
        for _ in range(2):
            y = y * (F32(2.0) - b * y)
    return y


def div(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """a/b as the C28x runtime computes it: ``a * recip(b)`` (binary32)."""
    return np.asarray(a, F32) * recip(b)


def sqrt(x: np.ndarray | float) -> np.ndarray:
    """sqrt(x) for x >= 0 as EISQRTF32 plus two Newton steps, times x (binary32; 0 at 0)."""
    x = np.asarray(x, F32)
    with np.errstate(divide="ignore", invalid="ignore"):
        y = _estimate(F32(1.0) / np.sqrt(x))
        h = F32(0.5) * x
        for _ in range(2):
            y = y * (F32(1.5) - (h * y) * y)
        return np.where(x > F32(0.0), x * y, F32(0.0)).astype(F32)


def ulp_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Units in the last place between binary32 values (ordered as integers; the harness's measure)."""
    def ordered(x: np.ndarray) -> np.ndarray:
        u = np.asarray(x, F32).view(np.uint32).astype(np.int64)
        return np.where(u >= 2**31, -(u - 2**31), u)

    return np.abs(ordered(a) - ordered(b))
