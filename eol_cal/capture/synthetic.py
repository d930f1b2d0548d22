"""An analytic motion-and-ripple model that makes captures with a known answer.

Constant mechanical speed, so the rotor angle is exact at every instant. The measured torque is

    T = kt*i_qo*cos(dtheta) - c6*sin(6*theta_r + phase_c6) - k6*i_qo*sin(6*theta_r + phase_k6) + noise

where ``theta_r`` is the electrical angle and ``dtheta`` the encoder quantisation error of the
seed paper, eq. (8)-(10): the controller's angle ``theta_enc = P*pi*n/N_enc`` steps at each rising
edge of channel A, so ``dtheta = theta_r - theta_enc`` is a saw tooth in ``[0, P*pi/N_enc)`` and
``kt*i_qo*(1 - cos(dtheta))`` is the torque the quantised angle loses (paper eq. 10, with
``kt = 3P/4*psi_f``). The ripple terms are those of the firmware contract's ripple model.

Encoder and halls follow the contract: channel A high for the first half of each of the
``N_enc`` pulses per mechanical revolution, B a quarter pitch behind A, halls U/V/W high on
[0, 180), [120, 300), [240, 60) electrical degrees. Their change times are computed exactly
and kept in ``Capture.events``; the sampled levels are the zero-order hold of those events.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from eol_cal.capture.columns import zoh
from eol_cal.capture.ecu_state import EcuState, with_ecu_state
from eol_cal.capture.data import Capture
from eol_cal.domain.motor_params import MotorParams, load_motor

MODEL_NAME = "analytic-v1"


def hall_state(theta_r: np.ndarray) -> np.ndarray:
    """Hall state (U = bit0, V = bit1, W = bit2) at electrical angle ``theta_r`` (rad)."""
    deg = np.mod(np.degrees(theta_r), 360.0)
    u = deg < 180.0
    v = (deg >= 120.0) & (deg < 300.0)
    w = (deg >= 240.0) | (deg < 60.0)
    return (u.astype(np.int8) | (v.astype(np.int8) << 1) | (w.astype(np.int8) << 2)).astype(np.int8)


def _square(x: np.ndarray) -> np.ndarray:
    """1 on the first half of each unit period of ``x``, else 0."""
    return (np.mod(x, 1.0) < 0.5).astype(np.int8)


def _crossings(x0: float, rate: float, t0: float, t1: float, step: float) -> np.ndarray:
    """Times in (t0, t1] at which ``x0 + rate*(t - t0)`` crosses a multiple of ``step``."""
    if rate == 0.0:
        return np.empty(0)
    xa, xb = x0, x0 + rate * (t1 - t0)
    lo, hi = min(xa, xb), max(xa, xb)
    k = np.arange(math.floor(lo / step), math.ceil(hi / step) + 1) * step
    k = k[(k > lo) & (k <= hi)] if rate > 0 else k[(k >= lo) & (k < hi)]
    times = t0 + (k - x0) / rate
    return np.sort(times)


def _events(
    level_of: Callable[[np.ndarray], np.ndarray], x0: float, rate: float, t0: float, t1: float, step: float
) -> tuple[np.ndarray, np.ndarray, int]:
    """Exact (change times, new levels) and the level at ``t0`` of a function of ``x``."""
    times = _crossings(x0, rate, t0, t1, step)
    # the new level is the one just past the boundary in the direction of motion
    after = x0 + rate * (times - t0) + math.copysign(step / 2, rate)
    # level just after t0, so that a boundary exactly at t0 is no event
    initial = int(level_of(np.array([x0 + math.copysign(1e-9 * step, rate or 1.0)]))[0])
    levels = level_of(after)
    return times, levels, initial


def synthetic_capture(
    rpm: float = 60.0,
    i_qo: float = 65.0,
    seconds: float = 1.0,
    fs: float = 20000.0,
    k6: float = 0.00062,
    phase_k6: float = 0.3,
    c6: float = 0.004,
    phase_c6: float = 1.1,
    noise: float = 0.002,
    seed: int = 0,
    theta_r0: float = 0.0,
    torque_lsb: float = 1e-5,
    motor: MotorParams | None = None,
    serial: str = "SYN-0001",
    iq_ref_channel: bool = True,
) -> Capture:
    """A capture of the analytic model (see the module docstring), with ``truth.*`` set.

    Parameters
    ----------
    rpm : float
        Constant mechanical speed (rpm); negative turns backwards.
    i_qo : float
        Nominal q current (A).
    seconds : float
        Duration (s).
    fs : float
        Sample rate (Hz).
    k6 : float
        Load-proportional 6th-harmonic ripple coefficient (N*m/A).
    phase_k6 : float
        Its phase (rad).
    c6 : float
        Cogging 6th-harmonic amplitude (N*m).
    phase_c6 : float
        Its phase (rad).
    noise : float
        Standard deviation of white torque noise (N*m).
    seed : int
        Seed of the noise generator.
    theta_r0 : float
        Electrical angle at t = 0 (rad); the encoder's pulse 0 starts at theta_r = 0.
    torque_lsb : float
        Resolution of the torque transducer (N*m); 0 keeps full float precision.
    motor : MotorParams, optional
        Motor (poles P, N_enc, kt); default the ``paper`` preset.
    serial : str
        Metadata serial.
    iq_ref_channel : bool
        Carry i_qo as an ``iq_ref`` channel (else as metadata ``iq_ref``).

    Returns
    -------
    Capture
        Channels ``torque`` (N*m), ``enc_a``, ``enc_b``, ``hall``, ``speed`` (rpm) and
        ``iq_ref`` (A); exact edge times in ``events``; the model's parameters in ``truth``.
    """
    motor = motor or load_motor("paper")
    P, N_enc, kt = motor.poles, motor.N_enc, motor.kt
    n = int(round(seconds * fs))
    t = np.arange(n) / fs
    omega_r = rpm * 2.0 * math.pi / 60.0 * P / 2  # electrical rad/s
    theta_r = theta_r0 + omega_r * t
    # x counts encoder pulses: A rises at integer x, theta_r = 0 at x = 0
    x_rate = omega_r * N_enc / (math.pi * P)
    x0 = theta_r0 * N_enc / (math.pi * P)
    x = x0 + x_rate * t
    dtheta = math.pi * P / N_enc * np.mod(x, 1.0)
    rng = np.random.default_rng(seed)
    torque = (
        kt * i_qo * np.cos(dtheta)
        - c6 * np.sin(6 * theta_r + phase_c6)
        - k6 * i_qo * np.sin(6 * theta_r + phase_k6)
        + noise * rng.standard_normal(n)
    )
    if torque_lsb > 0:
        torque = np.round(torque / torque_lsb) * torque_lsb
    t1 = float(t[-1])
    events = {
        "enc_a": _events(_square, x0, x_rate, 0.0, t1, 0.5),
        "enc_b": _events(_square, x0 - 0.25, x_rate, 0.0, t1, 0.5),
        "hall": _events(hall_state, theta_r0, omega_r, 0.0, t1, math.pi / 3),
    }
    channels: dict[str, np.ndarray] = {"torque": torque}
    capture_events: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, (times, levels, initial) in events.items():
        all_times = np.concatenate([[0.0], times])
        all_levels = np.concatenate([[initial], levels]).astype(np.int8)
        channels[name] = zoh(all_times, all_levels, t).astype(np.int8)
        capture_events[name] = (times, levels.astype(np.int8))
    metadata: dict[str, str | int | float] = {
        "serial": serial,
        "poles": P,
        "encoder_ppr": N_enc,
        "kt": kt,
        "comment": f"eol_cal.capture.synthetic {MODEL_NAME}",
    }
    if iq_ref_channel:
        channels["iq_ref"] = np.full(n, float(i_qo))
    else:
        metadata["iq_ref"] = float(i_qo)
    channels["speed"] = np.full(n, float(rpm))
    # the model's controller runs the raw encoder angle without compensation: an ECU with no
    # valid block, all along (eol_cal.capture.ecu_state)
    metadata = with_ecu_state(metadata, EcuState(None), EcuState(None))
    truth: dict[str, str | int | float] = {
        "model": MODEL_NAME,
        "k6": float(k6),
        "phase_k6": float(phase_k6),
        "c6": float(c6),
        "phase_c6": float(phase_c6),
        "rpm": float(rpm),
        "i_qo": float(i_qo),
        "theta_r0": float(theta_r0),
        "noise": float(noise),
        "seed": int(seed),
    }
    return Capture(t=t, channels=channels, metadata=metadata, truth=truth, events=capture_events, source="<synthetic>")
