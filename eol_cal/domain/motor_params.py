"""Motor parameters (seed paper Table I) and the small unit helpers every module shares."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from eol_cal.errors import InputError
from eol_cal.infra.inputs import load_toml, loads_toml


@dataclass(frozen=True)
class MotorParams:
    """SPMSM and drive parameters.

    Attributes
    ----------
    name : str
        Preset name.
    poles : int
        Number of poles P (pole pairs = P/2).
    R_s : float
        Stator resistance at ``T_ref_degC`` (ohm).
    T_ref_degC : float
        Temperature at which ``R_s`` is given (degC).
    alpha_cu : float
        Temperature coefficient of ``R_s`` (1/K).
    L_d, L_q : float
        d- and q-axis inductance (H).
    psi_f : float
        Magnet flux linkage, the paper's back-EMF constant phi_f (V*s).
    J : float
        Rotor moment of inertia (kg*m^2).
    B : float
        Viscous friction coefficient (N*m*s).
    u_dc : float
        DC-link voltage (V).
    N_enc : int
        Encoder pulses per mechanical revolution of channel A.
    f_pwm, f_cc, f_cmd : float
        PWM / estimator tick, current-control and command rates (Hz).
    current_bw_hz : float
        Closed-loop bandwidth the ECU's PI current controller is tuned for (Hz); the plant's
        controller and the compensator's lead both derive from it.
    i_max : float
        Current rating (A): the largest ``|i_q|`` the drive may command. A parameter block's
        ``iqc_limit`` and table values must stay within it (:mod:`eol_cal.firmware.block_sanity`).
    """

    name: str = "paper"
    poles: int = 6
    R_s: float = 0.023
    T_ref_degC: float = 70.0
    alpha_cu: float = 0.00393
    L_d: float = 68e-6
    L_q: float = 68e-6
    psi_f: float = 0.0109
    J: float = 0.00011
    B: float = 0.00021
    u_dc: float = 12.0
    N_enc: int = 64
    f_pwm: float = 20000.0
    f_cc: float = 1680.0
    f_cmd: float = 420.0
    current_bw_hz: float = 200.0
    i_max: float = 100.0

    @property
    def kt(self) -> float:
        """Torque constant 3P/4 * psi_f (N*m/A of i_q), seed eq. (3)."""
        return 0.75 * self.poles * self.psi_f

    @property
    def pole_pairs(self) -> int:
        return self.poles // 2

    def current_pi_gains(self) -> tuple[float, float, float, float]:
        """The ECU's dq current PI gains ``(Kp_d, Ki_d, Kp_q, Ki_q)`` (V/A, V/(A*s)).

        Internal-model tuning: the PI zero cancels the nominal R-L pole and the loop crosses at
        ``2*pi*current_bw_hz``, so the closed loop is first order at ``current_bw_hz``.
        """
        w_c = 2.0 * math.pi * self.current_bw_hz
        return w_c * self.L_d, w_c * self.R_s, w_c * self.L_q, w_c * self.R_s

    def R_s_at(self, temp_degC: float) -> float:
        """Stator resistance at ``temp_degC`` (ohm), linear copper model."""
        return self.R_s * (1.0 + self.alpha_cu * (temp_degC - self.T_ref_degC))


_FIELDS = {f.name: f.type for f in dataclasses.fields(MotorParams)}


def motor_from_mapping(data: dict, source: str = "<mapping>") -> MotorParams:
    """Build :class:`MotorParams` from a mapping; unknown keys and bad values are refused."""
    kwargs = {}
    for key, value in data.items():
        if key not in _FIELDS:
            raise InputError(source, key, f"unknown motor parameter; known: {', '.join(sorted(_FIELDS))}")
        want = _FIELDS[key]
        if want == "str":
            if not isinstance(value, str):
                raise InputError(source, key, "must be a string")
        elif want == "int":
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise InputError(source, key, f"must be a positive integer, got {value!r}")
        else:
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
                raise InputError(source, key, f"must be a finite number, got {value!r}")
            if key != "T_ref_degC" and key != "alpha_cu" and value <= 0:
                raise InputError(source, key, f"must be positive, got {value!r}")
            value = float(value)
        kwargs[key] = value
    params = MotorParams(**kwargs)
    if params.poles % 2:
        raise InputError(source, "poles", f"must be even, got {params.poles}")
    return params


def load_motor(preset: str = "paper", toml_file: str | Path | None = None) -> MotorParams:
    """Motor parameters from a built-in preset, overridden by the keys of a TOML file.

    Parameters
    ----------
    preset : str
        Name of a built-in preset (``eol_cal/motors/NAME.toml``).
    toml_file : path, optional
        TOML file whose top-level keys override the preset.
    """
    try:
        text = resources.files("eol_cal.motors").joinpath(f"{preset}.toml").read_text()
    except FileNotFoundError:
        raise InputError(None, "preset", f"unknown motor preset {preset!r}") from None
    data = loads_toml(text, f"preset {preset}")
    source = f"preset {preset}"
    if toml_file is not None:
        data.update(load_toml(toml_file))
        source = str(toml_file)
    return motor_from_mapping(data, source)


def rpm_to_omega_m(rpm: float) -> float:
    """Mechanical speed from rpm to rad/s."""
    return rpm * 2.0 * math.pi / 60.0

