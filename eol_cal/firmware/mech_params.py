"""The mechanical-order part of a layout-2 parameter block (contract revision 1.2): the encoder's
fingerprint, the identification thresholds, the mechanical orders and their tables.

:class:`MechParams` is what :class:`eol_cal.firmware.block.ParamBlock` carries as ``mech`` (None
in a layout-1 block); the byte layout is ``layout_v2.toml``, the firmware's use of it
``firmware_params/MECH.md`` and :mod:`eol_cal.firmware.mech`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any
from collections.abc import Sequence

import numpy as np

from eol_cal.errors import InputError
from eol_cal.firmware.block_layout import FIELDS_BY_VERSION

#: entries of the mechanical tables over one mechanical revolution (layout 2's ``mech_table_len``)
MECH_TABLE_LEN: int = FIELDS_BY_VERSION[2]["mech_table_len"]["value"]
#: pulses the fingerprint has room for, per direction (layout 2's ``fingerprint`` holds 2 x this)
FP_MAX: int = FIELDS_BY_VERSION[2]["fingerprint"]["count"] // 2
#: the mechanical orders the block carries (``mech_c[h-1]`` is order h)
ORDERS: tuple[int, ...] = tuple(range(1, FIELDS_BY_VERSION[2]["mech_c"]["count"] + 1))
#: ``fp_dirs`` bits: the forward and the reverse fingerprint were measured
FP_FORWARD = 1
FP_REVERSE = 2

#: defaults the tool writes (``eol-cal table``): least cosine of the best hypothesis, least margin
#: over the next one, largest hall-to-encoder fraction error (rad electrical, 2 degrees)
ID_MIN_SCORE = 0.5
ID_MARGIN = 0.25
ID_FRAC_TOL = math.radians(2.0)
#: the end of line's switch: ``MECH_COMP_ENABLE`` only when the prediction after a revolution at
#: 300 rpm (``eol_cal.analysis.fingerprint.predicted_margin``, the fingerprint's error measured by
#: ``split_noise``'s jackknife over the stretches) reaches both a cosine of SWITCH_MIN_SCORE and a
#: margin over the next hypothesis of SWITCH_MARGIN. Calibrated end to end
#: (``bench/bench_mech_margin.py --end-to-end``, firmware_params/MECH.md "The switch, calibrated"):
#: plant motors through the fit and the block it writes, the twin on the fitted fingerprint. Over
#: five sets (480 motors) the cosine separates the motors the twin identifies on every power-up
#: from those it does not where the margin cannot: every motor the twin missed was predicted at a
#: cosine of 0.270 or less, while their margins reached 0.097 (a 0.2x motor switched on at the
#: margin's former 0.06, the twin right on 118 of 128). 0.29 keeps a margin over 0.270. The margin
#: stays a floor at 0 (a neighbour hypothesis the cosine cannot see; the result file's threshold
#: is not negative): it turns off 3 of the 80 0.3x motors there that the twin identified (predicted
#: -0.036 to -0.001), none the cosine would. The firmware's runtime thresholds stay ID_MIN_SCORE
#: and ID_MARGIN.
SWITCH_MARGIN = 0.0
#: the least predicted cosine (see SWITCH_MARGIN)
SWITCH_MIN_SCORE = 0.29

_SCALARS = ("grid_phase", "id_min_score", "id_margin", "id_frac_tol")
_TRIPLES = ("mech_c", "mech_phase_c", "mech_k", "mech_phase_k")
_ARRAYS = ("mech_table_const", "mech_table_per_amp", "fingerprint")


def _f32_array(value: Any, name: str) -> np.ndarray:
    try:
        with np.errstate(over="ignore"):
            arr = np.array(value, dtype=np.float32, copy=True)
    except (TypeError, ValueError) as exc:
        raise InputError(None, name, f"not numbers: {exc}") from exc
    if arr.ndim != 1:
        raise InputError(None, name, f"must be 1-D, got shape {arr.shape}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class MechParams:
    """The mechanical-order extension of a layout-2 block (floats held as binary32).

    Attributes
    ----------
    fp_dirs : int
        ``FP_FORWARD`` | ``FP_REVERSE``: which halves of ``fingerprint`` were measured.
    grid_phase : float
        Electrical angle (rad, [0, 2*pi)) of the fingerprint frame's quadrature boundary 0 on the
        mean encoder grid: where the frame sits against the halls (the hall-to-encoder fraction).
    id_min_score, id_margin : float
        Identification thresholds: least cosine of the best pole-pair hypothesis, least cosine
        margin over the next (the confidence threshold).
    id_frac_tol : float
        Largest hall-to-encoder fraction error of an identified frame (rad, electrical).
    mech_c, mech_phase_c : tuple of 3 float
        Load-independent ripple at mechanical orders 1..3 (N*m) and phases (rad, in the
        fingerprint frame's mechanical angle).
    mech_k, mech_phase_k : tuple of 3 float
        Load-proportional ripple at mechanical orders 1..3 (N*m/A) and phases (rad).
    mech_table_const, mech_table_per_amp : ndarray (MECH_TABLE_LEN,)
        The mechanical i_qc (A, and A per A of i_qo) at mechanical angle ``2*pi*j/MECH_TABLE_LEN``.
    fingerprint : ndarray (2 * encoder_ppr,)
        Placement error of each A edge (rad, electrical), mean 0 per direction: entry ``2*m`` the
        forward edge of pulse m, ``2*m + 1`` its reverse edge (the estimator's ``c_tab`` layout).
    """

    fp_dirs: int
    grid_phase: float
    id_min_score: float
    id_margin: float
    id_frac_tol: float
    mech_c: tuple[float, ...]
    mech_phase_c: tuple[float, ...]
    mech_k: tuple[float, ...]
    mech_phase_k: tuple[float, ...]
    mech_table_const: np.ndarray = field(repr=False)
    mech_table_per_amp: np.ndarray = field(repr=False)
    fingerprint: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        put = object.__setattr__
        put(self, "fp_dirs", int(self.fp_dirs))
        for name in _SCALARS:
            put(self, name, float(np.float32(getattr(self, name))))
        for name in _TRIPLES:
            vals = tuple(float(np.float32(v)) for v in getattr(self, name))
            if len(vals) != len(ORDERS):
                raise InputError(None, name, f"needs {len(ORDERS)} values (orders {ORDERS}), got {len(vals)}")
            put(self, name, vals)
        for name in _ARRAYS:
            put(self, name, _f32_array(getattr(self, name), name))

    @property
    def fp_len(self) -> int:
        """Pulses in the fingerprint (the block's ``fp_len``)."""
        return int(self.fingerprint.size // 2)

    def replace(self, **changes: Any) -> MechParams:
        return replace(self, **changes)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, MechParams):
            return NotImplemented
        return all(_bits(getattr(self, f.name)) == _bits(getattr(other, f.name)) for f in fields(self))

    __hash__ = None  # type: ignore[assignment]

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dict (arrays as lists; non-finite floats as strings)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, (np.ndarray, tuple)):
                v = [_json(float(x)) for x in v]
            elif isinstance(v, float):
                v = _json(v)
            out[f.name] = v
        out["fp_len"] = self.fp_len
        return out


def _json(x: float) -> float | str:
    return x if math.isfinite(x) else str(x)


def _bits(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tobytes()
    if isinstance(v, tuple):
        return np.asarray(v, np.float32).tobytes()
    if isinstance(v, float):
        return np.float32(v).tobytes()
    return v


def mech_problems(mech: MechParams, encoder_ppr: int) -> list[tuple[str, str]]:
    """Why ``mech`` cannot be packed into a valid layout-2 block: (field, reason) pairs."""
    problems: list[tuple[str, str]] = []
    if not 0 <= mech.fp_dirs <= FP_FORWARD | FP_REVERSE:
        problems.append(("fp_dirs", f"{mech.fp_dirs}: bits 0 (forward) and 1 (reverse) only"))
    if mech.fingerprint.size != 2 * encoder_ppr:
        problems.append(("fingerprint", f"{mech.fingerprint.size} values, needs 2 x encoder_ppr = {2 * encoder_ppr}"))
    if encoder_ppr > FP_MAX:
        problems.append(("fp_len", f"{encoder_ppr} pulses, the fingerprint holds at most {FP_MAX}"))
    for name in ("mech_table_const", "mech_table_per_amp"):
        if getattr(mech, name).size != MECH_TABLE_LEN:
            problems.append((name, f"{getattr(mech, name).size} entries, needs {MECH_TABLE_LEN}"))
    for name in _SCALARS + _TRIPLES + _ARRAYS:
        if not np.all(np.isfinite(np.asarray(getattr(mech, name), dtype=np.float64))):
            problems.append((name, "not finite in binary32"))
    return problems


def unused_mech(encoder_ppr: int) -> MechParams:
    """An empty mechanical part (no fingerprint, no orders): what a layout-2 block carries when
    nothing was measured; the firmware never identifies with it (``fp_dirs`` 0)."""
    zeros3 = (0.0,) * len(ORDERS)
    table = np.zeros(MECH_TABLE_LEN, np.float32)
    return MechParams(fp_dirs=0, grid_phase=0.0, id_min_score=ID_MIN_SCORE, id_margin=ID_MARGIN, id_frac_tol=ID_FRAC_TOL,
                      mech_c=zeros3, mech_phase_c=zeros3, mech_k=zeros3, mech_phase_k=zeros3,
                      mech_table_const=table, mech_table_per_amp=table,
                      fingerprint=np.zeros(2 * encoder_ppr, np.float32))


def make_mech_tables(c: Sequence[float], phase_c: Sequence[float], k: Sequence[float], phase_k: Sequence[float],
                     kt: float, n: int = MECH_TABLE_LEN) -> tuple[np.ndarray, np.ndarray]:
    """The mechanical tables of orders 1..3 (firmware_params/MECH.md, "Tables").

    ``table_const[j] = sum_h c_h sin(h*theta_j + phase_c_h) / kt`` and likewise per ampere with
    ``k_h``, at the mechanical angle ``theta_j = 2*pi*j/n``; binary64, rounded once to binary32.

    Parameters
    ----------
    c, phase_c : sequences of 3 float
        Load-independent ripple (N*m) and phase (rad) at mechanical orders 1, 2, 3.
    k, phase_k : sequences of 3 float
        Load-proportional ripple (N*m/A) and phase (rad).
    kt : float
        Torque constant (N*m/A).
    """
    theta = 2.0 * np.pi * np.arange(n) / n
    tc = np.zeros(n)
    tp = np.zeros(n)
    for h, ch, pc, kh, pk in zip(ORDERS, c, phase_c, k, phase_k, strict=True):
        tc += ch * np.sin(h * theta + pc)
        tp += kh * np.sin(h * theta + pk)
    return (tc / kt).astype(np.float32), (tp / kt).astype(np.float32)
