"""The one-motor solver on compressed data: optimistix in JAX, jitted per (spec, segments, batch mode).

The delay enters only through a rotation of each segment's harmonic coefficients by
``h omega_s tau`` (``omega_s`` is the segment's mean speed; the dyno holds speed, so the per-sample
speed ripple changes the phase by ``h d_omega tau``, a few mrad at most).

The start is closed-form: for each tau on a grid (:func:`tau_grid`) the model is linear and solved
by linear least squares; the best grid point starts Gauss-Newton (or Levenberg-Marquardt) on the
full vector. Amplitudes are parameterised as cos/sin pairs (well conditioned also for a small
amplitude).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from eol_cal.analysis.fit.model import TAU_SCALE, FitSpec

#: the names of optimistix's ``RESULTS`` a solve can end with; the solver returns the index of its
#: result here (-1: a result this list does not name), :func:`solver_result` the name
SOLVER_RESULTS = ("successful", "max_steps_reached", "nonlinear_max_steps_reached", "nonlinear_divergence", "nonfinite",
                  "singular", "breakdown", "stagnation", "conlim", "nonfinite_input")
#: what :func:`solver_result` calls an index outside :data:`SOLVER_RESULTS`
UNKNOWN_RESULT = "unknown"

if TYPE_CHECKING:
    import jax
    import optimistix as optx

    #: a solver: the compressed data by name (one motor's, or a batch's stacked), the delay's start
    #: grid and the step limit -> the solution by name (p, cov_unscaled, ssr_red, res, jac, g, steps, result)
    Solver = Callable[[Mapping[str, np.ndarray | jax.Array], np.ndarray | jax.Array, int], dict[str, jax.Array]]


def build_solver(spec: FitSpec, S: int) -> Solver:
    """The jitted one-motor solver on compressed data, for a given spec and segment count.

    The per-segment nuisance (drift polynomial, mechanical pair) enters linearly and unconstrained
    through the leading block of the upper-triangular R, so it is projected out exactly: the top
    rows of each segment's residual can always be zeroed, the bottom ``2*len(harmonics)`` rows
    depend on the ripple parameters only. Levenberg-Marquardt / Gauss-Newton then runs on
    (delay, every cos/sin ripple coefficient), and its Jacobian gives the same covariance for them
    as the full problem would (Schur complement).
    """
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    H = jnp.asarray(spec.harmonics, dtype=float)
    nh = len(spec.harmonics)
    q = spec.n_nuis
    G = spec.n_glob
    n_tau = int(spec.fit_delay)

    def harm_coef(p, tau_known, i_qo, omega, gre, gim, cre, cim):
        """Coefficients of the sin/cos(h theta) columns per segment, shape (S, 2 nh)."""
        tau = p[0] * TAU_SCALE if n_tau else tau_known
        glob = p[n_tau : n_tau + G].reshape(-1, nh, 2)  # (part, harmonic, cos/sin)
        Zre = jnp.zeros((S, nh))
        Zim = jnp.zeros((S, nh))
        part = 0
        if spec.fit_c:
            Zre = Zre + glob[part, :, 0][None]
            Zim = Zim + glob[part, :, 1][None]
            part += 1
        if spec.fit_k:
            Zre = Zre + i_qo[:, None] * glob[part, :, 0][None]
            Zim = Zim + i_qo[:, None] * glob[part, :, 1][None]
        # the ripple of kt * i_q (known; zero without a current channel) is air-gap torque too
        Zre = Zre + cre
        Zim = Zim + cim
        # air gap -> shaft (bench mechanics), then the transducer
        Zre, Zim = Zre * gre - Zim * gim, Zre * gim + Zim * gre
        a = H[None, :] * omega[:, None] * tau
        if spec.transducer == "lowpass":
            # first-order transducer: each segment's phasor times 1 / (1 + i h omega tau)
            den = 1.0 + a * a
            cr, sr = 1.0 / den, -a / den
        else:
            # pure delay: harmonic h is seen at h*(theta - omega*tau), a rotation by -h omega tau
            cr, sr = jnp.cos(a), -jnp.sin(a)
        Rre = Zre * cr - Zim * sr
        Rim = Zre * sr + Zim * cr
        # T = ... - Re(Z') sin(h theta) - Im(Z') cos(h theta)
        return jnp.stack([-Rre, -Rim], axis=-1).reshape(S, 2 * nh)

    def residual(p, args):
        Rhh, zh, tau_known, i_qo, omega, gre, gim, cre, cim, valid = args
        g = harm_coef(p, tau_known, i_qo, omega, gre, gim, cre, cim)
        r = zh - jnp.einsum("sij,sj->si", Rhh, g)
        return (r * valid[:, None]).reshape(-1)

    def linear_start(args, tau):
        p_tau = jnp.atleast_1d(tau / TAU_SCALE)[:n_tau]

        def res_lin(lin):
            return residual(jnp.concatenate([p_tau, lin]), args)

        zero = jnp.zeros(G)
        r0 = res_lin(zero)
        A = jax.jacfwd(res_lin)(zero)
        lin = jnp.linalg.solve(A.T @ A, -A.T @ r0)
        return jnp.concatenate([p_tau, lin]), jnp.sum((A @ lin + r0) ** 2)

    def solve(comp, tau_grid, max_steps):
        Rhh = comp["R"][:, q:, q:]
        zh = comp["z"][:, q:]
        valid = (comp["n"] > 0).astype(zh.dtype)
        paths = tuple(comp[k] for k in ("gain_re", "gain_im", "cur_re", "cur_im"))
        # a known delay is the grid's one point, an argument: not a constant of the trace, so that
        # one compiled solver serves every delay (the model check fits each motor's bands at its own)
        args = (Rhh, zh, tau_grid[0], comp["i_qo"], comp["omega"], *paths, valid)
        if n_tau:
            starts, ssrs = jax.vmap(lambda tau: linear_start(args, tau))(tau_grid)
            p0 = starts[jnp.argmin(ssrs)]
        else:
            p0, _ = linear_start(args, 0.0)
        # Jacobi scaling: in u = (p - p0) / D every Jacobian column has unit norm, so the delay
        # (a tiny column) and the ripple coefficients start on the same footing.
        J0 = jax.jacfwd(residual)(p0, args)
        D = 1.0 / jnp.sqrt(jnp.maximum(jnp.sum(J0 * J0, axis=0), 1e-300))

        def residual_u(u, a):
            return residual(p0 + D * u, a)

        sol: optx.Solution[jax.Array, None] = optx.least_squares(
            residual_u, _make_solver(spec), jnp.zeros_like(p0), args=args, max_steps=max_steps, throw=False
        )
        p = p0 + D * sol.value
        r = residual(p, args)
        J = jax.jacfwd(residual)(p, args)
        return {
            "p": p,
            "cov_unscaled": jnp.linalg.inv(J.T @ J),
            "ssr_red": jnp.sum(r * r),
            # each segment's reduced rows (one cos/sin pair a harmonic) and their Jacobian: the segments'
            # scatter (motor_fit.segment_scatter) and the noise's covariance at each harmonic's own
            # noise (motor_fit.at_line_noise)
            "res": r.reshape(S, -1),
            "jac": J.reshape(S, -1, J.shape[1]),
            "g": harm_coef(p, tau_grid[0], comp["i_qo"], comp["omega"], *paths),
            "steps": sol.stats["num_steps"],
            "result": result_index(sol.result),
        }

    return solve


def result_index(result: Any) -> jax.Array:
    """The index in :data:`SOLVER_RESULTS` of optimistix's ``result`` (traced; -1: not listed).

    An optimistix result is an equinox enumeration item, compared by name (its integer is private):
    a JAX array leaves the jitted, vmapped or exported solver where the item cannot."""
    import jax.numpy as jnp
    import optimistix as optx

    index = jnp.asarray(-1, dtype=jnp.int32)
    for i, name in enumerate(SOLVER_RESULTS):
        if hasattr(optx.RESULTS, name):  # a name an older optimistix does not have stays -1
            index = jnp.where(result == getattr(optx.RESULTS, name), i, index)
    return index


def solver_result(index: int) -> str:
    """The optimistix ``RESULTS`` name of an index the solver returned (:data:`UNKNOWN_RESULT` if none)."""
    return SOLVER_RESULTS[index] if 0 <= index < len(SOLVER_RESULTS) else UNKNOWN_RESULT


def _make_solver(spec: FitSpec) -> optx.AbstractGaussNewton[jax.Array, jax.Array, None]:
    """Gauss-Newton (default) or Levenberg-Marquardt with a small initial damping.

    Measured on synthetic motors: optimistix's LM tests for termination only after an accepted
    step, so when the closed-form start is already optimal to rounding every trial step is
    rejected and it runs to ``max_steps`` (2 of 256 motors); from the closed-form start
    Gauss-Newton needs 3-6 steps. LM stays available (``solver="lm"``) for poor starts; it starts
    at damping ``1 / lm_init_step`` instead of 1 (which costs ~20 creeping steps here).
    """
    import equinox as eqx
    import jax.numpy as jnp
    import optimistix as optx

    if spec.solver == "gn":
        return optx.GaussNewton(rtol=spec.rtol, atol=spec.atol)
    solver: optx.LevenbergMarquardt[jax.Array, jax.Array, None] = optx.LevenbergMarquardt(rtol=spec.rtol, atol=spec.atol)
    try:  # private in optimistix 0.1: without it, the stock (slower-starting) LM still works
        from optimistix._solver.trust_region import _TrustRegionState
    except ImportError:  # pragma: no cover
        return solver

    class _Region(optx.ClassicalTrustRegion):
        init_step: float = eqx.field(static=True, default=1e3)

        def init(self, y, f_info_struct):
            return _TrustRegionState(step_size=jnp.array(self.init_step))

    return eqx.tree_at(lambda s: s.search, solver, _Region(init_step=spec.lm_init_step))


_SOLVERS: dict[tuple[FitSpec, int, str], Solver] = {}



def mode_solver(solve: Solver, mode: str) -> Solver:
    """The one-motor ``solve`` (:func:`build_solver`) for batch mode ``mode``: ``one`` itself,
    ``vmap`` vectorised over a chunk's motors, ``map`` by ``jax.lax.map`` over them (not jitted: the
    program :func:`cached_solver` jits and :func:`eol_cal.analysis.fit.fit_many` exports)."""
    import jax

    if mode == "one":
        return solve
    if mode == "vmap":
        return jax.vmap(solve, in_axes=(0, None, None))
    if mode == "map":
        return lambda comp, grid, steps: jax.lax.map(lambda c: solve(c, grid, steps), comp)
    raise ValueError(f"unknown batch mode {mode!r}")


def cached_solver(spec: FitSpec, S: int, mode: str) -> Solver:
    """Jitted solver, cached per (spec, S, mode)."""
    import jax

    key = (spec, S, mode)
    fn = _SOLVERS.get(key)
    if fn is None:
        # setdefault: threads that miss at once share the first one's (one jitted function compiles
        # once however many threads call it; two would compile twice)
        fn = _SOLVERS.setdefault(key, jax.jit(mode_solver(build_solver(spec, S), mode), static_argnums=(2,)))
    return fn


def tau_grid(spec: FitSpec, omega_max: float) -> np.ndarray:
    """Start grid for the delay (s) over [0, delay_max_s]; a known delay (``spec.delay_s``) alone.

    Spacing: the 6th harmonic at the highest speed moves at most 0.5 rad between grid points
    (8 to 64 points). With the low-pass model the phase ``atan(h omega tau)`` is monotone and
    bounded, so the best point is in the basin of the optimum; with the pure delay a shift of
    ``2 pi / (6 d_omega)`` would alias, which this spacing resolves for delays up to
    ``spec.delay_max``. Solver steps then refine every harmonic.
    """
    if not spec.fit_delay:
        return np.array([float(spec.delay_s or 0.0)])  # the known delay, the solver's argument
    span = 6 * max(omega_max, 1.0) * spec.delay_max
    n = int(min(max(math.ceil(span / 0.5) + 1, 8), 64))
    # a power of two, so that nearby speeds share one compiled solver
    n = 1 << (n - 1).bit_length()
    return np.linspace(0.0, spec.delay_max, n)
