"""One motor's fit result as a typed object: the one reader and writer of a ``motors`` entry.

The fit builds :class:`MotorResult` directly (:func:`eol_cal.analysis.result.motor_result`);
:meth:`MotorResult.to_json` writes it as an entry of an ``eol-cal/fit-result/1`` document, key for
key (``docs/json.md``), where a file or stdout is written; :meth:`MotorResult.from_json` reads such
an entry back from a file, checked strictly (types, finiteness, signs and physical bounds), and
refuses with the file, the field and the reason.
"""

from __future__ import annotations

import builtins
import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Any
from collections.abc import Mapping

from eol_cal.errors import ResultFormatError
# the physical bounds a fit result is read against are the block's (a block holds what a fit gives)
from eol_cal.firmware.contract import C6_MAX, DELAY_MAX, K6_MAX, KT_MAX, PHASE_MAX
from eol_cal.firmware.mech_params import ORDERS

ESTIMATE_KEYS = ("k6", "phase_k6", "c6", "phase_c6")


class FitStatus(StrEnum):
    """Whether a motor's fit is usable (``ok``) or why not; the value is the file's ``status``."""

    OK = "ok"
    #: the solver did not end successfully, or its values are not finite (``MotorResult.solver_result`` says how)
    NOT_CONVERGED = "not_converged"
    #: a 95 % interval wider than the limits
    CI_TOO_WIDE = "ci_too_wide"
    #: the speed bands contradict the model (the model check)
    MODEL_MISMATCH = "model_mismatch"


@dataclass(frozen=True)
class ValueCi:
    """An estimate and its 95 % interval half-width (same unit; ``ci95`` None when not finite)."""

    value: float
    ci95: float | None

    def to_json(self) -> dict[str, float | None]:
        return {"value": self.value, "ci95": self.ci95}


@dataclass(frozen=True)
class Harmonic:
    """Estimates of one order above 6 (``c`` N*m, ``k`` N*m/A, phases rad); None when not fitted."""

    order: int
    c: ValueCi | None = None
    phase_c: ValueCi | None = None
    k: ValueCi | None = None
    phase_k: ValueCi | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"order": self.order}
        for name in ("c", "phase_c", "k", "phase_k"):
            est = getattr(self, name)
            if est is not None:
                out[name] = est.to_json()
        return out


@dataclass(frozen=True)
class FitEstimates:
    """The estimates of a usable fit: k6 (N*m/A), c6 (N*m), phases (rad), delay_s (s), higher orders."""

    k6: ValueCi
    phase_k6: ValueCi
    c6: ValueCi
    phase_c6: ValueCi
    delay_s: ValueCi
    harmonics: tuple[Harmonic, ...]


@dataclass(frozen=True)
class OperatingPoint:
    """The segment the compensation is tuned for: speed (rpm) and i_qo (A)."""

    speed_rpm: float
    i_qo_a: float


@dataclass(frozen=True)
class MotorResult:
    """One entry of a fit result's ``motors`` (``docs/json.md``).

    Attributes
    ----------
    serial : str
    status : FitStatus
        ``ok``, ``not_converged``, ``ci_too_wide`` or ``model_mismatch``.
    reasons : tuple of str
        Why the fit is not usable.
    estimates : FitEstimates or None
        None when the fit is not usable (the file holds ``null`` in every estimate field).
    kt, kt_source
        Torque constant (N*m/A) and where it came from.
    metrics, fit, model, hall_angle
        The entry's objects as written by the fit (``hall_angle`` None for files older than it).
    poles, encoder_ppr
        Pole count and encoder pulses per revolution.
    operating_point : OperatingPoint
    segments : tuple of dict
        Per-segment table (source, t_start/t_end s, i_qo_a A, speed_rpm, T_avg_nm N*m, shaft gain/phase).
    sources : tuple of str
        Capture files.
    mech : MechResult or None
        The mechanical orders and the encoder's fingerprint (contract revision 1.2,
        :class:`MechResult`); None for results without them.
    left_out : tuple of (str, str), or None
        Each capture window that gave the fit no segment: its source and why (None: a result
        older than the field).
    model_check : dict or None
        The speed bands' agreement (:class:`eol_cal.analysis.fit.model_check.ModelCheck` as JSON;
        None: a result older than it).
    solver_result : str or None
        How the solver ended, the name of optimistix's ``RESULTS`` (``successful``,
        ``max_steps_reached``, ...: :attr:`eol_cal.analysis.fit.MotorFit.solver_result`; ``nonfinite``
        also where its values or their variances are not finite): ``successful`` exactly when the
        fit converged. None for a result read from a file, which keeps only ``fit.converged``.
    """

    serial: str
    status: FitStatus
    reasons: tuple[str, ...]
    estimates: FitEstimates | None
    kt: float
    kt_source: str
    metrics: dict[str, Any]
    fit: dict[str, Any]
    model: dict[str, Any]
    hall_angle: dict[str, Any] | None
    poles: int
    encoder_ppr: int
    operating_point: OperatingPoint
    segments: tuple[dict[str, Any], ...]
    sources: tuple[str, ...]
    mech: MechResult | None = None
    left_out: tuple[tuple[str, str], ...] | None = None
    model_check: dict[str, Any] | None = None
    solver_result: str | None = None

    @property
    def usable(self) -> bool:
        return self.status == FitStatus.OK and self.estimates is not None

    def to_json(self) -> dict[str, Any]:
        """The ``motors`` entry, keys in the order the fit writes them."""
        e = self.estimates
        out: dict[str, Any] = {"serial": self.serial, "status": str(self.status), "reasons": list(self.reasons)}
        for key in ESTIMATE_KEYS:
            out[key] = None if e is None else getattr(e, key).to_json()
        out["kt"] = self.kt
        out["kt_source"] = self.kt_source
        out["delay_s"] = None if e is None else e.delay_s.to_json()
        out["harmonics"] = None if e is None else [h.to_json() for h in e.harmonics]
        out["metrics"] = self.metrics
        out["fit"] = self.fit
        out["model"] = self.model
        if self.hall_angle is not None:
            out["hall_angle"] = self.hall_angle
        out["poles"] = self.poles
        out["encoder_ppr"] = self.encoder_ppr
        out["operating_point"] = {"speed_rpm": self.operating_point.speed_rpm, "i_qo_a": self.operating_point.i_qo_a}
        out["segments"] = [dict(s) for s in self.segments]
        out["sources"] = list(self.sources)
        if self.model_check is not None:
            out["model_check"] = self.model_check
        if self.left_out is not None:
            out["captures_left_out"] = [{"source": src, "reason": why} for src, why in self.left_out]
        if self.mech is not None:
            out["mech"] = self.mech.to_json()
        return out

    @classmethod
    def from_json(cls, rec: Any, source: str = "<result>", where: str = "") -> MotorResult:
        """Check one ``motors`` entry and build it; :class:`ResultFormatError` names file, field and reason.

        Parameters
        ----------
        rec : object
            The decoded JSON entry.
        source : str
            File it came from, for errors.
        where : str
            Prefix of field names in errors (e.g. ``motors[0].``).
        """
        r = _Reader(source, where)
        obj = r.obj(rec, "")
        serial = r.string(obj, "serial")
        status = r.status(obj)
        reasons = tuple(r.string_list(obj, "reasons"))
        estimates = None
        if status == FitStatus.OK:
            amp = {"k6": K6_MAX, "c6": C6_MAX}
            vals = {k: r.value_ci(obj, k, (0.0, amp[k]) if k in amp else (-PHASE_MAX, PHASE_MAX)) for k in ESTIMATE_KEYS}
            delay = r.value_ci(obj, "delay_s", (-DELAY_MAX, DELAY_MAX))
            harmonics = tuple(r.harmonic(h, f"harmonics[{i}]") for i, h in enumerate(r.list(obj, "harmonics")))
            estimates = FitEstimates(delay_s=delay, harmonics=harmonics, **vals)
        else:
            for k in (*ESTIMATE_KEYS, "delay_s", "harmonics"):
                if obj.get(k, None) is not None:
                    raise r.error(k, f"must be null when status is {status.value!r}")
        fit = r.obj(r.need(obj, "fit"), "fit")
        if status == FitStatus.OK and fit.get("converged") is not True:
            # a fit that did not converge is never a result, whatever its status says
            raise r.error("fit.converged", f"must be true when status is 'ok', got {fit.get('converged')!r}")
        op = r.obj(r.need(obj, "operating_point"), "operating_point")
        mech = None
        if obj.get("mech") is not None:
            mech = MechResult.from_json(obj["mech"], source, f"{where}mech.", r.integer(obj, "encoder_ppr"))
        return cls(
            serial=serial, status=status, reasons=reasons, estimates=estimates,
            kt=r.number(obj, "kt", (0.0, KT_MAX)), kt_source=r.string(obj, "kt_source"),
            metrics=r.obj(r.need(obj, "metrics"), "metrics"), fit=fit,
            model=r.obj(r.need(obj, "model"), "model"),
            hall_angle=None if "hall_angle" not in obj else r.obj(obj["hall_angle"], "hall_angle"),
            poles=r.integer(obj, "poles"), encoder_ppr=r.integer(obj, "encoder_ppr"),
            operating_point=OperatingPoint(r.number(op, "speed_rpm", None, "operating_point."),
                                           r.number(op, "i_qo_a", None, "operating_point.")),
            segments=tuple(r.obj(s, f"segments[{i}]") for i, s in enumerate(r.list(obj, "segments"))),
            sources=tuple(r.string_list(obj, "sources")), mech=mech,
            left_out=None if "captures_left_out" not in obj else r.left_out(obj),
            model_check=None if obj.get("model_check") is None else r.model_check(obj["model_check"]),
        )


class _Reader:
    """Typed getters that raise :class:`ResultFormatError` with the file and the field."""

    def __init__(self, source: str, where: str) -> None:
        self.source = source
        self.where = where

    def error(self, field: str, reason: str) -> ResultFormatError:
        return ResultFormatError(self.source, f"{self.where}{field}" or None, reason)

    def need(self, obj: Mapping[str, Any], key: str, prefix: str = "") -> Any:
        if key not in obj:
            raise self.error(prefix + key, "missing")
        return obj[key]

    def obj(self, value: Any, field: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.error(field, f"expected an object, got {_kind(value)}")
        return value

    def list(self, obj: Mapping[str, Any], key: str) -> list[Any]:
        value = self.need(obj, key)
        if not isinstance(value, list):
            raise self.error(key, f"expected a list, got {_kind(value)}")
        return value

    def string(self, obj: Mapping[str, Any], key: str) -> str:
        value = self.need(obj, key)
        if not isinstance(value, str):
            raise self.error(key, f"expected a string, got {_kind(value)}")
        return value

    def status(self, obj: Mapping[str, Any]) -> FitStatus:
        value = self.string(obj, "status")
        try:
            return FitStatus(value)
        except ValueError:
            raise self.error("status", f"{value!r} is not one of {', '.join(s.value for s in FitStatus)}") from None

    def string_list(self, obj: Mapping[str, Any], key: str) -> builtins.list[str]:  # builtins: list is the method above here
        value = self.list(obj, key)
        if not all(isinstance(v, str) for v in value):
            raise self.error(key, "expected a list of strings")
        return value

    def model_check(self, value: Any) -> dict[str, Any]:
        m = self.obj(value, "model_check")
        sub = _Reader(self.source, f"{self.where}model_check.")
        status = sub.string(m, "status")
        if status not in ("ok", "mismatch", "insensitive", "not checked"):
            raise sub.error("status", f"{status!r} is not ok, mismatch, insensitive or not checked")
        sub.string(m, "note")
        sub.number(m, "p_value", (0.0, 1.0), nullable=True)
        sub.list(m, "bands")
        if "bench" in m and m["bench"] not in ("identified", "simulated", "assumed"):  # absent before issue 34 (b)
            raise sub.error("bench", f"{m['bench']!r} is not identified, simulated or assumed")
        return m

    def left_out(self, obj: Mapping[str, Any]) -> tuple[tuple[str, str], ...]:
        out = []
        for i, entry in enumerate(self.list(obj, "captures_left_out")):
            e = self.obj(entry, f"captures_left_out[{i}]")
            sub = _Reader(self.source, f"{self.where}captures_left_out[{i}].")
            out.append((sub.string(e, "source"), sub.string(e, "reason")))
        return tuple(out)

    def integer(self, obj: Mapping[str, Any], key: str) -> int:
        value = self.need(obj, key)
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise self.error(key, f"expected a positive integer, got {value!r}")
        return value

    def number(self, obj: Mapping[str, Any], key: str, bounds: tuple[float, float] | None,
               prefix: str = "", *, nullable: bool = False) -> Any:
        value = self.need(obj, key, prefix)
        if value is None and nullable:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(prefix + key, f"expected a number, got {_kind(value)} {value!r}")
        if not math.isfinite(value):
            raise self.error(prefix + key, f"not a finite number: {value!r}")
        if bounds is not None and not bounds[0] <= value <= bounds[1]:
            raise self.error(prefix + key, f"{value!r} outside the physical bounds [{bounds[0]:g}, {bounds[1]:g}]")
        return value

    def value_ci(self, obj: Mapping[str, Any], key: str, bounds: tuple[float, float]) -> ValueCi:
        entry = self.need(obj, key)
        if isinstance(entry, dict):
            value = self.number(entry, "value", bounds, f"{key}.")
            ci95 = self.number(entry, "ci95", (0.0, math.inf), f"{key}.", nullable=True)
            return ValueCi(value, ci95)
        # a bare number where {"value", "ci95"} belongs: judged as the value, so the reason is the real one
        self.number(obj, key, bounds)
        raise self.error(key, "expected an object {value, ci95}")

    def harmonic(self, value: Any, field: str) -> Harmonic:
        h = self.obj(value, field)
        sub = _Reader(self.source, f"{self.where}{field}.")
        order = sub.integer(h, "order")
        parts: dict[str, ValueCi] = {}
        for name in ("c", "phase_c", "k", "phase_k"):
            if name in h:
                bounds = {"c": (0.0, C6_MAX), "k": (0.0, K6_MAX)}.get(name, (-PHASE_MAX, PHASE_MAX))
                parts[name] = sub.value_ci(h, name, bounds)
        return Harmonic(order, **parts)


# --- the mechanical part (contract revision 1.2) ---------------------------------------------
# A motor's ``mech`` object: ``status`` ``"ok"`` when the block may switch ``MECH_COMP_ENABLE`` on,
# else ``"off"`` with the reasons (a fingerprint too weak to identify, not measured, orders not
# fitted): such a motor gets a layout-2 block with ``MECH_COMP_ENABLE`` clear, never a guess.

MECH_OK = "ok"
MECH_OFF = "off"
#: fingerprint entries are placement errors of a few tenths of a pitch at most (rad electrical)
FP_MAX_RAD = 1.0


@dataclass(frozen=True)
class MechOrder:
    """One mechanical order: load-independent ripple ``c`` (N*m) and its phase (rad, the block's
    mechanical frame), each with its 95 % interval; ``no_interval`` says why both intervals are
    None where the fit cannot give an honest one (JSON key ``no_interval``, written only then: a
    document without it reads as before)."""

    order: int
    c: ValueCi
    phase_c: ValueCi
    no_interval: str | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"order": self.order, "c": self.c.to_json(), "phase_c": self.phase_c.to_json()}
        if self.no_interval is not None:
            out["no_interval"] = self.no_interval
        return out


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
        The least predicted margin end of line switches ``MECH_COMP_ENABLE`` on at
        (``SWITCH_MARGIN``); the block's own ``id_margin``, the firmware's runtime threshold on the
        margin it measures, is ``ID_MARGIN`` whatever this is.
    ref_rpm : float
        Speed the prediction is for (rpm).
    orders : tuple of MechOrder
        Mechanical orders 1..3 (empty when not fitted).
    min_score : float or None
        The least predicted cosine the switch requires (``SWITCH_MIN_SCORE``); None in a result
        file written before it was recorded.
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
    min_score: float | None = None

    @property
    def enabled(self) -> bool:
        return self.status == MECH_OK

    def to_json(self) -> dict[str, Any]:
        return {
            "status": self.status, "reasons": list(self.reasons), "dirs": self.dirs, "grid_phase": self.grid_phase,
            "margin": {"predicted": self.margin, "score": self.score, "threshold": self.threshold, "ref_rpm": self.ref_rpm,
                       **({} if self.min_score is None else {"min_score": self.min_score})},
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
        if status not in (MECH_OK, MECH_OFF):
            raise r.error("status", f"{status!r} is not {MECH_OK!r} or {MECH_OFF!r}")
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
        orders: list[MechOrder] = []
        for i, o in enumerate(r.list(obj, "orders")):
            osub = _Reader(source, f"{where}orders[{i}].")
            oo = r.obj(o, f"orders[{i}]")
            order = osub.integer(oo, "order")
            if order not in ORDERS or order in (o.order for o in orders):
                raise osub.error("order", f"{order}: the block carries mechanical orders {ORDERS}, each once")
            orders.append(MechOrder(order, osub.value_ci(oo, "c", (0.0, C6_MAX)),
                                    osub.value_ci(oo, "phase_c", (-PHASE_MAX, PHASE_MAX)),
                                    osub.string(oo, "no_interval") if "no_interval" in oo else None))
        return cls(status=status, reasons=tuple(r.string_list(obj, "reasons")), fingerprint=fps, sigma=sgs, dirs=dirs,
                   grid_phase=r.number(obj, "grid_phase", (0.0, 2 * math.pi)), windows=tuple(windows),
                   score=sub.number(m, "score", (-1.5, 1.5)), margin=sub.number(m, "predicted", (-3.0, 3.0)),
                   threshold=sub.number(m, "threshold", (0.0, 2.0)), ref_rpm=sub.number(m, "ref_rpm", (0.0, 1e5)),
                   orders=tuple(orders),
                   min_score=sub.number(m, "min_score", (0.0, 1.0)) if "min_score" in m else None)


def _num(r: _Reader, v: Any, field: str, bound: float, lo: float | None = None) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise r.error(field, f"expected a finite number, got {v!r}")
    low = -bound if lo is None else lo
    if not low <= v <= bound:
        raise r.error(field, f"{v!r} outside [{low:g}, {bound:g}]")
    return float(v)


def _kind(value: Any) -> str:
    return {bool: "a boolean", str: "a string", type(None): "null", list: "a list", dict: "an object"}.get(
        type(value), type(value).__name__)
