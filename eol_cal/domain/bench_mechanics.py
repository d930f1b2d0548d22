"""The test bench's mechanics (:class:`BenchMechanics`): the shaft, the dyno and its speed loop.

One model of the mechanics for the whole library: :func:`shaft_response` is its frequency
response (what the ripple fit divides out), :func:`mech_step` its time step (what the plant
integrates at the PWM tick). The plant holds a :class:`BenchMechanics` as it holds the motor's
:class:`eol_cal.domain.motor_params.MotorParams`.

The transducer sits in the shaft between the motor's rotor (inertia ``J``) and the dyno (inertia
``J_dyno``, held at speed by its drive's PI loop). A ripple torque of the motor reaches the shaft
only in part: a share of it accelerates the rotor, near the torsion mode the shaft amplifies it,
and the speed ripple it causes moves the back-EMF, which the ECU's current loop does not fully
reject, so the current (and with it the torque) ripples a little against it.
:func:`shaft_response` is that transfer, ``T_shaft / T_ripple``, for the linear models the plant
integrates (:func:`mech_step`, :mod:`eol_cal.plant.machine`, the PI of
:meth:`eol_cal.domain.motor_params.MotorParams.current_pi_gains`). The ripple fit divides it out, so that k6
and c6 are the motor's own at constant current (what the compensating current has to cancel),
not the bench's view of them: on the paper bench the shaft sees 0.4 % less of the 6th at 60 rpm
than the motor makes, and the current loop takes another 0.3 %.

Time step: two inertias (motor rotor ``J``, dyno ``J_dyno``) joined by a shaft of stiffness
``K_shaft`` (N*m/rad) and damping ``D_shaft`` (N*m*s/rad); the torque transducer sits in that
shaft and reads ``T_shaft = K_shaft*twist + D_shaft*(omega_m - omega_d)`` (positive when the
motor drives the dyno). The dyno holds its speed reference with a PI speed controller (its own
drive, fast compared to the profile, slow compared to the ripple). Integration is semi-implicit
Euler at the PWM tick, stable for the shaft mode as long as ``omega_n*dt << 2`` (0.1 for the
paper bench). The twist is a state of its own so that float32 keeps it exact at any absolute
angle.

A bench's mechanics are a TOML file (``eol_cal/benches/NAME.toml`` built in, or a file of the
same keys); the name ``none`` means a rigid coupling (no response divided out). A file written by
``eol-cal bench identify`` (:mod:`eol_cal.analysis.bench_id`) also gives the torque transducer
(``transducer_bw_hz``, ``transducer_delay_s``) and an ``[identification]`` table (intervals, the
sweep it came from), which is kept for the reader and not used by the model. Where a bench was
read from is kept in :attr:`BenchMechanics.source` (and ``sha256`` of the text), so that a fit's
result says which bench file it assumed.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Protocol

import numpy as np

from eol_cal.numerics.arrays import Array, ArrayModule
from eol_cal.errors import InputError
from eol_cal.infra.inputs import MAX_TOML_BYTES, loads_toml, read_text
from eol_cal.domain.motor_params import MotorParams
from eol_cal.numerics.wrap import wrap_2pi


TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class BenchMechanics:
    """Mechanics of a test bench: the shaft between the motor and the dyno, the dyno's speed loop.

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
    transducer_bw_hz : float or None
        The torque transducer's first-order bandwidth (Hz), where the bench file gives it (an
        identified bench); None: not given (the fit estimates the transducer's lag per motor).
    transducer_delay_s : float or None
        The transducer chain's pure delay (s), where given: relative to the capture's sample
        times, so a chain sampled ahead of the continuous model reads slightly negative.
    source : str
        Where the description was read from (``bench NAME`` for a built-in one, else the file);
        not compared.
    sha256 : str
        SHA-256 of the file's text (empty when not read from a file); not compared.
    identified : bool
        The file carries an ``[identification]`` table: ``eol-cal bench identify`` measured it on
        the bench (a built-in or hand-written file is an assumption about the bench); not compared.
    """

    name: str = "paper"
    J_dyno: float = 0.02
    K_shaft: float = 2000.0
    shaft_zeta: float = 0.3
    dyno_bw_hz: float = 5.0
    dyno_zeta: float = 0.8
    transducer_bw_hz: float | None = None
    transducer_delay_s: float | None = None
    source: str = field(default="", compare=False)
    sha256: str = field(default="", compare=False)
    identified: bool = field(default=False, compare=False)


#: the keys every bench file must give (the shaft line's model)
SHAFT_KEYS = ("J_dyno", "K_shaft", "shaft_zeta", "dyno_bw_hz", "dyno_zeta")
#: the keys a bench file may give (an identified bench): the transducer
TRANSDUCER_KEYS = ("transducer_bw_hz", "transducer_delay_s")
#: the table an identified bench file carries for its reader (intervals, sweep); not part of the model
IDENTIFICATION_TABLE = "identification"
#: largest |transducer_delay_s| (s) a bench file may give
MAX_DELAY_S = 0.1
_KNOWN = ("name", *SHAFT_KEYS, *TRANSDUCER_KEYS, IDENTIFICATION_TABLE)


#: the bench name that means a rigid coupling (no response divided out)
RIGID = "none"


def mechanics_or_rigid(name_or_file: str | Path) -> BenchMechanics | None:
    """:func:`load_mechanics`, or ``None`` (rigid coupling) for the name :data:`RIGID`."""
    return None if str(name_or_file) == RIGID else load_mechanics(name_or_file)


def load_mechanics(name_or_file: str | Path = "paper") -> BenchMechanics:
    """A bench's mechanics from a built-in name (``eol_cal/benches/NAME.toml``) or a TOML file.

    Every key of :data:`SHAFT_KEYS` must be given, those of :data:`TRANSDUCER_KEYS` may be (the
    delay may be 0 or negative, within :data:`MAX_DELAY_S`), an ``[identification]`` table is
    kept for the reader; unknown keys and non-positive values are refused (InputError naming the
    file and the key).
    """
    path = Path(name_or_file)
    if path.suffix == ".toml":
        source = str(path)
        text = read_text(path, max_bytes=MAX_TOML_BYTES)
    else:
        source = f"bench {name_or_file}"
        try:
            text = resources.files("eol_cal.benches").joinpath(f"{name_or_file}.toml").read_text()
        except FileNotFoundError:
            known = sorted(p.name[:-5] for p in resources.files("eol_cal.benches").iterdir() if p.name.endswith(".toml"))
            raise InputError(None, "bench",
                             f"unknown bench {name_or_file!r}; known: {', '.join(known)}, or a .toml file") from None
    data = loads_toml(text, source)
    kwargs: dict = {}
    for key, value in data.items():
        if key not in _KNOWN:
            raise InputError(source, key, f"unknown bench parameter; known: {', '.join(sorted(_KNOWN))}")
        if key == "name":
            if not isinstance(value, str):
                raise InputError(source, key, "must be a string")
        elif key == IDENTIFICATION_TABLE:
            if not isinstance(value, dict):
                raise InputError(source, key, "must be a table ([identification])")
            continue
        elif key == "transducer_delay_s":
            # relative to the capture's sample times: a chain sampled ahead of its model leads (< 0)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not abs(value) <= MAX_DELAY_S:
                raise InputError(source, key, f"must be a number of seconds within ±{MAX_DELAY_S:g}, got {value!r}")
            value = float(value)
        elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise InputError(source, key, f"must be a positive number, got {value!r}")
        else:
            value = float(value)
        kwargs[key] = value
    missing = [k for k in SHAFT_KEYS if k not in kwargs]
    if missing:
        raise InputError(source, missing[0], f"missing bench parameter(s): {', '.join(missing)}")
    kwargs.setdefault("name", path.stem)
    digest = hashlib.sha256(text.encode()).hexdigest() if path.suffix == ".toml" else ""
    return BenchMechanics(**kwargs, source=source, sha256=digest, identified=IDENTIFICATION_TABLE in data)


#: the capture metadata key under which the simulated plant records the bench it simulated
#: (:func:`model_digest` of its mechanics)
SIMULATED_BENCH_KEY = "simulated_bench"


def model_digest(mech: BenchMechanics) -> str:
    """A short digest of the model a bench description gives (its shaft and transducer keys, not its
    name or file): two descriptions with the same digest make the same torque path."""
    values = [getattr(mech, k) for k in (*SHAFT_KEYS, *TRANSDUCER_KEYS)]
    return hashlib.sha256(repr(values).encode()).hexdigest()[:16]


def speed_gains(J_total: float, bw_hz: float, zeta: float = 0.8) -> tuple[float, float]:
    """PI gains (N*m*s/rad, N*m/rad) placing the dyno's speed loop at ``bw_hz`` (Hz).

    ``J_total`` is the inertia the dyno drive turns (kg*m^2: rotor and dyno), ``zeta`` the
    damping ratio the loop is tuned for (1).
    """
    w = TWO_PI * bw_hz
    return 2.0 * zeta * w * J_total, w * w * J_total


def shaft_damping(K_shaft: float, J: float, J_dyno: float, zeta: float) -> float:
    """Shaft damping (N*m*s/rad) that gives the torsion mode the damping ratio ``zeta`` (1).

    ``K_shaft`` in N*m/rad, the inertias ``J`` (rotor) and ``J_dyno`` in kg*m^2.
    """
    J_eff = J * J_dyno / (J + J_dyno)
    return 2.0 * zeta * math.sqrt(K_shaft * J_eff)


def shaft_response(omega: np.ndarray, motor: MotorParams, mechanics: BenchMechanics) -> np.ndarray:
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
    mechanics : BenchMechanics
        The shaft and the dyno.

    Returns
    -------
    array of complex
        ``T_shaft / T_ripple`` (1) at each ``omega``.
    """
    s = 1j * np.asarray(omega, dtype=float)
    G = torsion_response(omega, motor.J, motor.B, mechanics)
    Z_m = motor.J * s + motor.B
    _, _, Kp_q, Ki_q = motor.current_pi_gains()
    Y = 1.0 / (motor.L_q * s + motor.R_s + Kp_q + Ki_q / s)
    feedback = motor.kt * motor.psi_f * motor.pole_pairs * Y * (1.0 - G) / Z_m
    return G / (1.0 + feedback)


def torsion_response(omega: np.ndarray, J: float, B: float, mechanics: BenchMechanics) -> np.ndarray:
    """The shaft line alone: ``G = T_shaft / T_airgap`` at angular frequencies ``omega`` (rad/s).

    ``G = 1 / (1 + Z_m/Z_d + Z_m/Z_s)`` with the rotor ``Z_m = J s + B`` (``J`` kg*m^2, ``B``
    N*m*s/rad), the dyno ``Z_d`` and the shaft ``Z_s`` of :func:`shaft_response`; the air-gap
    torque includes the current loop's reaction (what :func:`shaft_response` closes on top), so
    this is the transfer from a torque whose current part is measured (``eol-cal bench identify``).
    """
    s = 1j * np.asarray(omega, dtype=float)
    Kp, Ki = speed_gains(J + mechanics.J_dyno, mechanics.dyno_bw_hz, mechanics.dyno_zeta)
    D = shaft_damping(mechanics.K_shaft, J, mechanics.J_dyno, mechanics.shaft_zeta)
    Z_m = J * s + B
    Z_d = mechanics.J_dyno * s + Kp + Ki / s
    Z_s = mechanics.K_shaft / s + D
    return 1.0 / (1.0 + Z_m / Z_d + Z_m / Z_s)


def transducer_response(omega: np.ndarray, bw_hz: float | None, delay_s: float | None) -> np.ndarray:
    """The torque transducer: ``exp(-i omega delay) / (1 + i omega / (2 pi bw))`` at ``omega`` (rad/s).

    ``bw_hz`` (Hz) None or infinite: no low-pass; ``delay_s`` (s) None: no delay.
    """
    w = np.asarray(omega, dtype=float)
    lowpass = 1.0 if bw_hz is None or not math.isfinite(bw_hz) else 1.0 / (1.0 + 1j * w / (TWO_PI * bw_hz))
    return lowpass * np.exp(-1j * w * (delay_s or 0.0))


class ShaftLine(Protocol):
    """The shaft line's coefficients in the per-tick float32 form (a plant's parameters hold them)."""

    @property
    def J(self) -> Array: ...  # kg*m^2, rotor

    @property
    def B(self) -> Array: ...  # N*m*s/rad, rotor friction

    @property
    def J_dyno(self) -> Array: ...  # kg*m^2

    @property
    def K_shaft(self) -> Array: ...  # N*m/rad

    @property
    def D_shaft(self) -> Array: ...  # N*m*s/rad

    @property
    def Kp_dyno(self) -> Array: ...  # N*m*s/rad, dyno speed loop

    @property
    def Ki_dyno(self) -> Array: ...  # N*m/rad, dyno speed loop


def shaft_torque(twist: Array, omega_m: Array, omega_d: Array, p: ShaftLine) -> Array:
    """Torque in the shaft (N*m) from its twist (rad) and the two speeds (rad/s, mechanical).

    ``p`` holds ``K_shaft`` (N*m/rad) and ``D_shaft`` (N*m*s/rad).
    """
    return p.K_shaft * twist + p.D_shaft * (omega_m - omega_d)


def mech_step(
    theta_m: Array, twist: Array, omega_m: Array, omega_d: Array, x_dyno: Array,
    T_rotor: Array, omega_ref: Array, p: ShaftLine, dt: float, xp: ArrayModule,
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Advance the shaft line by one tick (semi-implicit Euler, see the module doc).

    Parameters
    ----------
    theta_m : array
        Mechanical rotor angle (rad, kept in [0, 2*pi)).
    twist : array
        Shaft twist (rad).
    omega_m, omega_d : array
        Motor and dyno speed (rad/s).
    x_dyno : array
        Dyno PI integrator (N*m).
    T_rotor : array
        Electromagnetic torque minus ripple acting on the rotor (N*m).
    omega_ref : array
        Dyno speed reference (rad/s, signed).
    p : ShaftLine
        ``J``, ``B``, ``J_dyno``, ``K_shaft``, ``D_shaft``, ``Kp_dyno``, ``Ki_dyno`` (the
        per-tick float32 form of the motor and its :class:`BenchMechanics`).
    dt : float
        Tick (s).
    xp : module
        ``numpy`` or ``jax.numpy``.

    Returns
    -------
    tuple
        theta_m, twist, omega_m, omega_d, x_dyno, T_shaft (N*m, at the start of the tick).
    """
    T_shaft = shaft_torque(twist, omega_m, omega_d, p)
    err = omega_ref - omega_d
    T_dyno = p.Kp_dyno * err + x_dyno
    x_dyno = x_dyno + p.Ki_dyno * dt * err
    omega_m = omega_m + (dt / p.J) * (T_rotor - p.B * omega_m - T_shaft)
    omega_d = omega_d + (dt / p.J_dyno) * (T_shaft + T_dyno)
    twist = twist + dt * (omega_m - omega_d)
    theta_m = wrap_2pi(theta_m + dt * omega_m, xp)
    return theta_m, twist, omega_m, omega_d, x_dyno, T_shaft
