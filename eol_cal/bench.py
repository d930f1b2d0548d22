"""The dyno bench's mechanics, and what they do to the torque the transducer measures.

The transducer sits in the shaft between the motor's rotor (inertia ``J``) and the dyno (inertia
``J_dyno``, held at speed by its drive's PI loop). A ripple torque of the motor reaches the shaft
only in part: a share of it accelerates the rotor, near the torsion mode the shaft amplifies it,
and the speed ripple it causes moves the back-EMF, which the ECU's current loop does not fully
reject, so the current (and with it the torque) ripples a little against it.
:func:`shaft_response` is that transfer, ``T_shaft / T_ripple``, for the linear models the plant
integrates (:mod:`eol_cal.plant.dyno`, :mod:`eol_cal.plant.motor`, the PI of
:meth:`eol_cal.motor.MotorParams.current_pi_gains`). The ripple fit divides it out, so that k6
and c6 are the motor's own at constant current (what the compensating current has to cancel),
not the bench's view of them: on the paper bench the shaft sees 0.4 % less of the 6th at 60 rpm
than the motor makes, and the current loop takes another 0.3 %.

Benches are TOML files (``eol_cal/benches/NAME.toml`` built in, or a file of the same keys).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from eol_cal.errors import InputError
from eol_cal.motor import MotorParams

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class BenchParams:
    """Mechanics of a dyno bench.

    Attributes
    ----------
    name : str
        Bench name.
    J_dyno : float
        Dyno-side inertia (kg*m^2).
    K_shaft : float
        Torsional stiffness between rotor and dyno (N*m/rad).
    shaft_zeta : float
        Damping ratio of the torsion mode (1).
    dyno_bw_hz : float
        Bandwidth of the dyno drive's PI speed loop (Hz).
    dyno_zeta : float
        Damping ratio the speed loop is tuned for (1).
    """

    name: str = "paper"
    J_dyno: float = 0.02
    K_shaft: float = 2000.0
    shaft_zeta: float = 0.3
    dyno_bw_hz: float = 5.0
    dyno_zeta: float = 0.8


_FIELDS = {f.name: f.type for f in dataclasses.fields(BenchParams)}


#: the bench name that means a rigid coupling (no response divided out)
RIGID = "none"


def bench_or_rigid(name_or_file: str | Path) -> BenchParams | None:
    """:func:`load_bench`, or ``None`` (rigid coupling) for the name ``"none"`` (the CLI's ``--bench none``)."""
    return None if str(name_or_file) == RIGID else load_bench(name_or_file)


def load_bench(name_or_file: str | Path = "paper") -> BenchParams:
    """A bench from a built-in name (``eol_cal/benches/NAME.toml``) or a TOML file.

    Every key of :class:`BenchParams` must be given; unknown keys and non-positive values are
    refused (InputError naming the file and the key).
    """
    path = Path(name_or_file)
    if path.suffix == ".toml":
        source = str(path)
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise InputError(source, None, "file not found") from None
    else:
        source = f"bench {name_or_file}"
        try:
            text = resources.files("eol_cal.benches").joinpath(f"{name_or_file}.toml").read_text()
        except FileNotFoundError:
            known = sorted(p.name[:-5] for p in resources.files("eol_cal.benches").iterdir() if p.name.endswith(".toml"))
            raise InputError(None, "bench", f"unknown bench {name_or_file!r}; known: {', '.join(known)}, or a .toml file") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(source, None, f"not valid TOML: {exc}") from None
    kwargs: dict = {}
    for key, value in data.items():
        if key not in _FIELDS:
            raise InputError(source, key, f"unknown bench parameter; known: {', '.join(sorted(_FIELDS))}")
        if key == "name":
            if not isinstance(value, str):
                raise InputError(source, key, "must be a string")
        elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise InputError(source, key, f"must be a positive number, got {value!r}")
        else:
            value = float(value)
        kwargs[key] = value
    missing = sorted(set(_FIELDS) - set(kwargs) - {"name"})
    if missing:
        raise InputError(source, missing[0], f"missing bench parameter(s): {', '.join(missing)}")
    kwargs.setdefault("name", path.stem)
    return BenchParams(**kwargs)


def speed_gains(J_total: float, bw_hz: float, zeta: float = 0.8) -> tuple[float, float]:
    """PI gains (N*m*s/rad, N*m/rad) placing the dyno's speed loop at ``bw_hz`` (Hz)."""
    w = TWO_PI * bw_hz
    return 2.0 * zeta * w * J_total, w * w * J_total


def shaft_damping(K_shaft: float, J: float, J_dyno: float, zeta: float) -> float:
    """Shaft damping (N*m*s/rad) that gives the torsion mode the damping ratio ``zeta``."""
    J_eff = J * J_dyno / (J + J_dyno)
    return 2.0 * zeta * math.sqrt(K_shaft * J_eff)


def shaft_response(omega: np.ndarray, motor: MotorParams, bench: BenchParams) -> np.ndarray:
    """Complex response ``T_shaft / T_ripple`` at angular frequencies ``omega`` (rad/s).

    Mechanics: rotor ``(J s + B) w_m = T_airgap - T_shaft``, shaft
    ``T_shaft = (K/s + D)(w_m - w_d)``, dyno ``(J_dyno s + Kp + Ki/s) w_d = T_shaft``, so
    ``T_shaft = G T_airgap`` with ``G = 1 / (1 + Z_m/Z_d + Z_m/Z_s)`` and the rotor speed
    ``w_m = (1 - G) / Z_m T_airgap``. Current loop: the back-EMF ``psi_f (P/2) w_m`` on the q
    axis drives ``di_q = -Y e_q`` with ``Y = 1 / (L_q s + R_s + Kp_q + Ki_q/s)`` (continuous PI),
    adding ``kt di_q`` to the air-gap torque. Closing that loop:
    ``T_shaft / T_ripple = G / (1 + kt psi_f (P/2) Y (1 - G) / Z_m)``. A sinusoid
    ``e^{i omega t}`` comes out times the response at ``omega``; a negative ``omega`` (reverse
    rotation) gives the complex conjugate.

    Parameters
    ----------
    omega : array
        Angular frequency (rad/s, signed, non-zero).
    motor : MotorParams
        Rotor inertia, friction, winding and current-loop data (nominal values).
    bench : BenchParams
    """
    s = 1j * np.asarray(omega, dtype=float)
    J, B = motor.J, motor.B
    Kp, Ki = speed_gains(J + bench.J_dyno, bench.dyno_bw_hz, bench.dyno_zeta)
    D = shaft_damping(bench.K_shaft, J, bench.J_dyno, bench.shaft_zeta)
    Z_m = J * s + B
    Z_d = bench.J_dyno * s + Kp + Ki / s
    Z_s = bench.K_shaft / s + D
    G = 1.0 / (1.0 + Z_m / Z_d + Z_m / Z_s)
    _, _, Kp_q, Ki_q = motor.current_pi_gains()
    Y = 1.0 / (motor.L_q * s + motor.R_s + Kp_q + Ki_q / s)
    feedback = motor.kt * motor.psi_f * motor.pole_pairs * Y * (1.0 - G) / Z_m
    return G / (1.0 + feedback)
