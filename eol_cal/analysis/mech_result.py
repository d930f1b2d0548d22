"""A motor's mechanical-order result (contract revision 1.2): the ``mech`` object of a fit result's
``motors`` entry, typed, with its one writer and its one strict reader.

``status`` is ``"ok"`` when the block may switch ``MECH_COMP_ENABLE`` on, else ``"off"`` with the
reasons (a fingerprint too weak to identify, not measured, orders not fitted): such a motor gets a
layout-2 block with ``MECH_COMP_ENABLE`` clear, never a guess.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from eol_cal.analysis.motor_result import C6_MAX, PHASE_MAX, ValueCi, _Reader

STATUS_OK = "ok"
STATUS_OFF = "off"
#: fingerprint entries are placement errors of a few tenths of a pitch at most (rad electrical)
FP_MAX_RAD = 1.0


@dataclass(frozen=True)
class MechOrder:
    """One mechanical order: load-independent ripple ``c`` (N*m) and its phase (rad, the block's
    mechanical frame), each with its 95 % interval."""

    order: int
    c: ValueCi
    phase_c: ValueCi

    def to_json(self) -> dict[str, Any]:
        return {"order": self.order, "c": self.c.to_json(), "phase_c": self.phase_c.to_json()}


@dataclass(frozen=True)
class MechResult:
    """The ``mech`` object of a motor result.

    Attributes
    ----------
    status, reasons
        ``"ok"`` or ``"off"`` and why it is off.
    fingerprint, sigma : tuple of float (2 * encoder_ppr)
        Edge errors (rad electrical; entry 2m forward, 2m+1 reverse) and their standard errors
        in the block's frame (0 / inf where not measured: JSON null).
    dirs : int
        FP_FORWARD | FP_REVERSE measured.
    grid_phase : float
        rad electrical, where the frame's count boundary 0 sits.
    windows : tuple of (int or None)
        Per capture window, its offset into the frame (None: not identified, not used).
    score, margin : float
        Predicted cosine of the true hypothesis and margin after one revolution at ``ref_rpm``.
    threshold : float
        The identification margin the block requires (``id_margin``).
    ref_rpm : float
        Speed the prediction is for (rpm).
    orders : tuple of MechOrder
        Mechanical orders 1..3 (empty when not fitted).
    """

    status: str
    reasons: tuple[str, ...]
    fingerprint: tuple[float, ...]
    sigma: tuple[float | None, ...]
    dirs: int
    grid_phase: float
    windows: tuple[int | None, ...]
    score: float
    margin: float
    threshold: float
    ref_rpm: float
    orders: tuple[MechOrder, ...]

    @property
    def enabled(self) -> bool:
        return self.status == STATUS_OK

    def to_json(self) -> dict[str, Any]:
        return {
            "status": self.status, "reasons": list(self.reasons), "dirs": self.dirs, "grid_phase": self.grid_phase,
            "margin": {"predicted": self.margin, "score": self.score, "threshold": self.threshold, "ref_rpm": self.ref_rpm},
            "orders": [o.to_json() for o in self.orders],
            "windows": list(self.windows),
            "fingerprint": list(self.fingerprint), "sigma": list(self.sigma),
        }

    @classmethod
    def from_json(cls, value: Any, source: str, where: str, encoder_ppr: int) -> MechResult:
        """Check a ``mech`` object strictly; :class:`ResultFormatError` names file, field and reason."""
        r = _Reader(source, where)
        obj = r.obj(value, "")
        status = r.string(obj, "status")
        if status not in (STATUS_OK, STATUS_OFF):
            raise r.error("status", f"{status!r} is not {STATUS_OK!r} or {STATUS_OFF!r}")
        m = r.obj(r.need(obj, "margin"), "margin")
        sub = _Reader(source, f"{where}margin.")
        fp = r.list(obj, "fingerprint")
        sg = r.list(obj, "sigma")
        if len(fp) != 2 * encoder_ppr or len(sg) != 2 * encoder_ppr:
            raise r.error("fingerprint", f"needs 2 x encoder_ppr = {2 * encoder_ppr} values and sigmas, "
                                         f"got {len(fp)} and {len(sg)}")
        fps = tuple(_num(r, v, f"fingerprint[{i}]", FP_MAX_RAD) for i, v in enumerate(fp))
        sgs = tuple(None if v is None else _num(r, v, f"sigma[{i}]", math.inf, lo=0.0) for i, v in enumerate(sg))
        dirs = obj.get("dirs")
        if isinstance(dirs, bool) or not isinstance(dirs, int) or not 0 <= dirs <= 3:
            raise r.error("dirs", f"expected 0..3, got {dirs!r}")
        windows = r.list(obj, "windows")
        if not all(w is None or (isinstance(w, int) and not isinstance(w, bool) and 0 <= w < encoder_ppr)
                   for w in windows):
            raise r.error("windows", f"expected offsets 0..{encoder_ppr - 1} or null")
        orders = []
        for i, o in enumerate(r.list(obj, "orders")):
            osub = _Reader(source, f"{where}orders[{i}].")
            oo = r.obj(o, f"orders[{i}]")
            orders.append(MechOrder(osub.integer(oo, "order"), osub.value_ci(oo, "c", (0.0, C6_MAX)),
                                    osub.value_ci(oo, "phase_c", (-PHASE_MAX, PHASE_MAX))))
        return cls(status=status, reasons=tuple(r.string_list(obj, "reasons")), fingerprint=fps, sigma=sgs, dirs=dirs,
                   grid_phase=r.number(obj, "grid_phase", (0.0, 2 * math.pi)), windows=tuple(windows),
                   score=sub.number(m, "score", (-1.5, 1.5)), margin=sub.number(m, "predicted", (-3.0, 3.0)),
                   threshold=sub.number(m, "threshold", (0.0, 2.0)), ref_rpm=sub.number(m, "ref_rpm", (0.0, 1e5)),
                   orders=tuple(orders))


def _num(r: _Reader, v: Any, field: str, bound: float, lo: float | None = None) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise r.error(field, f"expected a finite number, got {v!r}")
    low = -bound if lo is None else lo
    if not low <= v <= bound:
        raise r.error(field, f"{v!r} outside [{low:g}, {bound:g}]")
    return float(v)
