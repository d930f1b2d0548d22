"""Ripple metrics: the paper's ripple index eta and peak-to-peak torque ripple over steady windows.

The definition of the peak-to-peak figure is in ``docs/metrics.md``; in short:

- Each direction of rotation is judged on its own. 60-degree units (one period of the 6th
  harmonic) are cut from the reconstructed angle theta_r. A unit is steady when its mean
  speed and its mean i_qo stay within a tolerance of the first unit of the run it belongs
  to, and i_qo varies inside it by no more than that.
- In each steady run the first ``settle_s`` is dropped; from there the run is cut into
  consecutive, non-overlapping windows of whole electrical revolutions: P/2 (one mechanical
  revolution, the paper's 1 s scope view at 60 rpm) where the run holds that many, else as
  many as it holds (at least one).
- Spikes are removed with a Hampel filter before anything else; "filtered" adds a zero-phase
  Butterworth low-pass at ``cutoff_order`` times the electrical frequency of the run.
- Per window ``pp% = (max - min) / |mean| * 100`` with the mean of the despiked raw torque;
  the reported figure is the median over all windows (the max is reported too).
- ``no_mech1``: the same filtered figure with the window's mechanical order 1 (rotor unbalance,
  eccentricity: no table of one 6th-harmonic period can cancel it) taken out by least squares;
  only over windows of at least half a mechanical revolution (over a shorter arc a sinusoid of
  one mechanical period cannot be told from a slope).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from eol_cal.analysis.angle import AngleResult, capture_angle
from eol_cal.analysis.steady import IQ_TOL_A, IQ_TOL_REL, direction_pieces, revolution_bounds, steady_runs
from eol_cal.capture.data import Capture
from eol_cal.errors import InputError
from eol_cal.numerics.iir import lowpass_zero_phase

TWO_PI = 2.0 * np.pi

#: steadiness is judged per 1/6 electrical revolution (one period of the 6th harmonic)
UNITS_PER_REV = 6


def eta_percent(N_enc: np.ndarray | float, poles: np.ndarray | float) -> np.ndarray | float:
    """Ripple index of encoder quantisation, seed eq. (12): ``100 * (1 - cos(P*pi/N_enc))``.

    Parameters
    ----------
    N_enc : array_like
        Encoder pulses per mechanical revolution (channel A).
    poles : array_like
        Number of poles P.

    Returns
    -------
    eta : ndarray or float
        Torque ripple caused by the quantised angle, percent of the average torque (%);
        4.3 % at 64 PPR and 0.44 % at 200 PPR for P = 6. Elementwise (broadcasts).
    """
    N_enc = np.asarray(N_enc, dtype=float)
    poles = np.asarray(poles, dtype=float)
    eta = 100.0 * (1.0 - np.cos(poles * np.pi / N_enc))
    return float(eta) if eta.ndim == 0 else eta


def hampel(x: np.ndarray, half_width: int, n_sigma: float = 3.0, chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
    """Hampel filter: replace samples far from their window median by that median.

    A sample ``x[i]`` is a spike when ``|x[i] - m_i| > n_sigma * max(1.4826 * MAD_i, s)``,
    where ``m_i`` is the median and ``MAD_i`` the median absolute deviation from ``m_i`` of the
    ``2*half_width + 1`` samples centred on ``i`` (edges reflected). The floor ``s`` is the
    larger of the record's white-noise estimate ``1.4826 * median(|diff(x)|) / sqrt(2)`` and
    its resolution (smallest non-zero ``|diff(x)|``, one LSB of a quantised transducer): it
    keeps the one-LSB flicker of a flat quantised signal (MAD 0) from counting as spikes.

    Parameters
    ----------
    x : ndarray
        Signal (any unit).
    half_width : int
        Half window length (samples), at least 1.
    n_sigma : float
        Threshold in robust standard deviations.
    chunk : int
        Samples per block (bounds memory to ``chunk * (2*half_width+1)`` floats).

    Returns
    -------
    y : ndarray
        Signal with spikes replaced (same unit as ``x``).
    spikes : ndarray of bool
        Which samples were replaced.
    """
    x = np.asarray(x, dtype=float)
    k = max(int(half_width), 1)
    d = np.abs(np.diff(x))
    step = float(d[d > 0].min()) if (d > 0).any() else 0.0
    floor = max(1.4826 * float(np.median(d)) / np.sqrt(2.0), step) if len(d) else 0.0
    limit = n_sigma * floor
    padded = np.pad(x, k, mode="reflect" if len(x) > k else "edge")  # scipy.ndimage's "mirror" / "nearest"
    win = sliding_window_view(padded, 2 * k + 1)
    # Only a sample beyond n_sigma * floor of its window median can be a spike, and the median
    # m_i of 2k+1 values is below a (above b) exactly when at least k+1 of them are: counting
    # those against x_i -/+ the limit (less a margin far above the rounding) finds every candidate
    # without sorting each window; the exact median and MAD are taken for the candidates alone.
    margin = 1e-9 * (limit + np.abs(x))
    need = k + 1
    lo, hi = x - limit + margin, x + limit - margin
    below = np.zeros(len(x), dtype=np.intp)
    above = np.zeros(len(x), dtype=np.intp)
    for j in range(2 * k + 1):  # window offset j: contiguous slices, no (n, 2k+1) temporary
        below += padded[j : j + len(x)] < lo
        above += padded[j : j + len(x)] > hi
    cand = np.flatnonzero((below >= need) | (above >= need))
    y = x.copy()
    spikes = np.zeros(len(x), dtype=bool)
    for s in range(0, len(cand), chunk):
        c = cand[s : s + chunk]
        med = np.partition(win[c], k, axis=1)[:, k]  # the middle of 2k+1 values: the median exactly
        mad = np.median(np.abs(win[c] - med[:, None]), axis=1)
        is_bad = np.abs(x[c] - med) > n_sigma * np.maximum(1.4826 * mad, floor)
        y[c[is_bad]] = med[is_bad]
        spikes[c[is_bad]] = True
    return y, spikes


@dataclass(frozen=True)
class SteadyWindow:
    """One window of whole electrical revolutions at a steady operating point.

    Attributes
    ----------
    t_start, t_end : float
        Window start and end (s).
    n_revs : int
        Electrical revolutions in the window.
    T_avg_nm : float
        Mean despiked torque (N*m).
    raw_pp_nm, filtered_pp_nm : float
        Peak-to-peak torque, despiked and despiked + low-passed (N*m).
    raw_pct, filtered_pct : float
        Peak-to-peak over |T_avg| (%); NaN where |T_avg| is zero.
    speed_rpm : float
        Mean mechanical speed (rpm), signed.
    i_qo_a : float
        Mean nominal q current (A); NaN when the capture has none.
    no_mech1_pp_nm, no_mech1_pct : float
        Filtered peak-to-peak (N*m, %) with the window's mechanical order 1 taken out; NaN when
        the window holds less than half a mechanical revolution.
    """

    t_start: float
    t_end: float
    n_revs: int
    T_avg_nm: float
    raw_pp_nm: float
    filtered_pp_nm: float
    raw_pct: float
    filtered_pct: float
    speed_rpm: float
    i_qo_a: float
    no_mech1_pp_nm: float = float("nan")
    no_mech1_pct: float = float("nan")


@dataclass(frozen=True)
class RipplePP:
    """Peak-to-peak torque ripple of a capture (definition in ``docs/metrics.md``).

    Attributes
    ----------
    raw_pct, filtered_pct : float
        Median over the windows of the per-window p-p percent (%), despiked, and despiked +
        low-passed.
    raw_pct_max, filtered_pct_max : float
        Largest per-window value (%).
    raw_pp_nm, filtered_pp_nm : float
        Median per-window p-p (N*m).
    T_avg_nm : float
        Mean torque over all windows (N*m).
    speed_rpm : float
        Mean mechanical speed over all windows (rpm).
    windows : tuple[SteadyWindow, ...]
        Every window that counted.
    window_revs : int
        Most electrical revolutions in a window (each window has its own ``n_revs``).
    segments : tuple[tuple[float, float], ...]
        Steady runs after the settle time (s): where the windows were cut from.
    cutoff_order : float
        Low-pass cut-off as a multiple of the electrical frequency.
    n_spikes : int
        Samples the Hampel filter replaced in the whole record.
    no_mech1_pct : float
        Median over the windows of the filtered p-p with the mechanical order 1 taken out (%);
        NaN when no window holds half a mechanical revolution.
    """

    raw_pct: float
    filtered_pct: float
    raw_pct_max: float
    filtered_pct_max: float
    raw_pp_nm: float
    filtered_pp_nm: float
    T_avg_nm: float
    speed_rpm: float
    windows: tuple[SteadyWindow, ...]
    window_revs: int
    segments: tuple[tuple[float, float], ...]
    cutoff_order: float
    n_spikes: int
    no_mech1_pct: float = float("nan")


def _percent(pp_nm: float, mean_nm: float) -> float:
    """Peak-to-peak (N*m) as percent of |mean| (N*m); NaN when the mean is zero."""
    return 100.0 * pp_nm / abs(mean_nm) if mean_nm != 0.0 else float("nan")


def without_mech1(y: np.ndarray, theta_r: np.ndarray, pole_pairs: int) -> np.ndarray:
    """``y`` less its least-squares mechanical order 1 against ``theta_r / pole_pairs``.

    Parameters
    ----------
    y : ndarray
        Torque samples (N*m), best over whole mechanical revolutions (over a part of one the
        order-1 term is fitted on that arc).
    theta_r : ndarray
        Electrical angle (rad) at the same samples; its offset does not matter (the phase of
        the order-1 term is free).
    pole_pairs : int
        P/2.
    """
    theta_m = np.asarray(theta_r, dtype=float) / pole_pairs
    X = np.column_stack([np.ones_like(theta_m), np.cos(theta_m), np.sin(theta_m)])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    return y - X[:, 1:] @ coef[1:]


def ripple_pp(
    t: np.ndarray,
    torque: np.ndarray,
    theta_r: np.ndarray,
    *,
    poles: int,
    i_qo: np.ndarray | None = None,
    window_revs: int | None = None,
    settle_s: float = 0.1,
    speed_tol: float = 0.02,
    iq_tol_a: float = IQ_TOL_A,
    iq_tol_rel: float = IQ_TOL_REL,
    cutoff_order: float = 48.0,
    filter_order: int = 6,
    hampel_half_width_s: float = 0.5e-3,
    hampel_sigma: float = 3.0,
    source: str = "<memory>",
) -> RipplePP:
    """Peak-to-peak torque ripple over steady windows, raw and filtered.

    Parameters
    ----------
    t : ndarray
        Sample times (s), uniformly sampled.
    torque : ndarray
        Shaft torque (N*m).
    theta_r : ndarray
        Unwrapped electrical angle (rad), e.g. from :func:`eol_cal.analysis.angle.reconstruct_angle`.
    poles : int
        Number of poles P (the default window is one mechanical revolution, P/2 electrical).
    i_qo : ndarray, optional
        Nominal q current per sample (A); without it only the speed decides steadiness.
    window_revs : int, optional
        Electrical revolutions per window, for every run (runs that hold fewer give no
        window). Default: per run, P/2 where the run holds that many after the settle time,
        else as many whole revolutions as it holds (at least 1).
    settle_s : float
        Time dropped at the start of every steady run (s).
    speed_tol : float
        Relative speed tolerance between the revolutions of a run.
    iq_tol_a, iq_tol_rel : float
        i_qo tolerance ``max(iq_tol_a, iq_tol_rel*|i_qo|)`` (A).
    cutoff_order : float
        Low-pass cut-off of the filtered figure as a multiple of the run's electrical
        frequency (48 = 8 times the 6th harmonic).
    filter_order : int
        Butterworth order of one pass of the zero-phase low-pass.
    hampel_half_width_s : float
        Half window of the Hampel despiking filter (s); at least one sample.
    hampel_sigma : float
        Hampel threshold (robust standard deviations).
    source : str
        File name for error messages.

    Returns
    -------
    RipplePP
    """
    t = np.asarray(t, dtype=float)
    torque = np.asarray(torque, dtype=float)
    theta_r = np.asarray(theta_r, dtype=float)
    i_qo = None if i_qo is None else np.asarray(i_qo, dtype=float)
    if not (len(t) == len(torque) == len(theta_r)):
        raise InputError(source, "torque", "torque, time and angle differ in length")
    if not np.all(np.isfinite(torque)):
        raise InputError(source, "torque", "torque holds NaN or infinite values")
    fs = (len(t) - 1) / (t[-1] - t[0])
    despiked, spikes = hampel(torque, max(1, round(hampel_half_width_s * fs)), hampel_sigma)

    if np.ptp(theta_r) < TWO_PI:
        raise InputError(source, "torque", "the capture does not hold one whole electrical revolution")
    # Each direction of rotation is judged on its own (a reversal is never steady).
    pieces = direction_pieces(np.gradient(theta_r, t))
    # Steadiness is judged per 60-degree unit: one period of the 6th harmonic, so its speed
    # ripple does not move a unit's mean speed, and a run starts at most 60 deg after a change.
    runs_units: list[tuple[list[int], np.ndarray, bool]] = []  # (run, unit bounds, ends the record)
    for a, b in pieces:
        units = revolution_bounds(theta_r[a:b], per_rev=UNITS_PER_REV) + a
        if len(units) < 2:
            continue
        for run in steady_runs(t, units, i_qo, speed_tol, iq_tol_a, iq_tol_rel):
            runs_units.append((run, units, run[-1] == len(units) - 2 and b == len(t)))

    windows: list[SteadyWindow] = []
    segments: list[tuple[float, float]] = []
    filtered_cache: dict[float, np.ndarray] = {}
    for run, units, at_end in runs_units:
        t_run0, t_run1 = t[units[run[0]]], t[units[run[-1] + 1]]
        f_e = len(run) / UNITS_PER_REV / (t_run1 - t_run0)
        f_c = cutoff_order * f_e
        # Unless the run ends the record, the low-pass smears what follows (an unsteady unit,
        # a reversal) back into it by about its impulse response: keep clear of it.
        guard = 0.0 if at_end else 2.0 / f_c
        i0 = int(np.searchsorted(t, t_run0 + settle_s - 1e-12, side="left"))
        i1 = int(np.searchsorted(t, t_run1 - guard + 1e-12, side="right"))
        if i1 - i0 < 2:
            continue
        revs = revolution_bounds(theta_r[i0:i1]) + i0  # whole revolutions from the usable start
        n_avail = len(revs) - 1
        n_w = int(window_revs) if window_revs is not None else min(poles // 2, n_avail)
        if n_w < 1 or n_avail < n_w:
            continue
        key = round(f_c, 9)
        if key not in filtered_cache:
            filtered_cache[key] = lowpass_zero_phase(despiked, fs, f_c, filter_order)
        filt = filtered_cache[key]
        n_win = n_avail // n_w
        segments.append((float(t[revs[0]]), float(t[revs[n_win * n_w]])))
        for w in range(n_win):
            k0, k1 = revs[w * n_w], revs[(w + 1) * n_w]
            sl = slice(k0, k1)
            raw_w, filt_w = despiked[sl], filt[sl]
            mean = float(raw_w.mean())
            pp_raw = float(raw_w.max() - raw_w.min())
            pp_filt = float(filt_w.max() - filt_w.min())
            dt = t[k1] - t[k0]
            dtheta = theta_r[k1] - theta_r[k0]
            pp_nm1 = float("nan")
            if 2 * n_w >= poles // 2:
                rest = without_mech1(filt_w, theta_r[sl], poles // 2)
                pp_nm1 = float(rest.max() - rest.min())
            windows.append(
                SteadyWindow(
                    t_start=float(t[k0]),
                    t_end=float(t[k1]),
                    n_revs=n_w,
                    T_avg_nm=mean,
                    raw_pp_nm=pp_raw,
                    filtered_pp_nm=pp_filt,
                    raw_pct=_percent(pp_raw, mean),
                    filtered_pct=_percent(pp_filt, mean),
                    speed_rpm=float(dtheta / dt / (poles / 2) * 60.0 / TWO_PI),
                    i_qo_a=float(np.mean(i_qo[sl])) if i_qo is not None else float("nan"),
                    no_mech1_pp_nm=pp_nm1,
                    no_mech1_pct=_percent(pp_nm1, mean),
                )
            )
    if not windows:
        need = f"{window_revs}" if window_revs is not None else "one"
        raise InputError(
            source, "torque",
            f"no steady window of {need} whole electrical revolution(s) after {settle_s} s settling "
            f"(speed within {speed_tol:.0%}, i_qo within max({iq_tol_a} A, {iq_tol_rel:.0%}))",
        )

    raw = np.array([w.raw_pct for w in windows])
    filt = np.array([w.filtered_pct for w in windows])
    weights = np.array([w.t_end - w.t_start for w in windows])
    no_mech1 = [w.no_mech1_pct for w in windows if np.isfinite(w.no_mech1_pct)]
    return RipplePP(
        raw_pct=float(np.median(raw)),
        filtered_pct=float(np.median(filt)),
        raw_pct_max=float(np.max(raw)),
        filtered_pct_max=float(np.max(filt)),
        raw_pp_nm=float(np.median([w.raw_pp_nm for w in windows])),
        filtered_pp_nm=float(np.median([w.filtered_pp_nm for w in windows])),
        T_avg_nm=float(np.average([w.T_avg_nm for w in windows], weights=weights)),
        speed_rpm=float(np.average([w.speed_rpm for w in windows], weights=weights)),
        windows=tuple(windows),
        window_revs=max(w.n_revs for w in windows),
        segments=tuple(segments),
        cutoff_order=float(cutoff_order),
        n_spikes=int(spikes.sum()),
        no_mech1_pct=float(np.median(no_mech1)) if no_mech1 else float("nan"),
    )


def capture_ripple_pp(capture: Capture, angle: AngleResult | None = None, **kwargs: Any) -> RipplePP:
    """:func:`ripple_pp` on a :class:`~eol_cal.capture.data.Capture`.

    Parameters
    ----------
    capture : Capture
        Needs ``torque``, the angle's channels, and ``iq_ref`` (channel or metadata) if
        the steadiness of i_qo is to be judged.
    angle : AngleResult, optional
        Reconstructed angle; computed with :func:`eol_cal.analysis.angle.capture_angle`
        when not given.
    **kwargs
        Passed to :func:`ripple_pp`.
    """
    if not capture.has("torque"):
        raise InputError(capture.source, "torque", "missing channel")
    if angle is None:
        angle = capture_angle(capture)
    i_qo = capture.iq_ref() if ("iq_ref" in capture.channels or "iq_ref" in capture.metadata) else None
    return ripple_pp(
        capture.t, capture["torque"], angle.theta_r, poles=capture.poles, i_qo=i_qo, source=capture.source, **kwargs
    )
