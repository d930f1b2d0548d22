"""Parameters of one simulated motor on the test bench: the motor as built, its sensors, the
bench's mechanics.

:class:`PlantSpec` is the human-readable description (units in the names' docs); it is what a
plant preset or :mod:`eol_cal.plant.variation` produces and what goes into a capture's
``truth.*``. It holds the motor's data sheet (:class:`eol_cal.domain.motor_params.MotorParams`) and the bench's
mechanics (:class:`eol_cal.domain.bench_mechanics.BenchMechanics`) as objects of their own.
:class:`PlantParams` is the same as float32 arrays with the per-tick coefficients precomputed,
the pytree the scan closes over (batched along a leading axis for a lot of motors).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from eol_cal.firmware.estimator import NOMINAL_HALL_ANGLE, HallTables, hall_tables
from eol_cal.firmware.kinematics import SensorErrors
from eol_cal.firmware.mech import MechTables, mech_tables
from eol_cal.domain.bench_mechanics import SHAFT_KEYS, BenchMechanics, load_mechanics, shaft_damping, speed_gains
from eol_cal.domain.motor_params import MotorParams, load_motor
from eol_cal.plant import machine as motor_model
from eol_cal.plant import ripple

if TYPE_CHECKING:
    from eol_cal.firmware.kinematics import SensorErrors
    from eol_cal.firmware.mech import MechTables


@dataclass(frozen=True)
class PlantSpec:
    """One motor on the test bench, as built (truth), plus the bench's mechanics.

    Attributes
    ----------
    motor : MotorParams
        Nominal data sheet values (seed Table I); the ECU's controller is tuned on these.
    serial : str
        Motor serial number.
    R_s_scale : float
        Production spread of the winding resistance, multiplies ``motor.R_s`` (1).
    temp_degC : float
        Winding temperature during the test (degC); R_s follows ``motor.R_s_at``.
    c6, phase_c6 : float
        Cogging 6th harmonic amplitude (N*m) and phase (rad).
    k6, phase_k6 : float
        Load-proportional 6th harmonic coefficient (N*m/A) and phase (rad).
    c12, phase_c12, k12, phase_k12, c18, phase_c18, k18, phase_k18 : float
        Higher multiples of 6, same meaning (N*m, rad, N*m/A, rad).
    unb1, phase_unb1 : float
        Mechanical order-1 unbalance torque (N*m) and phase (rad, mechanical).
    unb2, phase_unb2, unb3, phase_unb3 : float
        Mechanical orders 2 and 3 (N*m, rad mechanical): ``unb_h sin(h theta_m + phase_unb_h)``
        (eccentricity, magnet and stator-segment tolerances).
    enc_edge_err_deg : tuple of float
        Placement error of each of the ``N_enc`` encoder pulses (mechanical degrees); empty = 0.
    grid_offset_deg : float
        Mechanical angle of pulse 0's nominal rising edge (mechanical degrees).
    hall_err_deg : tuple of 6 float
        Switching-point errors of the halls (electrical degrees): U rise, U fall, V rise,
        V fall, W rise, W fall (as seen in forward rotation).
    tq_bw_hz, tq_noise_nm, tq_lsb_nm : float
        Torque transducer bandwidth (Hz), noise (N*m rms), ADC resolution (N*m).
    i_noise_a, i_lsb_a : float
        Phase-current sensor noise (A rms) and ADC resolution (A).
    mechanics : BenchMechanics
        The shaft and the dyno (inertia kg*m^2, stiffness N*m/rad, speed loop Hz); default: the
        ``paper`` bench (``eol_cal/benches/paper.toml``), the one the fit assumes by default.
    dead_time_s : float
        Inverter dead time (s); 0 switches the dead-time model off.
    """

    motor: MotorParams = field(default_factory=lambda: load_motor("paper"))
    serial: str = "SIM-0001"
    R_s_scale: float = 1.0
    temp_degC: float = 70.0
    c6: float = 0.0
    phase_c6: float = 0.0
    k6: float = 0.0
    phase_k6: float = 0.0
    c12: float = 0.0
    phase_c12: float = 0.0
    k12: float = 0.0
    phase_k12: float = 0.0
    c18: float = 0.0
    phase_c18: float = 0.0
    k18: float = 0.0
    phase_k18: float = 0.0
    unb1: float = 0.0
    phase_unb1: float = 0.0
    unb2: float = 0.0
    phase_unb2: float = 0.0
    unb3: float = 0.0
    phase_unb3: float = 0.0
    enc_edge_err_deg: tuple[float, ...] = ()
    grid_offset_deg: float = 0.0
    hall_err_deg: tuple[float, ...] = (0.0,) * 6
    tq_bw_hz: float = 2000.0
    tq_noise_nm: float = 0.0
    tq_lsb_nm: float = 1e-4
    i_noise_a: float = 0.0
    i_lsb_a: float = 0.05
    mechanics: BenchMechanics = field(default_factory=lambda: load_mechanics("paper"))
    dead_time_s: float = 0.0

    def replace(self, **changes: Any) -> PlantSpec:
        return dataclasses.replace(self, **changes)

    @property
    def R_s_true(self) -> float:
        """Winding resistance during the test (ohm)."""
        return self.R_s_scale * self.motor.R_s_at(self.temp_degC)

    def without_ripple(self) -> PlantSpec:
        """The same bench with every ripple source set to zero (for torque-balance checks)."""
        zero = {n: 0.0 for n in ("c6", "k6", "c12", "k12", "c18", "k18", "unb1", "unb2", "unb3")}
        return self.replace(**zero)

    def ripple_harmonics(self) -> tuple[tuple[int, float, float, float, float], ...]:
        """Higher multiples of 6 as ``(order, c, phase_c, k, phase_k)`` (compensator format)."""
        return ((12, self.c12, self.phase_c12, self.k12, self.phase_k12),
                (18, self.c18, self.phase_c18, self.k18, self.phase_k18))

    def truth(self) -> dict[str, str | int | float]:
        """Everything a test may judge a result against (keys without the ``truth.`` prefix)."""
        out: dict[str, str | int | float] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name in ("motor", "serial"):
                continue
            if f.name == "mechanics":
                out.update({k: float(getattr(value, k)) for k in SHAFT_KEYS})
                continue
            if isinstance(value, tuple):
                out[f.name] = " ".join(f"{v:.6g}" for v in value)
            else:
                out[f.name] = float(value)
        out["R_s"] = self.R_s_true
        out["kt"] = self.motor.kt
        out["transducer_delay_s"] = 1.0 / (2.0 * math.pi * self.tq_bw_hz)
        out["transducer_bw_hz"] = self.tq_bw_hz
        out["motor_preset"] = self.motor.name
        return out


class PlantParams(NamedTuple):
    """Float32 arrays the scan reads (leading batch axis when vmapped). Units as in PlantSpec."""

    # motor, exact R-L coefficients over one tick
    a_d: np.ndarray
    b_d: np.ndarray
    a_q: np.ndarray
    b_q: np.ndarray
    L_d: np.ndarray
    L_q: np.ndarray
    psi_f: np.ndarray
    J: np.ndarray
    B: np.ndarray
    # ripple: sin/cos coefficients (see ripple.coefficients)
    s6c: np.ndarray
    c6c: np.ndarray
    s6k: np.ndarray
    c6k: np.ndarray
    s12c: np.ndarray
    c12c: np.ndarray
    s12k: np.ndarray
    c12k: np.ndarray
    s18c: np.ndarray
    c18c: np.ndarray
    s18k: np.ndarray
    c18k: np.ndarray
    s1u: np.ndarray
    c1u: np.ndarray
    s2u: np.ndarray
    c2u: np.ndarray
    s3u: np.ndarray
    c3u: np.ndarray
    # sensors (eol_cal.firmware.kinematics.SensorErrors fields)
    edge_error: np.ndarray    # (N_enc,) rad mechanical
    hall_offset: np.ndarray   # (3, 2) rad electrical
    grid_offset: np.ndarray   # rad mechanical
    tq_gain: np.ndarray
    tq_noise_nm: np.ndarray
    tq_lsb_nm: np.ndarray
    i_noise_a: np.ndarray
    i_lsb_a: np.ndarray
    # inverter
    u_dc: np.ndarray
    u_dead: np.ndarray
    # dyno
    J_dyno: np.ndarray
    K_shaft: np.ndarray
    D_shaft: np.ndarray
    Kp_dyno: np.ndarray
    Ki_dyno: np.ndarray
    # ECU (nominal motor data, as the firmware has them)
    Kp_d: np.ndarray
    Kp_q: np.ndarray
    Ki_d: np.ndarray
    Ki_q: np.ndarray
    L_d_nom: np.ndarray
    L_q_nom: np.ndarray
    psi_f_nom: np.ndarray
    # compensator block
    table_const: np.ndarray
    table_per_amp: np.ndarray
    lead_s: np.ndarray
    iqc_limit: np.ndarray
    # the block's hall_angle table as the estimator's lookups (eol_cal.firmware.estimator.HallTables)
    hall_start: np.ndarray    # (8,) rad electrical
    hall_width: np.ndarray    # (8,) rad electrical
    hall_mid: np.ndarray      # (8,) rad electrical
    # layout 2: the identifier's tables (eol_cal.firmware.mech.MechTables, flattened; all 0 without)
    mech_enabled: np.ndarray  # 0/1
    mech_dirs: np.ndarray     # fp_dirs
    mech_dF: np.ndarray       # (2 N_enc,) rad electrical, the fingerprint's pitch errors
    mech_EF: np.ndarray       # (2,) their energy per direction
    mech_grid_phase: np.ndarray  # rad electrical
    mech_id_min_score: np.ndarray
    mech_id_margin: np.ndarray
    mech_id_frac_tol: np.ndarray  # rad electrical
    mech_table_const: np.ndarray    # (128,) A
    mech_table_per_amp: np.ndarray  # (128,) A/A


def to_params(spec: PlantSpec, table_const: np.ndarray, table_per_amp: np.ndarray,
              lead_s: float, iqc_limit: float,
              hall_angle: Sequence[float] = NOMINAL_HALL_ANGLE, mech_tb: MechTables | None = None) -> PlantParams:
    """Float32 parameters of one motor on the bench, with the ECU's gains and the compensation tables.

    ``hall_angle`` (6 float, rad electrical) is the table of the motor's parameter block, the
    one its ECU's estimator anchors on (the contract's nominal one when it has no block);
    ``mech_tb`` the identifier's tables of a layout-2 block (:func:`eol_cal.firmware.mech.block_mech_tables`;
    disabled without one).
    """
    if mech_tb is None:
        mech_tb = mech_tables(None, lead_s, False, spec.motor.N_enc)
    m = spec.motor
    dt = 1.0 / m.f_pwm
    R = spec.R_s_true
    a_d, b_d = motor_model.rl_coefficients(R, m.L_d, dt, np)
    a_q, b_q = motor_model.rl_coefficients(R, m.L_q, dt, np)
    mech = spec.mechanics
    Kp_dyno, Ki_dyno = speed_gains(m.J + mech.J_dyno, mech.dyno_bw_hz, mech.dyno_zeta)
    Kp_d, Ki_d, Kp_q, Ki_q = m.current_pi_gains()
    edge = np.zeros(m.N_enc) if not spec.enc_edge_err_deg else np.radians(spec.enc_edge_err_deg)
    if edge.shape != (m.N_enc,):
        raise ValueError(f"enc_edge_err_deg needs {m.N_enc} values, got {edge.shape}")
    hall = np.radians(np.asarray(spec.hall_err_deg, dtype=float)).reshape(3, 2)
    values = dict(
        a_d=a_d, b_d=b_d, a_q=a_q, b_q=b_q, L_d=m.L_d, L_q=m.L_q, psi_f=m.psi_f, J=m.J, B=m.B,
        **ripple.coefficients(spec),
        edge_error=edge, hall_offset=hall, grid_offset=math.radians(spec.grid_offset_deg),
        tq_gain=1.0 - math.exp(-2.0 * math.pi * spec.tq_bw_hz * dt),
        tq_noise_nm=spec.tq_noise_nm, tq_lsb_nm=spec.tq_lsb_nm,
        i_noise_a=spec.i_noise_a, i_lsb_a=spec.i_lsb_a,
        u_dc=m.u_dc, u_dead=m.u_dc * spec.dead_time_s * m.f_pwm,
        J_dyno=mech.J_dyno, K_shaft=mech.K_shaft,
        D_shaft=shaft_damping(mech.K_shaft, m.J, mech.J_dyno, mech.shaft_zeta),
        Kp_dyno=Kp_dyno, Ki_dyno=Ki_dyno,
        Kp_d=Kp_d, Kp_q=Kp_q, Ki_d=Ki_d, Ki_q=Ki_q,
        L_d_nom=m.L_d, L_q_nom=m.L_q, psi_f_nom=m.psi_f,
        table_const=table_const, table_per_amp=table_per_amp, lead_s=lead_s, iqc_limit=iqc_limit,
        **dict(zip(("hall_start", "hall_width", "hall_mid"), hall_tables(hall_angle), strict=True)),
        **{f"mech_{name}": getattr(mech_tb, name) for name in _MECH_FIELDS},
    )
    return PlantParams(**{k: np.asarray(v, dtype=np.float32) for k, v in values.items()})


#: the MechTables fields PlantParams carries as mech_<name> (lead_s is the block's, shared)
_MECH_FIELDS = ("enabled", "dirs", "dF", "EF", "grid_phase", "id_min_score", "id_margin", "id_frac_tol",
                "table_const", "table_per_amp")


def mech_tables_of(p: PlantParams) -> MechTables:
    """The identifier's tables of these parameters (one motor's, or traced under ``vmap``)."""
    fields = {name: getattr(p, f"mech_{name}") for name in _MECH_FIELDS}
    fields["enabled"] = fields["enabled"].astype("int32")
    fields["dirs"] = fields["dirs"].astype("int32")
    return MechTables(lead_s=p.lead_s, **fields)


def estimator_tables(p: PlantParams) -> HallTables:
    """The estimator's hall lookups of these parameters (one motor's, or traced under ``vmap``)."""
    return HallTables(p.hall_start, p.hall_width, p.hall_mid)


def sensor_errors(p: PlantParams) -> SensorErrors:
    """The kinematic sensor model's error record of these parameters."""
    return SensorErrors(p.edge_error, p.hall_offset, p.grid_offset)
