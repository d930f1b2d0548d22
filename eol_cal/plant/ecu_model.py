"""What the simulated ECU runs: the block (the ideal one from the plant's truth), the control
mode and estimator options its flags select, and the ECU state a simulated capture records.

:func:`eol_cal.plant.simulate.simulate` compiles these into its scan; the station's rig and
``eol-cal simulate`` choose the block.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from eol_cal.capture.ecu_state import EcuState
from eol_cal.errors import InputError
from eol_cal.firmware import compensator, estimator
from eol_cal.firmware.block import FLAG_COMP_ENABLE, FLAG_INTERP_ENABLE, ParamBlock, flag_names
from eol_cal.firmware.contract import DEFAULT_TABLE_LEN
from eol_cal.firmware.estimator import NOMINAL_HALL_ANGLE, EstimatorConfig
from eol_cal.firmware.kinematics import fingerprint_of
from eol_cal.firmware.mech_params import FP_FORWARD, FP_REVERSE, MechParams, make_mech_tables, unused_mech
from eol_cal.firmware.options import honoured_options, options_label, parse_options
from eol_cal.plant.params import PlantSpec, sensor_errors, to_params


def true_block(spec: PlantSpec, table_len: int = DEFAULT_TABLE_LEN, harmonics: bool = False,
               flags: int = FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE, mech: bool = False) -> ParamBlock:
    """A parameter block made from the plant's true 6th-harmonic ripple (the ideal calibration).

    The paper's compensator cancels the 6th harmonic only; ``harmonics=True`` adds the true
    12th and 18th to the tables as well. The lead is the current loop's time constant
    ``1/(2*pi*current_bw_hz)``; ``iqc_limit`` is 10 % of 65 A. ``mech=True`` makes it a layout-2
    block (:func:`true_mech`: the encoder's true fingerprint, the true mechanical orders 1-3);
    ``flags`` then decides whether ``MECH_COMP_ENABLE`` is set.
    """
    m = spec.motor
    harm = spec.ripple_harmonics() if harmonics else ()
    tc, tp = compensator.make_tables(spec.c6, spec.phase_c6, spec.k6, spec.phase_k6, m.kt, table_len, harm)
    return ParamBlock(
        sequence=1, flags=flags, serial=spec.serial[:16], calibrated_at=0, poles=m.poles,
        encoder_ppr=m.N_enc, tick_hz=m.f_pwm, kt=m.kt, hall_angle=NOMINAL_HALL_ANGLE,
        c6=spec.c6, phase_c6=spec.phase_c6, k6=spec.k6, phase_k6=spec.phase_k6,
        lead_s=1.0 / (2.0 * math.pi * m.current_bw_hz), iqc_limit=6.5,
        table_const=tc, table_per_amp=tp, mech=true_mech(spec) if mech else None,
    )


def true_mech(spec: PlantSpec) -> MechParams:
    """The layout-2 mechanical part a perfect end of line would write for this plant motor.

    The block's frame is the encoder model's pulse numbering (:func:`eol_cal.firmware.kinematics.fingerprint_of`);
    its mechanical angle 0 is electrical angle 0 under the pole pair that holds the frame's
    count boundary 0, which sits ``shift`` = 0 or one pole pitch (2*pi/pp) from the plant's
    mechanical 0: each mechanical order ``unb_h sin(h theta_m + phase_unb_h)`` (h = 1..3) is at
    phase ``phase_unb_h - h shift`` there.
    """
    m = spec.motor
    pp = m.poles // 2
    err = sensor_errors(to_params(spec, np.zeros(16), np.zeros(16), 0.0, 0.0))
    err = err._replace(edge_error=np.asarray(err.edge_error, float), grid_offset=float(err.grid_offset))
    fp, gp = fingerprint_of(err, m.poles)
    e = np.asarray(spec.enc_edge_err_deg or np.zeros(m.N_enc), float)
    boundary0 = math.radians(spec.grid_offset_deg + float(e.mean())) - 2.0 * math.pi / m.N_enc / 4.0
    shift = gp / pp - boundary0  # 0 or a pole pitch: where the block frame's mechanical 0 lies
    c = (spec.unb1, spec.unb2, spec.unb3)
    ph = tuple(float(p - h * shift) for h, p in enumerate((spec.phase_unb1, spec.phase_unb2, spec.phase_unb3), 1))
    zeros = (0.0, 0.0, 0.0)
    tc, tp = make_mech_tables(c, ph, zeros, zeros, m.kt)
    return unused_mech(m.N_enc).replace(fp_dirs=FP_FORWARD | FP_REVERSE, grid_phase=gp, mech_c=c, mech_phase_c=ph,
                                        mech_table_const=tc, mech_table_per_amp=tp, fingerprint=fp)


def mode_of_block(block: ParamBlock) -> str:
    """The control mode a firmware runs with this block's flags."""
    if block.flags & FLAG_COMP_ENABLE:
        return "compensated"
    return "estimated" if block.flags & FLAG_INTERP_ENABLE else "raw"


def simulated_ecu_state(spec: PlantSpec, mode: str, block: ParamBlock | None) -> EcuState:
    """The ECU state a simulation stands for (the capture's ``ecu_before``/``ecu_after``).

    The block the simulated ECU runs, in bank 0, with the flags that select ``mode`` (other bits
    of a given block kept): the given block, else one from the plant's true ripple
    (:func:`true_block`); raw mode without a block is an ECU with no valid block.
    """
    if block is None and mode == "raw":
        return EcuState(None)
    mode_bits = {"raw": 0, "estimated": FLAG_INTERP_ENABLE, "compensated": FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE}[mode]
    base = block if block is not None else true_block(spec)
    flags = (base.flags & ~(FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE)) | mode_bits
    # (the block itself when its flags select the mode already: its image, packed once and valid
    # by construction, holds the CRC; a copy packs its own)
    blk = base if flags == base.flags else dataclasses.replace(base, flags=flags)
    return EcuState(0, blk.sequence, f"{blk.crc:08x}", flag_names(flags))


def estimator_config(spec: PlantSpec, block: ParamBlock | None = None, options: int | None = None) -> EstimatorConfig:
    """The firmware estimator's configuration on this bench.

    The hall table is the block's (nominal without one); the options (contract flags bits 2-5)
    are ``options`` when given, else those the block's flags select (none without a block: the
    paper's estimator).
    """
    m = spec.motor
    hall = block.hall_angle if block is not None else NOMINAL_HALL_ANGLE
    if options is None:
        options = honoured_options(block.flags) if block is not None else 0
    return estimator.EstimatorConfig.from_flags(FLAG_INTERP_ENABLE | options, poles=m.poles, N_enc=m.N_enc,
                                                tick_hz=m.f_pwm, hall_angle=tuple(float(a) for a in hall))


def batch_options(blocks: Sequence[ParamBlock | None], ecu_estimator: str | None = None) -> int:
    """The estimator option bits the ECUs of one batch run: ``ecu_estimator`` (a choice as
    :func:`eol_cal.firmware.options.parse_options` reads it) when given, else what the blocks'
    flags select (none for a motor without a block). They are compiled into the scan, so every
    motor of a batch must run the same ones.
    """
    if ecu_estimator is not None:
        return parse_options(ecu_estimator, None, "ecu_estimator")
    found = {honoured_options(b.flags) if b is not None else 0 for b in blocks}
    if len(found) > 1:
        raise InputError(None, "blocks", "a batch must share the estimator options; the blocks select "
                                         + ", ".join(sorted(options_label(o) for o in found)))
    return found.pop() if found else 0

