"""Physical sanity of a parameter block: may it drive this motor?

The firmware's check routine (:func:`eol_cal.firmware.block.check`) only asks whether a bank
holds a block (magic, layout, lengths, CRC). A block with a NaN ``k6``, an infinite or 3e38 A
``iqc_limit``, tables of +-3e38 A, 0 poles or a 0 Hz tick passes it, boots, and drives the motor
with garbage; a block for an 8-pole motor passes it on a 6-pole ECU. These rules refuse such a
block before any command writes, exports or flashes it (``eol-cal block check``, ``table``,
``flash``, before security access):

- every float finite (scalars, hall angles, both tables);
- with compensation on (``COMP_ENABLE``): ``0 < iqc_limit <= i_max``, the motor's current
  rating; with it off, ``0 <= iqc_limit <= i_max`` (the measurement block has 0);
- ``|table_const| <= i_max`` (A) and ``|table_per_amp| <= 1`` A/A, so that neither part of
  ``i_qc`` exceeds the rating for any ``|i_qo| <= i_max``;
- ``0 < kt <= KT_MAX``, ``0 <= k6 <= K6_MAX``, ``0 <= c6 <= C6_MAX``, phases and hall angles
  within ``+-PHASE_MAX`` (the fit result's own bounds, :mod:`eol_cal.analysis.motor_result`);
- ``0 <= lead_s < LEAD_MAX_S``;
- poles even, 2..1000; encoder PPR 1..65535; tick rate 1 kHz..1 MHz;
- the motor type (poles, encoder PPR, tick rate) that of the ECU (:func:`type_problems`);
- layout 2 (revision 1.2): the mechanical tables as bounded as the 6th-harmonic ones, orders
  and phases within the fit's bounds, ``0 <= id_min_score <= 1``, ``0 <= id_margin <= 2``,
  ``0 < id_frac_tol < pi``, ``grid_phase`` in [0, 2*pi), every fingerprint entry within half a
  pitch (rad electrical).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from eol_cal.errors import InputError
from eol_cal.firmware import block as B
from eol_cal.firmware.block_layout import FIELDS_BY_VERSION, SIZE
from eol_cal.firmware.contract import C6_MAX, FLAGS, K6_MAX, KT_MAX, MAGIC, PHASE_MAX
from eol_cal.firmware.mech_params import FP_MAX, MechParams
from eol_cal.domain.motor_params import MotorParams

#: largest look-up lead (s) a block may carry
LEAD_MAX_S = 0.1
#: largest |table_per_amp| (A/A): a compensation current as large as the current itself is no ripple
TABLE_PER_AMP_MAX = 1.0
#: plausible estimator tick rates (Hz)
TICK_HZ_RANGE = (1e3, 1e6)
POLES_MAX = 1000
#: relative tolerance of a tick rate stored as binary32
_TICK_RTOL = 1e-6


def field_limits(name: str, version: int, table_len: int, motor: MotorParams) -> tuple[float, float]:
    """The least and largest value field ``name`` of a layout-``version`` block may hold (closed
    interval; docs/firmware-contract.md section 2, "Bounds"): the rules above, for ``motor``'s
    rating ``i_max`` and its pitch where a bound depends on them, the element type's range where
    nothing narrower holds. What the A2L gives calibration tools as each characteristic's limits.

    Raises
    ------
    KeyError
        ``name`` is not a field of the layout.
    """
    f = FIELDS_BY_VERSION[version][name]
    half_pitch = motor.poles * math.pi / motor.N_enc / 2
    named_flags = sum(1 << flag.bit for flag in FLAGS.values())
    fixed = {"magic": MAGIC, "layout_version": version, "block_bytes": B.block_bytes(table_len, version),
             "reserved": 0, "reserved2": 0, "mech_table_len": f.get("value", 0)}
    if name in fixed:
        return fixed[name], fixed[name]
    bounds: dict[str, tuple[float, float]] = {
        "sequence": (1, 0xFFFFFFFE), "flags": (0, named_flags), "serial": (0, 127), "poles": (2, POLES_MAX),
        "encoder_ppr": (1, 0xFFFF), "tick_hz": TICK_HZ_RANGE, "kt": (0.0, KT_MAX), "c6": (0.0, C6_MAX),
        "k6": (0.0, K6_MAX), "lead_s": (0.0, LEAD_MAX_S), "iqc_limit": (0.0, motor.i_max),
        "table_len": (B.TABLE_LEN_MIN, B.TABLE_LEN_MAX), "table_const": (-motor.i_max, motor.i_max),
        "table_per_amp": (-TABLE_PER_AMP_MAX, TABLE_PER_AMP_MAX),
        "mech_table_const": (-motor.i_max, motor.i_max), "mech_table_per_amp": (-TABLE_PER_AMP_MAX, TABLE_PER_AMP_MAX),
        "fp_len": (0, FP_MAX), "fp_dirs": (0, 3), "grid_phase": (0.0, 2 * math.pi), "id_min_score": (0.0, 1.0),
        "id_margin": (0.0, 2.0), "id_frac_tol": (0.0, math.pi), "mech_c": (0.0, C6_MAX), "mech_k": (0.0, K6_MAX),
        "fingerprint": (-half_pitch, half_pitch)}
    if name in bounds:
        return bounds[name]
    if "phase" in name or name == "hall_angle":
        return -PHASE_MAX, PHASE_MAX
    if f["type"] == "f32":
        big = float(np.finfo(np.float32).max)
        return -big, big
    return 0, (1 << (8 * SIZE[f["type"]])) - 1


def header_field(head: bytes, name: str) -> int | float:
    """One scalar field of a block header's bytes (e.g. read from the ECU's active bank), unchecked."""
    if len(head) < B.HEADER_BYTES:
        raise ValueError(f"{len(head)} bytes, a block header has {B.HEADER_BYTES}")
    fmt = {"u16": "<H", "u32": "<I", "f32": "<f"}
    return struct.unpack_from(fmt[B.FIELDS[name]["type"]], head, B.field_offset(name))[0]


@dataclass(frozen=True)
class MotorType:
    """What makes a block fit a motor: poles P, encoder PPR N_enc and the estimator tick (Hz)."""

    poles: int
    encoder_ppr: int
    tick_hz: float

    @classmethod
    def of_motor(cls, motor: MotorParams) -> MotorType:
        """The motor type of a station's motor parameters."""
        return cls(motor.poles, motor.N_enc, float(np.float32(motor.f_pwm)))

    @classmethod
    def of_block(cls, blk: B.ParamBlock) -> MotorType:
        return cls(blk.poles, blk.encoder_ppr, blk.tick_hz)

    @classmethod
    def of_header(cls, head: bytes) -> MotorType:
        """The motor type in the header of a block image (e.g. read from the ECU's active bank)."""
        if len(head) < B.HEADER_BYTES:
            raise ValueError(f"{len(head)} bytes, a block header has {B.HEADER_BYTES}")
        get = {n: header_field(head, n) for n in ("poles", "encoder_ppr", "tick_hz")}
        return cls(int(get["poles"]), int(get["encoder_ppr"]), float(get["tick_hz"]))

    def __str__(self) -> str:
        return f"{self.poles} poles, {self.encoder_ppr} PPR, {self.tick_hz:g} Hz tick"


def _bounded(problems: list[tuple[str, str]], name: str, value: float, lo: float, hi: float, unit: str,
             lo_open: bool = False) -> None:
    if not math.isfinite(value):
        problems.append((name, f"{value} is not finite"))
    elif value < lo or (lo_open and value == lo) or value > hi:
        low = f"> {lo:g}" if lo_open else f">= {lo:g}"
        problems.append((name, f"{value:g} {unit} is outside the physical bounds ({low} and <= {hi:g})".replace("  ", " ")))


def sanity_problems(blk: B.ParamBlock, i_max: float) -> list[tuple[str, str]]:
    """Why ``blk`` is not physically sane for a motor rated ``i_max`` A: (field, reason) pairs.

    Parameters
    ----------
    blk : ParamBlock
        The decoded block (CRC and sequence are :func:`eol_cal.firmware.block.check`'s business).
    i_max : float
        The motor's current rating (A): the largest ``|i_q|`` its drive may command.
    """
    problems: list[tuple[str, str]] = []
    comp = bool(blk.flags & B.FLAG_COMP_ENABLE)
    _bounded(problems, "iqc_limit", blk.iqc_limit, 0.0, i_max, "A", lo_open=comp)
    _bounded(problems, "kt", blk.kt, 0.0, KT_MAX, "N*m/A", lo_open=True)
    _bounded(problems, "k6", blk.k6, 0.0, K6_MAX, "N*m/A")
    _bounded(problems, "c6", blk.c6, 0.0, C6_MAX, "N*m")
    for name in ("phase_k6", "phase_c6"):
        _bounded(problems, name, getattr(blk, name), -PHASE_MAX, PHASE_MAX, "rad")
    _bounded(problems, "lead_s", blk.lead_s, 0.0, LEAD_MAX_S, "s")
    _bounded(problems, "tick_hz", blk.tick_hz, *TICK_HZ_RANGE, "Hz")
    if not (2 <= blk.poles <= POLES_MAX and blk.poles % 2 == 0):
        problems.append(("poles", f"{blk.poles}: needs an even number from 2 to {POLES_MAX}"))
    if not 1 <= blk.encoder_ppr <= 0xFFFF:
        problems.append(("encoder_ppr", f"{blk.encoder_ppr}: needs 1..65535 pulses per revolution"))
    hall = np.asarray(blk.hall_angle, dtype=np.float64)
    if not np.all(np.isfinite(hall)):
        problems.append(("hall_angle", "not finite"))
    elif np.any(np.abs(hall) > PHASE_MAX):
        problems.append(("hall_angle", f"an angle beyond +-{PHASE_MAX:g} rad"))
    tables = [(name, getattr(blk, name), limit, unit)
              for name, limit, unit in (("table_const", i_max, "A"), ("table_per_amp", TABLE_PER_AMP_MAX, "A/A"))]
    if blk.mech is not None:
        tables += [(name, getattr(blk.mech, name), limit, unit) for name, limit, unit in (
            ("mech_table_const", i_max, "A"), ("mech_table_per_amp", TABLE_PER_AMP_MAX, "A/A"))]
        if blk.poles > 0 and blk.encoder_ppr > 0:
            tables.append(("fingerprint", blk.mech.fingerprint, blk.poles * math.pi / blk.encoder_ppr / 2, "rad"))
        problems += _mech_problems(blk.mech)
    for name, values, limit, unit in tables:
        table = np.asarray(values, dtype=np.float64)
        bad = ~np.isfinite(table) | (np.abs(table) > limit)
        if bad.any():
            j = int(np.argmax(bad))
            problems.append((name, f"entry {j} is {table[j]:g} {unit}, outside +-{limit:g} {unit}; "
                                   f"{int(bad.sum())} such entries"))
    return problems


def _mech_problems(mech: MechParams) -> list[tuple[str, str]]:
    """The scalar bounds of a layout-2 block's mechanical part."""
    problems: list[tuple[str, str]] = []
    for name, amp_max, unit in (("mech_c", C6_MAX, "N*m"), ("mech_k", K6_MAX, "N*m/A")):
        for h, v in enumerate(getattr(mech, name), start=1):
            _bounded(problems, f"{name}[{h}]", v, 0.0, amp_max, unit)
    for name in ("mech_phase_c", "mech_phase_k"):
        for h, v in enumerate(getattr(mech, name), start=1):
            _bounded(problems, f"{name}[{h}]", v, -PHASE_MAX, PHASE_MAX, "rad")
    _bounded(problems, "id_min_score", mech.id_min_score, 0.0, 1.0, "")
    _bounded(problems, "id_margin", mech.id_margin, 0.0, 2.0, "")
    _bounded(problems, "id_frac_tol", mech.id_frac_tol, 0.0, math.pi, "rad", lo_open=True)
    if not (math.isfinite(mech.grid_phase) and 0.0 <= mech.grid_phase < 2 * math.pi):
        problems.append(("grid_phase", f"{mech.grid_phase:g} rad is outside [0, 2*pi)"))
    return problems


def type_problems(blk: B.ParamBlock, want: MotorType) -> list[tuple[str, str]]:
    """Why ``blk`` is for another motor type than ``want``: (field, reason) pairs."""
    have = MotorType.of_block(blk)
    problems = []
    if have.poles != want.poles:
        problems.append(("poles", f"the block is for {have.poles} poles, the motor has {want.poles}"))
    if have.encoder_ppr != want.encoder_ppr:
        problems.append(("encoder_ppr", f"the block is for {have.encoder_ppr} PPR, the motor has {want.encoder_ppr}"))
    if not (math.isfinite(have.tick_hz) and abs(have.tick_hz - want.tick_hz) <= _TICK_RTOL * abs(want.tick_hz)):
        problems.append(("tick_hz", f"the block is for a {have.tick_hz:g} Hz tick, the ECU runs {want.tick_hz:g} Hz"))
    return problems


def require_safe(blk: B.ParamBlock, motor: MotorParams, source: str | None, check_type: bool = True) -> None:
    """Refuse a block that is not sane for ``motor`` (and, with ``check_type``, not of its type).

    Raises
    ------
    InputError
        Naming ``source``, the first field at fault, and every problem found.
    """
    problems = sanity_problems(blk, motor.i_max)
    if check_type:
        problems += type_problems(blk, MotorType.of_motor(motor))
    if problems:
        raise InputError(source, problems[0][0], "unsafe parameter block: " + "; ".join(f"{f}: {r}" for f, r in problems))
