"""The same ripple model fitted the plain way: scipy.optimize.least_squares over every sample.

This is the alternative a user would write first, kept as the reference that the benchmark
compares with and that the tests hold the compressed JAX path against (same optimum). One
residual per sample; the parameter vector holds the delay, the ripple cos/sin pairs and every
segment's nuisance coefficients. Not used by the product.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from eol_cal.analysis.fit import TAU_SCALE, FitSpec, SteadySegments, design_matrix, path_gain


def fit_segments_scipy(seg: SteadySegments, spec: FitSpec, p0: np.ndarray | None = None) -> dict:
    """Fit one motor with scipy's trust-region least squares on the full per-sample residual.

    Parameters
    ----------
    seg : SteadySegments
        As for :func:`eol_cal.analysis.fit.fit_segments`.
    spec : FitSpec
        Same model; ``spec.fit_delay`` decides whether the delay is free.
    p0 : ndarray, optional
        Start; default zeros for the ripple and the delay at 0.

    Returns
    -------
    dict
        ``harmonics`` {order: {"c": (amplitude N*m, phase rad), "k": (N*m/A, rad)}}, ``delay_s``,
        ``nfev``, ``cost`` (half the sum of squares, N*m^2), ``success``.
    """
    nh = len(spec.harmonics)
    q = spec.n_nuis
    n_tau = int(spec.fit_delay)
    G = spec.n_glob
    S = seg.n_segments
    Xs = [design_matrix(np.unwrap(th), t, seg.pole_pairs, spec) for th, t in zip(seg.theta, seg.t, strict=True)]
    ys = [np.asarray(y, dtype=float) for y in seg.torque]
    H = np.asarray(spec.harmonics, dtype=float)
    gain = path_gain(seg, spec)

    def residual(p):
        tau = p[0] * TAU_SCALE if n_tau else spec.delay_s
        glob = p[n_tau : n_tau + G].reshape(-1, nh, 2)
        nuis = p[n_tau + G :].reshape(S, q)
        out = []
        for s in range(S):
            Z = np.zeros(nh, dtype=complex)
            part = 0
            if spec.fit_c:
                Z = Z + glob[part, :, 0] + 1j * glob[part, :, 1]
                part += 1
            if spec.fit_k:
                Z = Z + seg.i_qo[s] * (glob[part, :, 0] + 1j * glob[part, :, 1])
            Z = Z * gain[s]
            a = H * seg.omega_e[s] * tau
            Z = Z / (1.0 + 1j * a) if spec.transducer == "lowpass" else Z * np.exp(-1j * a)
            g = np.concatenate([nuis[s], np.stack([-Z.real, -Z.imag], axis=-1).reshape(-1)])
            out.append(ys[s] - Xs[s] @ g)
        return np.concatenate(out)

    if p0 is None:
        p0 = np.zeros(n_tau + G + S * q)
        p0[n_tau + G :: q] = [y.mean() for y in ys]
    sol = least_squares(residual, p0, method="trf", xtol=1e-10, ftol=1e-10)
    p = sol.x
    harmonics: dict = {h: {} for h in spec.harmonics}
    parts = [name for name, on in (("c", spec.fit_c), ("k", spec.fit_k)) if on]
    for ip, name in enumerate(parts):
        for ih, h in enumerate(spec.harmonics):
            i = n_tau + (ip * nh + ih) * 2
            harmonics[h][name] = (float(np.hypot(p[i], p[i + 1])), float(np.arctan2(p[i + 1], p[i])))
    return {
        "harmonics": harmonics,
        "delay_s": float(p[0] * TAU_SCALE) if spec.delay_s is None else float(spec.delay_s),  # None: fitted, p[0]
        "nfev": int(sol.nfev),
        "cost": float(sol.cost),
        "success": bool(sol.success),
    }
