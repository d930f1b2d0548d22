"""The firmware contract's constants (``docs/firmware-contract.md``), each spelled here once.

The block's byte layouts (offsets, types) are in ``layout_v1.toml`` and ``layout_v2.toml``; what the bytes mean lives here:
the block marker, the ``flags`` bits, the check routine's status codes, the hall convention and
its nominal table, and the UDS identifiers. :mod:`eol_cal.firmware.block`, the estimator, the
ECU client and simulator read them from here, and :mod:`eol_cal.firmware.gen_header` writes them
into the C header ``firmware_params/eol_param_block.h``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

# --- physical bounds ------------------------------------------------------------------------
#: What a block's values (and a fit's estimates, which become them) must lie within; the block's
#: sanity check (:mod:`eol_cal.firmware.block_sanity`) and the fit result reader share them.
#: The paper's motor has k6 ~ 6e-4 N*m/A and c6 ~ 5e-3 N*m; anything past these is a corrupt
#: file, not a motor (documented in docs/json.md).
K6_MAX = 1.0  # N*m/A
C6_MAX = 10.0  # N*m
KT_MAX = 10.0  # N*m/A
PHASE_MAX = 100.0  # rad (phases are wrapped to a few pi; 100 rad only catches garbage)
DELAY_MAX = 1.0  # s

DEFAULT_TABLE_LEN = 256
"""Table length N that eol-cal builds when none is given (``eol-cal table``, the checked-in A2L)."""

# --- the parameter block (section 2) ----------------------------------------------------------
MAGIC = 0xEC6A
"""Block marker, the block's first u16."""


class Flag(NamedTuple):
    """One bit of the block's ``flags`` word."""

    bit: int
    meaning: str


#: The block's ``flags`` bits by name (every other bit 0). Bits 2-5 (revision 1.1) are the
#: estimator options, each honoured only with ``INTERP_ENABLE``; their arithmetic is the estimator
#: reference's (firmware_params/ESTIMATOR.md). Bit 6 (revision 1.2) switches the mechanical-order
#: compensation of a layout-2 block (firmware_params/MECH.md), honoured only with COMP_ENABLE,
#: INTERP_ENABLE and EST_LEARN_PITCH_ERRORS.
FLAGS: dict[str, Flag] = {
    "COMP_ENABLE": Flag(0, "apply i_qc"),
    "INTERP_ENABLE": Flag(1, "use the interpolated angle theta_hat (0 = raw encoder angle)"),
    "EST_CLAMP_TO_NEXT_EDGE": Flag(2, "estimator: prediction kept inside the current quadrature count, "
                                      "speed bounded by one pitch per elapsed tick count"),
    "EST_LEARN_GRID_OFFSET": Flag(3, "estimator: encoder grid offset = running mean of the hall corrections"),
    "EST_ACCEL_PREDICTION": Flag(4, "estimator: extrapolates the filtered acceleration between edges"),
    "EST_LEARN_PITCH_ERRORS": Flag(5, "estimator: learns each edge's placement error at steady speed"),
    "MECH_COMP_ENABLE": Flag(6, "identify the rotor's mechanical angle (layout 2) and add the mechanical-order i_qc"),
}
FLAG_COMP_ENABLE = 1 << FLAGS["COMP_ENABLE"].bit
FLAG_INTERP_ENABLE = 1 << FLAGS["INTERP_ENABLE"].bit
FLAG_EST_CLAMP_TO_NEXT_EDGE = 1 << FLAGS["EST_CLAMP_TO_NEXT_EDGE"].bit
FLAG_EST_LEARN_GRID_OFFSET = 1 << FLAGS["EST_LEARN_GRID_OFFSET"].bit
FLAG_EST_ACCEL_PREDICTION = 1 << FLAGS["EST_ACCEL_PREDICTION"].bit
FLAG_EST_LEARN_PITCH_ERRORS = 1 << FLAGS["EST_LEARN_PITCH_ERRORS"].bit
FLAG_MECH_COMP_ENABLE = 1 << FLAGS["MECH_COMP_ENABLE"].bit
#: the bits MECH_COMP_ENABLE needs besides itself (and a layout-2 block)
FLAGS_MECH_NEEDS = (1 << FLAGS["COMP_ENABLE"].bit) | (1 << FLAGS["INTERP_ENABLE"].bit) | FLAG_EST_LEARN_PITCH_ERRORS
#: name prefix of the estimator option bits
EST_PREFIX = "EST_"
#: the estimator option bits (2-5) by name
ESTIMATOR_OPTIONS: dict[str, int] = {name: 1 << f.bit for name, f in FLAGS.items() if name.startswith(EST_PREFIX)}
#: every estimator option bit
FLAGS_ESTIMATOR = sum(ESTIMATOR_OPTIONS.values())
#: every bit the contract defines
FLAGS_KNOWN = sum(1 << f.bit for f in FLAGS.values())


class CheckStatus(NamedTuple):
    """One answer of the ECU's check routine (``RID_CHECK``)."""

    code: int
    text: str


#: The check routine's status codes by name; ``HEADER_INVALID`` wins over ``CRC_MISMATCH``.
CHECK_STATUS: dict[str, CheckStatus] = {
    "VALID": CheckStatus(0, "valid"),
    "CRC_MISMATCH": CheckStatus(1, "CRC mismatch"),
    "HEADER_INVALID": CheckStatus(2, "header invalid"),
}
STATUS_VALID = CHECK_STATUS["VALID"].code
STATUS_CRC_MISMATCH = CHECK_STATUS["CRC_MISMATCH"].code
STATUS_HEADER_INVALID = CHECK_STATUS["HEADER_INVALID"].code

# --- the hall convention (section 2) ----------------------------------------------------------
#: Hall states in forward rotation (U = bit0, V = bit1, W = bit2); state 5 begins at 0 rad
#: electrical and each state spans 60 degrees. States 0 and 7 are faults.
HALL_FORWARD_SEQUENCE: tuple[int, ...] = (5, 1, 3, 2, 6, 4)
HALL_SECTOR_RAD = math.pi / 3
"""Electrical angle one hall state spans (rad)."""
#: Forward successor of hall state s (``HALL_NEXT[s]``), 0 for the fault states 0 and 7.
HALL_NEXT: tuple[int, ...] = tuple(
    HALL_FORWARD_SEQUENCE[(HALL_FORWARD_SEQUENCE.index(s) + 1) % 6] if s in HALL_FORWARD_SEQUENCE else 0
    for s in range(8)
)
#: Nominal ``hall_angle`` table (rad, electrical): entry s-1 is where state s begins in forward
#: rotation (60, 180, 120, 300, 0, 240 degrees for the states 1..6).
NOMINAL_HALL_ANGLE: tuple[float, ...] = tuple(
    math.radians(60.0 * HALL_FORWARD_SEQUENCE.index(s)) for s in range(1, 7)
)

# --- UDS identifiers (section 3) ---------------------------------------------------------------
DID_SERIAL = 0xF18C
"""ReadDataByIdentifier: ECU serial (ASCII)."""
DID_SW_VERSION = 0xF195
"""ReadDataByIdentifier: software version (ASCII)."""
DID_LAYOUTS = 0xFD00
"""ReadDataByIdentifier: supported layout versions (count u8, one u16 each)."""
DID_ACTIVE_BLOCK = 0xFD01
"""ReadDataByIdentifier: the active block (bank, sequence)."""
NO_BANK = 0xFF
"""``DID_ACTIVE_BLOCK`` bank value when no bank holds a valid block."""
RID_ERASE = 0xFF00
"""RoutineControl: erase a bank."""
RID_CHECK = 0x0202
"""RoutineControl: check the block at an address (answers a ``CHECK_STATUS`` code)."""
