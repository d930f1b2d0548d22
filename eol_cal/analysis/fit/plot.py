"""Plots of a motor's fit: torque against electrical angle with the fitted curve, residual spectrum."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from eol_cal.analysis.fit import FitSpec, MotorFit, design_matrix, path_gain
from eol_cal.analysis.fit.model import transducer_gain
from eol_cal.analysis.fit.motor_input import MotorInput
from eol_cal.rendering.renderer import plain
from eol_cal.numerics.wrap import wrap_2pi

_MAX_PANELS = 8
_MAX_POINTS = 4000


def segment_model(mi: MotorInput, fit: MotorFit, spec: FitSpec, s: int) -> tuple[np.ndarray, np.ndarray]:
    """Fitted torque of segment ``s`` at its samples, and the part of it that is drift + mechanical order 1 (N*m)."""
    seg = mi.segments
    theta = np.unwrap(seg.theta[s])
    X = design_matrix(theta, seg.t[s], seg.pole_pairs, spec)
    mean = float(np.mean(seg.torque[s]))
    q = spec.n_nuis
    assert fit.coef is not None  # unpack, which makes every MotorFit, sets it
    nuisance = X[:, 1:q] @ fit.coef[s, 1:q]  # drift above the constant, and the mechanical pair
    return mean + X @ fit.coef[s], nuisance


def fitted_ripple(mi: MotorInput, fit: MotorFit, spec: FitSpec, s: int, theta: np.ndarray,
                  gains: np.ndarray | None = None) -> np.ndarray:
    """T_avg and the fitted ripple of segment ``s`` as the transducer sees it, at angles ``theta``.

    Parameters
    ----------
    mi, fit, spec
        The motor's inputs, its fit and the model it was fitted with.
    s : int
        Segment index.
    theta : ndarray
        Electrical angles (rad).
    gains : ndarray, optional
        :func:`eol_cal.analysis.fit.path_gain` of the segments (computed when not given).

    Returns
    -------
    ndarray
        Torque (N*m): through the bench's response and the transducer's lag at the segment's
        speed, as in the fit's own model.
    """
    seg = mi.segments
    gains = path_gain(seg, spec) if gains is None else gains
    curve = np.full_like(np.asarray(theta, dtype=float), fit.t_avg[s])
    for h, parts in fit.harmonics.items():
        gain = transducer_gain(spec, fit.delay_s, h * seg.omega_e[s])
        gain *= gains[s, spec.harmonics.index(h)]
        # c sin(x + phase_c) + k i_qo sin(x + phase_k) = Im(e^ix (c e^i phase_c + k i_qo e^i phase_k)): one sine
        amp = 0j
        if "c" in parts:
            amp += parts["c"].value * np.exp(1j * parts["c"].phase)
        if "k" in parts:
            amp += parts["k"].value * seg.i_qo[s] * np.exp(1j * parts["k"].phase)
        if fit.current is not None:  # the current's ripple, known air-gap torque
            amp += fit.current[s, spec.harmonics.index(h)]
        curve -= abs(gain) * abs(amp) * np.sin(h * theta + (np.angle(gain) + np.angle(amp)))
    return curve


def plot_fit(path: str | Path, mi: MotorInput, fit: MotorFit, spec: FitSpec) -> None:
    """Torque (drift and mechanical order 1 removed) against electrical angle, fitted ripple on top.

    Parameters
    ----------
    path : path
        PNG to write (atomically).
    mi, fit, spec
        The motor's inputs, its fit and the model it was fitted with.
    """
    from eol_cal.rendering.figures import pyplot, write_png

    plt = pyplot()
    n = min(mi.segments.n_segments, _MAX_PANELS)
    cols = 2 if n > 1 else 1
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 2.6 * rows), squeeze=False)
    grid = np.linspace(0.0, 2 * math.pi, 721)
    bench = path_gain(mi.segments, spec)
    for s in range(n):
        ax = axes[s // cols][s % cols]
        seg = mi.segments
        model, nuisance = segment_model(mi, fit, spec, s)
        th = np.asarray(wrap_2pi(seg.theta[s]))  # numpy in, numpy out
        y = seg.torque[s] - nuisance
        step = max(1, len(th) // _MAX_POINTS)
        ax.plot(np.degrees(th[::step]), y[::step], ".", ms=1.5, alpha=0.5, label="measured")
        curve = fitted_ripple(mi, fit, spec, s, grid, gains=bench)
        ax.plot(np.degrees(grid), curve, "-", color="C3", lw=1.2, label="fit")
        info = mi.info[s]
        ax.set_title(f"{plain(Path(info.source).name)}: {info.speed_rpm:.0f} rpm, i_qo {info.i_qo:.1f} A", fontsize=8)
        ax.set_xlim(0, 360)
        ax.set_xlabel("electrical angle theta_r (deg)", fontsize=8)
        ax.set_ylabel("torque (N*m)", fontsize=8)
        ax.tick_params(labelsize=7)
    for s in range(n, rows * cols):
        axes[s // cols][s % cols].axis("off")
    axes[0][0].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{plain(mi.serial)}: torque vs electrical angle (drift and mechanical order 1 removed)", fontsize=9)
    fig.tight_layout()
    write_png(fig, path)
    plt.close(fig)


def plot_residual_spectrum(path: str | Path, mi: MotorInput, fit: MotorFit, spec: FitSpec, max_order: int = 36) -> None:
    """Order spectrum of the fit's residual, one line per segment (N*m against electrical order)."""
    from eol_cal.rendering.figures import pyplot, write_png
    from eol_cal.analysis.spectrum import order_spectrum
    from eol_cal.errors import InputError

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.2))
    seg = mi.segments
    for s in range(seg.n_segments):
        model, _ = segment_model(mi, fit, spec, s)
        try:
            sp = order_spectrum(seg.theta[s], seg.torque[s] - model, mi.poles, max_order=max_order)
        except InputError:
            continue  # less than one electrical revolution one way: no spectrum for this segment
        info = mi.info[s]
        ax.plot(sp.orders, sp.amplitude_nm, ".-", ms=3, lw=0.8, label=f"{info.speed_rpm:.0f} rpm, {info.i_qo:.0f} A")
    for h in spec.harmonics:
        ax.axvline(h, color="0.8", lw=0.8, zorder=0)
    ax.set_xlabel("electrical order")
    ax.set_ylabel("residual amplitude (N*m)")
    ax.set_title(f"{plain(mi.serial)}: residual spectrum (rms {fit.rms:.3g} N*m)", fontsize=9)
    if seg.n_segments <= 10:
        ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    write_png(fig, path)
    plt.close(fig)
