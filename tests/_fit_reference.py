"""The compression's plain reference for the fit's tests: one segment's normal equations from
``design_matrix`` over every sample, numpy products and Cholesky (no blocks, no batching)."""

from __future__ import annotations

import numpy as np

from eol_cal.analysis import fit


def plain_normal_equations(theta: np.ndarray, t: np.ndarray, y: np.ndarray, pole_pairs: int,
                           spec: fit.FitSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
    """``(X^T X, L, z, floor, empty)``: ``L`` its lower Cholesky factor (an empty column's diagonal
    set to 1), ``z = L^-1 X^T (y - mean)``, ``floor`` the sum of squares no coefficient removes,
    ``empty`` the columns that are zero on this segment."""
    X = fit.design_matrix(theta, t, pole_pairs, spec)
    yc = y - y.mean()
    XtX = X.T @ X
    empty = np.diag(XtX) == 0.0
    XtX[empty, empty] = 1.0
    L = np.linalg.cholesky(XtX)
    z = np.linalg.solve(L, X.T @ yc)
    return XtX, L, z, float(yc @ yc - z @ z), empty
