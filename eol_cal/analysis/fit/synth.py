"""Analytic torque records for testing and benchmarking the fit at the array level.

Evaluates the contract's ripple model sample by sample (not through the fit's compressed
segments), with a delayed transducer, drift, a mechanical order-1 term and white noise. The
capture-level generator (encoder, halls, files) is :mod:`eol_cal.capture.synthetic`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from eol_cal.analysis.fit import SteadySegments


def synthetic_segments(
    rng: np.random.Generator,
    *,
    k6: float = 0.00062,
    phase_k6: float = 0.4,
    c6: float = 0.004,
    phase_c6: float = -1.1,
    delay_s: float = 1.5e-4,
    loads_a: tuple[float, ...] = (20.0, 60.0),
    speeds_rpm: tuple[float, ...] = (300.0, 600.0),
    directions: tuple[int, ...] = (1,),
    seg_s: float = 0.25,
    fs_hz: float = 20000.0,
    noise_nm: float = 0.01,
    kt: float = 0.04905,
    pole_pairs: int = 3,
    mech_nm: float = 0.003,
    drift_nm_per_s: float = 0.01,
    extra: dict[int, tuple[float, float, float, float]] | None = None,
    transducer: str = "lowpass",
    path_response: Callable[[np.ndarray], np.ndarray] | None = None,
    iq6: tuple[float, float] | None = None,
) -> tuple[SteadySegments, dict]:
    """One motor's segments: every load x speed x direction, each ``seg_s`` long.

    Parameters
    ----------
    rng : numpy Generator
        Noise and random start angles.
    k6 : float
        Load-proportional 6th-harmonic coefficient (N*m/A); ``phase_k6`` (rad).
    c6 : float
        Load-independent 6th-harmonic amplitude (N*m); ``phase_c6`` (rad).
    delay_s : float
        Torque transducer delay (s).
    loads_a, speeds_rpm, directions
        Load points i_qo (A), mechanical speeds (rpm), directions (+1/-1); torque sign follows
        i_qo.
    seg_s, fs_hz
        Segment length (s) and sample rate (Hz).
    noise_nm : float
        White measurement noise, standard deviation (N*m).
    kt : float
        Torque constant (N*m/A).
    pole_pairs : int
        P/2.
    mech_nm : float
        Mechanical order-1 amplitude (N*m), random phase per segment.
    drift_nm_per_s : float
        Linear torque drift (N*m/s).
    extra : dict, optional
        Higher harmonics: order -> (c, phase_c, k, phase_k).
    transducer : {"delay", "lowpass"}
        ``delay``: the torque is seen ``delay_s`` late; ``lowpass``: through a first-order
        low-pass of time constant ``delay_s`` (each harmonic's steady-state gain and phase).
    path_response : callable, optional
        The bench's air-gap-to-shaft response (:attr:`SteadySegments.path_response`), applied to
        every harmonic before the transducer and handed to the fit with the segments.
    iq6 : (float, float), optional
        The ECU's own 6th-order current ripple, ``(a, phase)`` (a in 1 / (rad/s) of electrical speed,
        phase in rad): ``i_q = i_qo (1 + a |omega_e| sin(6 theta + phase))``, growing with load and
        speed as the current loop's reaction does; air-gap torque ``kt i_q`` through the path and
        the transducer like the motor's ripple. The segments then carry ``kt_iq``.

    Returns
    -------
    (SteadySegments, dict)
        The segments and the truth (keys ``k6``, ``phase_k6``, ``c6``, ``phase_c6``, ``delay_s``).
    """
    terms = {6: (c6, phase_c6, k6, phase_k6)}
    terms.update(extra or {})
    thetas, ts, ys, iqs, omegas, labels, kt_iq = [], [], [], [], [], [], []
    t_start = 0.0
    n = int(round(seg_s * fs_hz))
    for direction in directions:
        for rpm in speeds_rpm:
            for i_qo in loads_a:
                omega_e = direction * rpm * 2 * math.pi / 60 * pole_pairs
                t = t_start + np.arange(n) / fs_hz
                theta0 = rng.uniform(0, 2 * math.pi)
                theta = theta0 + omega_e * (t - t_start)
                seen = theta - omega_e * delay_s  # the transducer reports torque delay_s late
                torque = kt * i_qo + drift_nm_per_s * (t - t_start)
                torque = torque + mech_nm * np.sin(seen / pole_pairs + rng.uniform(0, 2 * math.pi))
                for h, (c, pc, k, pk) in terms.items():
                    path = complex(path_response(np.array([h * omega_e]))[0]) if path_response else 1.0
                    if transducer == "lowpass":
                        gain = path / (1.0 + 1j * h * omega_e * delay_s)
                        arg, g = h * theta + np.angle(gain), abs(gain)
                    else:
                        arg, g = h * seen + np.angle(path), abs(path)
                    torque = torque - g * c * np.sin(arg + pc) - g * k * i_qo * np.sin(arg + pk)
                    if h == 6 and iq6 is not None:
                        torque = torque + g * kt * i_qo * iq6[0] * abs(omega_e) * np.sin(arg + iq6[1])
                if iq6 is not None:
                    kt_iq.append(kt * i_qo * (1.0 + iq6[0] * abs(omega_e) * np.sin(6 * theta + iq6[1])))
                torque = torque + rng.normal(0.0, noise_nm, n)
                thetas.append(theta)
                ts.append(t)
                ys.append(torque)
                iqs.append(i_qo)
                omegas.append(omega_e)
                labels.append(f"synthetic {direction:+d} {rpm:g} rpm {i_qo:g} A")
                t_start = t[-1] + 1.0 / fs_hz
    seg = SteadySegments(thetas, ts, ys, np.array(iqs), np.array(omegas), pole_pairs, labels, path_response,
                         kt_iq if iq6 is not None else None)
    truth = {"k6": k6, "phase_k6": phase_k6, "c6": c6, "phase_c6": phase_c6, "delay_s": delay_s,
             "transducer": transducer}
    return seg, truth
