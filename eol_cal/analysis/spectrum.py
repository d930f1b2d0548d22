"""Order spectrum of torque against electrical angle, and the encoder's quantisation figures.

Convention: each order n contributes ``amplitude[n] * cos(n*theta_r + phase[n])`` (N*m, rad)
with theta_r the electrical angle in the hall frame (``docs/angle-frame.md``). The contract's
ripple model writes ``-c * sin(6*theta + phi)``; that is ``c * cos(6*theta + phi + pi/2)``, so
``phi = wrap(phase[6] - pi/2)`` and ``c = amplitude[6]`` for a single such term.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eol_cal.analysis.angle import AngleResult, capture_angle
from eol_cal.analysis.edges import level_changes
from eol_cal.analysis.metrics import eta_percent
from eol_cal.capture.data import Capture
from eol_cal.errors import InputError
from eol_cal.numerics.wrap import wrap_pi

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True, eq=False)
class OrderSpectrum:
    """Amplitude and phase of torque at electrical orders.

    Attributes
    ----------
    orders : ndarray of int
        Electrical orders (1..max_order).
    amplitude_nm : ndarray
        Amplitude at each order (N*m), one-sided (the cosine's amplitude).
    phase_rad : ndarray
        Phase at each order (rad), wrapped to (-pi, pi]; the term is ``A*cos(n*theta + phase)``.
    mech1_amplitude_nm, mech1_phase_rad : float
        Mechanical order 1 (electrical order 2/P) against the mechanical angle
        ``theta_r / (P/2)``; NaN when less than one mechanical revolution was available.
    T_avg_nm : float
        Mean torque over the analysed span (N*m).
    n_elec_revs : int
        Whole electrical revolutions analysed.
    span_s : tuple[float, float]
        Start and end time of the analysed span (s).
    """

    orders: np.ndarray
    amplitude_nm: np.ndarray
    phase_rad: np.ndarray
    mech1_amplitude_nm: float
    mech1_phase_rad: float
    T_avg_nm: float
    n_elec_revs: int
    span_s: tuple[float, float]

    def amplitude(self, order: int) -> float:
        """Amplitude at electrical order ``order`` (N*m)."""
        return float(self.amplitude_nm[int(order) - 1])

    def phase(self, order: int) -> float:
        """Phase at electrical order ``order`` (rad)."""
        return float(self.phase_rad[int(order) - 1])


def _longest_monotone(theta: np.ndarray) -> slice:
    """Longest stretch of samples over which the angle moves one way (ties allowed)."""
    d = np.sign(np.diff(theta))
    # Carry the last non-zero direction over standstill samples.
    idx = np.where(d != 0, np.arange(len(d)), 0)
    np.maximum.accumulate(idx, out=idx)
    d = d[idx]
    change = np.flatnonzero(d[1:] != d[:-1]) + 1
    starts = np.concatenate(([0], change))
    ends = np.concatenate((change, [len(d)]))
    k = int(np.argmax(ends - starts))
    return slice(int(starts[k]), int(ends[k]) + 1)


def order_spectrum(
    theta_r: np.ndarray,
    torque: np.ndarray,
    poles: int,
    t: np.ndarray | None = None,
    max_order: int = 36,
    source: str = "<memory>",
) -> OrderSpectrum:
    """Order spectrum of torque against electrical angle over whole revolutions.

    The longest one-way stretch of the record is trimmed to whole mechanical revolutions
    (to whole electrical ones when it holds less than a mechanical revolution), torque is
    resampled linearly onto a uniform angle grid with at least as many points as the stretch
    has samples, and an FFT gives the orders.

    Parameters
    ----------
    theta_r : ndarray
        Unwrapped electrical angle per sample (rad).
    torque : ndarray
        Torque per sample (N*m).
    poles : int
        Number of poles P.
    t : ndarray, optional
        Sample times (s), only to report the span.
    max_order : int
        Highest electrical order returned.
    source : str
        File name for error messages.

    Returns
    -------
    OrderSpectrum
    """
    theta_r = np.asarray(theta_r, dtype=float)
    torque = np.asarray(torque, dtype=float)
    sl = _longest_monotone(theta_r)
    th, tq = theta_r[sl], torque[sl]
    tt = None if t is None else np.asarray(t, dtype=float)[sl]
    sign = 1.0 if th[-1] >= th[0] else -1.0
    travel = sign * (th - th[0])
    pp = poles // 2
    n_mech = int(np.floor(travel[-1] / (TWO_PI * pp)))
    n_elec = n_mech * pp if n_mech >= 1 else int(np.floor(travel[-1] / TWO_PI))
    if n_elec < 1:
        raise InputError(source, "torque", "less than one whole electrical revolution in one direction: no spectrum")
    span = n_elec * TWO_PI
    end = int(np.searchsorted(travel, span, side="left"))
    n_grid = max(int(end), 8 * max_order * n_elec)
    n_grid += (-n_grid) % n_elec  # a whole number of points per revolution
    grid = np.arange(n_grid) * (span / n_grid)
    # np.interp needs increasing x: travel is non-decreasing; drop standstill duplicates.
    keep = np.concatenate(([True], np.diff(travel[: end + 1]) > 0))
    x = travel[: end + 1][keep]
    y = tq[: end + 1][keep]
    resampled = np.interp(grid, x, y)
    spec = np.fft.rfft(resampled) / n_grid
    # On the grid theta = theta_start + sign*grid, so order n's phase gains n*theta_start and
    # flips sign with the direction.
    theta_start = float(th[0])

    def term(bin_index: int, order: float) -> tuple[float, float]:
        c = spec[bin_index]
        amp = 2.0 * abs(c)
        ph = sign * np.angle(c) - order * theta_start
        return float(amp), float(wrap_pi(ph))

    orders = np.arange(1, max_order + 1)
    amp = np.empty(len(orders))
    ph = np.empty(len(orders))
    for i, n in enumerate(orders):
        amp[i], ph[i] = term(int(n * n_elec), float(n))
    if n_mech >= 1:
        m_amp, m_ph = term(n_mech, 1.0 / pp)
    else:
        m_amp, m_ph = float("nan"), float("nan")
    span_s = (float(tt[0]), float(tt[min(end, len(tt) - 1)])) if tt is not None else (float("nan"), float("nan"))
    return OrderSpectrum(
        orders=orders,
        amplitude_nm=amp,
        phase_rad=ph,
        mech1_amplitude_nm=m_amp,
        mech1_phase_rad=m_ph,
        T_avg_nm=float(spec[0].real),
        n_elec_revs=n_elec,
        span_s=span_s,
    )


@dataclass(frozen=True)
class QuantisationFigures:
    """How coarse the raw encoder angle is, against the reconstructed angle.

    Attributes
    ----------
    deg_per_count : float
        Electrical degrees per count of A rising edges, ``P*180/N_enc`` (deg; seed eq. 9).
    deg_per_edge : float
        Electrical degrees between adjacent edges used by the reconstruction (deg).
    enc_error_rms_deg, enc_error_max_deg : float
        RMS and max of ``theta_r - theta_enc`` (electrical deg), with ``theta_enc`` the raw
        encoder angle of seed eq. (8): the reconstructed angle held from each rising edge of
        A to the next, as a firmware without interpolation sees it.
    eta_pct : float
        Ripple index of seed eq. (12) for this encoder and motor (%).
    """

    deg_per_count: float
    deg_per_edge: float
    enc_error_rms_deg: float
    enc_error_max_deg: float
    eta_pct: float


def quantisation_figures(capture: Capture, angle: AngleResult | None = None) -> QuantisationFigures:
    """Angle-quantisation figures of a capture's encoder.

    Parameters
    ----------
    capture : Capture
        Needs ``enc_a``, ``hall`` and metadata ``poles``, ``encoder_ppr``.
    angle : AngleResult, optional
        Reconstructed angle; computed when not given.

    Returns
    -------
    QuantisationFigures
    """
    if angle is None:
        angle = capture_angle(capture)
    P, N_enc = capture.poles, capture.encoder_ppr
    t = capture.t
    t_a, lev = level_changes(t, capture["enc_a"], capture.events.get("enc_a"))
    t_rise = t_a[lev == 1]
    if len(t_rise) < 1:
        raise InputError(capture.source, "enc_a", "no rising edge of channel A")
    theta_rise = np.interp(t_rise, t, angle.theta_r)
    after = t >= t_rise[0]
    held = np.searchsorted(t_rise, t[after], side="right") - 1
    err = np.rad2deg(angle.theta_r[after] - theta_rise[held])
    return QuantisationFigures(
        deg_per_count=P * 180.0 / N_enc,
        deg_per_edge=float(np.rad2deg(angle.edge_step_rad)),
        enc_error_rms_deg=float(np.sqrt(np.mean(err**2))),
        enc_error_max_deg=float(np.max(np.abs(err))),
        eta_pct=float(eta_percent(N_enc, P)),
    )


def capture_spectrum(capture: Capture, angle: AngleResult | None = None, span_s: tuple[float, float] | None = None,
                     max_order: int = 36) -> OrderSpectrum:
    """:func:`order_spectrum` of a capture's torque, optionally over a time span.

    Parameters
    ----------
    capture : Capture
        Needs ``torque`` and the angle's channels.
    angle : AngleResult, optional
        Reconstructed angle; computed when not given.
    span_s : (float, float), optional
        Only the samples with ``span_s[0] <= t < span_s[1]`` (s), e.g. a steady run.
    max_order : int
        Highest electrical order.
    """
    if not capture.has("torque"):
        raise InputError(capture.source, "torque", "missing channel")
    if angle is None:
        angle = capture_angle(capture)
    mask: slice | np.ndarray = slice(None)
    if span_s is not None:
        mask = (capture.t >= span_s[0]) & (capture.t < span_s[1])
    return order_spectrum(angle.theta_r[mask], capture["torque"][mask], capture.poles, t=capture.t[mask],
                          max_order=max_order, source=capture.source)
