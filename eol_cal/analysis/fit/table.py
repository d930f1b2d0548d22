"""From a motor's fit result to the firmware's parameter block (contract section 2).

The tables come from :func:`eol_cal.firmware.compensator.make_tables`, the bytes from
:func:`eol_cal.firmware.block.pack`; this module only decides the block's other fields:

- ``flags`` = COMP_ENABLE | INTERP_ENABLE and the estimator options chosen (contract bits 2-5,
  :mod:`eol_cal.firmware.options`; default ``best``, all four); ``sequence`` = 1 (the flasher
  writes the real one);
- ``hall_angle`` the record's (measured per motor, or nominal): the table the fit measured the
  firmware frame of its phases with, so phases and anchoring agree;
- ``lead_s`` from :mod:`eol_cal.analysis.lead` at the fit's operating speed, or given;
- ``iqc_limit`` = 10 % of the largest |i_qo| the motor was calibrated at (65 A -> 6.5 A), unless
  given: a bound on what a wrong table could inject, well above the ~1-2 A the paper needed;
- ``calibrated_at`` = the result's ``created`` time;
- layout 2 (contract revision 1.2, the default): the result's fingerprint, frame and mechanical
  orders 1..3 (load-independent; the per-ampere part 0) with their tables, the identification
  thresholds, and ``MECH_COMP_ENABLE`` when the result's mechanical status is ``ok`` and the
  estimator options include ``EST_LEARN_PITCH_ERRORS`` (else off, the reason in
  :func:`mech_off_reasons`); ``layout=1`` writes the block of revision 1.1.
"""

from __future__ import annotations

import datetime as dt
import math
from typing import TYPE_CHECKING, Any

from eol_cal.errors import CheckFailed, InputError
from eol_cal.firmware.contract import DEFAULT_TABLE_LEN
from eol_cal.domain.motor_params import MotorParams

if TYPE_CHECKING:
    from eol_cal.analysis.motor_result import MotorResult, ValueCi
    from eol_cal.firmware.block import ParamBlock
    from eol_cal.firmware.mech_params import MechParams

IQC_LIMIT_FRACTION = 0.10


def select_motor(doc: dict[str, Any], serial: str | None, source: str) -> dict[str, Any]:
    """The motor record for ``serial`` (or the only one)."""
    motors = doc["motors"]
    if serial is None:
        if len(motors) != 1:
            raise InputError(source, "serial", f"{len(motors)} motors in the result: choose one by serial "
                             f"({', '.join(m['serial'] for m in motors)})")
        return motors[0]
    for m in motors:
        if m["serial"] == serial:
            return m
    raise InputError(source, "serial", f"{serial!r} not in the result ({', '.join(m['serial'] for m in motors)})")


def block_from_result(
    res: MotorResult,
    motor: MotorParams,
    *,
    table_len: int = DEFAULT_TABLE_LEN,
    lead_s: float | None = None,
    iqc_limit: float | None = None,
    calibrated_at: int | None = None,
    source: str = "<result>",
    options: int | None = None,
    layout: int = 2,
) -> ParamBlock:
    """A :class:`~eol_cal.firmware.block.ParamBlock` for one usable motor result.

    Parameters
    ----------
    res : MotorResult
        One motor of the fit result (``status`` must be ``"ok"``).
    motor : MotorParams
        Current-loop bandwidth and rates for the automatic lead; ``f_pwm`` becomes ``tick_hz``.
    table_len : int
        N, a power of two 16..1024.
    lead_s : float, optional
        Look-up lead (s); ``None`` = automatic at the result's operating speed.
    iqc_limit : float, optional
        Clamp of |i_qc| (A); ``None`` = 10 % of the largest |i_qo| of the result's segments.
    calibrated_at : int, optional
        Unix time (s); default now.
    source : str
        Result file, for errors.
    options : int, optional
        Estimator option bits (contract ``flags`` bits 2-5) the block carries; default the
        ``best`` choice (:data:`eol_cal.firmware.options.DEFAULT_PRESET`).
    layout : {2, 1}
        2: with the mechanical part of revision 1.2 (``MECH_COMP_ENABLE`` as :func:`mech_off_reasons`
        decides); 1: the block of revision 1.1.

    Raises
    ------
    CheckFailed
        The motor's fit is not usable (its ``status`` is not ``"ok"``).
    """
    from eol_cal.analysis.lead import auto_lead_s
    from eol_cal.firmware.block import FLAG_COMP_ENABLE, FLAG_INTERP_ENABLE, ParamBlock, serial_problem
    from eol_cal.firmware.compensator import make_tables

    serial = res.serial
    e = res.estimates
    if e is None or res.status != "ok":
        why = "; ".join(res.reasons) or "no reason recorded"
        raise CheckFailed(f"motor {serial}: fit status {res.status!r} ({why}); no table from an unusable fit")
    c6, phase_c6, k6, phase_k6 = e.c6.value, e.phase_c6.value, e.k6.value, e.phase_k6.value
    kt = float(res.kt)

    def part(est: ValueCi | None) -> float:
        return float(est.value) if est is not None else 0.0

    harmonics = [(h.order, part(h.c), part(h.phase_c), part(h.k), part(h.phase_k)) for h in e.harmonics]
    tc, tp = make_tables(c6, phase_c6, k6, phase_k6, kt, table_len, harmonics)
    hall_angle = _hall_angle(res, source)
    if lead_s is None:
        lead_s = auto_lead_s(res.operating_point.speed_rpm, motor)
    if iqc_limit is None:
        try:
            iqc_limit = IQC_LIMIT_FRACTION * max(abs(float(s["i_qo_a"])) for s in res.segments)
        except (KeyError, TypeError, ValueError):
            raise InputError(source, "segments", f"motor {serial!r}: every segment needs a number 'i_qo_a' (A)") from None
    if calibrated_at is None:
        calibrated_at = int(dt.datetime.now(dt.UTC).timestamp())
    problem = serial_problem(str(serial))
    if problem is not None:
        raise InputError(source, "serial", f"{serial!r}: {problem} (the block's serial field)")
    if layout not in (1, 2):
        raise InputError(source, "layout", f"{layout!r}: layout 1 or 2")
    flags = FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE | _options(options)
    mech = None
    if layout == 2:
        mech = mech_params(res, kt)
        if not mech_off_reasons(res, flags):
            from eol_cal.firmware.block import FLAG_MECH_COMP_ENABLE

            flags |= FLAG_MECH_COMP_ENABLE
    return ParamBlock(
        sequence=1,
        flags=flags,
        mech=mech,
        serial=str(serial),
        calibrated_at=int(calibrated_at),
        poles=int(res.poles),
        encoder_ppr=int(res.encoder_ppr),
        tick_hz=motor.f_pwm,
        kt=kt,
        hall_angle=hall_angle,
        c6=float(c6),
        phase_c6=float(phase_c6),
        k6=float(k6),
        phase_k6=float(phase_k6),
        lead_s=float(lead_s),
        iqc_limit=float(iqc_limit),
        table_const=tc,
        table_per_amp=tp,
    )


def mech_off_reasons(res: MotorResult, flags: int) -> list[str]:
    """Why a layout-2 block of this result leaves ``MECH_COMP_ENABLE`` off (empty: it may switch it on)."""
    from eol_cal.firmware.contract import FLAGS_MECH_NEEDS
    from eol_cal.firmware.block import flag_names

    if res.mech is None:
        return ["the fit result has no mechanical part (written before revision 1.2, or without a firmware frame)"]
    reasons = list(res.mech.reasons) if not res.mech.enabled else []
    if flags & FLAGS_MECH_NEEDS != FLAGS_MECH_NEEDS:
        reasons.append(f"the estimator options lack {flag_names(FLAGS_MECH_NEEDS & ~flags)}, which the "
                       "identification needs")
    return reasons


def mech_params(res: MotorResult, kt: float) -> MechParams:
    """The block's mechanical part from the result (an empty one without a mechanical result)."""
    import numpy as np

    from eol_cal.firmware.mech_params import ORDERS, make_mech_tables, unused_mech

    m = res.mech
    base = unused_mech(int(res.encoder_ppr))
    if m is None:
        return base
    c = [0.0] * len(ORDERS)
    ph = [0.0] * len(ORDERS)
    for o in m.orders:
        if o.order in ORDERS:
            c[o.order - 1], ph[o.order - 1] = float(o.c.value), float(o.phase_c.value)
    zeros = [0.0] * len(ORDERS)
    tc, tp = make_mech_tables(c, ph, zeros, zeros, kt)
    # id_margin and id_min_score stay the firmware's runtime thresholds (base's ID_MARGIN, ID_MIN_SCORE):
    # the result's threshold is end of line's switch on its prediction (SWITCH_MARGIN, 0), not the
    # margin the ECU must measure before it applies a frame
    return base.replace(fp_dirs=m.dirs, grid_phase=m.grid_phase, mech_c=tuple(c),
                        mech_phase_c=tuple(ph), mech_table_const=tc, mech_table_per_amp=tp,
                        fingerprint=np.asarray(m.fingerprint, dtype=np.float32))


def _options(options: int | None) -> int:
    """The option bits to write: ``options``, or the default choice's; bits outside 2-5 refused."""
    from eol_cal.firmware.options import DEFAULT_PRESET, PRESETS, options_label

    if options is None:
        return PRESETS[DEFAULT_PRESET]
    if options & ~PRESETS["best"]:
        raise InputError(None, "estimator", f"0x{options:x} has bits outside the estimator options "
                                            f"({options_label(PRESETS['best'])} = 0x{PRESETS['best']:02x})")
    return options


def uncompensated_block(serial: str, motor: MotorParams, calibrated_at: int | None = None,
                        options: int | None = None) -> ParamBlock:
    """The block a motor is measured under: the field's estimator, no compensation.

    ``flags`` = INTERP_ENABLE and the estimator options the calibrated block will carry
    (``options``, default the ``best`` choice), so the motor is measured under the estimator it
    will run; zero tables (N = 16), nominal ``hall_angle``, no lead, and
    ``iqc_limit`` 0: whatever the ECU ran before (no valid bank: the raw encoder angle; a motor
    being re-tested: its old compensation) the calibration capture then sees the motor's own
    ripple under the angle estimate the ECU will use in the field.

    Parameters
    ----------
    serial : str
        Motor serial (at most 16 ASCII characters).
    motor : MotorParams
        Motor type: poles, encoder PPR, tick rate (Hz) and kt (N*m/A) of the block.
    calibrated_at : int, optional
        Unix time (s, UTC); default now.
    options : int, optional
        Estimator option bits (contract ``flags`` bits 2-5); default the ``best`` choice.
    """
    import numpy as np

    from eol_cal.analysis.angle import NOMINAL_HALL_ANGLES
    from eol_cal.firmware.block import FLAG_INTERP_ENABLE, ParamBlock

    if calibrated_at is None:
        calibrated_at = int(dt.datetime.now(dt.UTC).timestamp())
    zeros = np.zeros(16, np.float32)
    return ParamBlock(
        sequence=1, flags=FLAG_INTERP_ENABLE | _options(options), serial=str(serial), calibrated_at=int(calibrated_at),
        poles=motor.poles, encoder_ppr=motor.N_enc, tick_hz=motor.f_pwm, kt=motor.kt,
        hall_angle=tuple(NOMINAL_HALL_ANGLES), c6=0.0, phase_c6=0.0, k6=0.0, phase_k6=0.0,
        lead_s=0.0, iqc_limit=0.0, table_const=zeros, table_per_amp=zeros.copy(),
    )


def _hall_angle(res: MotorResult, source: str) -> tuple[float, ...]:
    """The result's hall table (rad, 6 entries); nominal for results written before it existed."""
    from eol_cal.analysis.angle import NOMINAL_HALL_ANGLES

    entry = res.hall_angle
    if entry is None:
        return tuple(NOMINAL_HALL_ANGLES)
    try:
        values = tuple(float(v) for v in entry["value"])
    except (KeyError, TypeError, ValueError):
        raise InputError(source, "hall_angle", f"motor {res.serial!r}: 'value' must be 6 numbers (rad)") from None
    if len(values) != 6 or not all(math.isfinite(v) and 0.0 <= v < 2.0 * math.pi for v in values):
        raise InputError(source, "hall_angle", f"motor {res.serial!r}: needs 6 angles in [0, 2*pi) rad, got {values}")
    return values


def created_unix(doc: dict[str, Any], source: str | None = None) -> int | None:
    """The result's ``created`` time as Unix seconds (the block's ``calibrated_at``, u32), or None
    when absent.

    Raises
    ------
    InputError
        ``created`` is there but not an ISO 8601 instant with its UTC offset, or one a block
        cannot carry (before 1970 or after 2106): ``"yesterday"`` was taken as "now".
    """
    if doc.get("created") is None:
        return None
    text = doc["created"]
    try:
        when = dt.datetime.fromisoformat(text) if isinstance(text, str) else None
    except ValueError:
        when = None
    if when is None or when.utcoffset() is None:
        raise InputError(source, "created", f"{str(text)[:60]!r}: expected an ISO 8601 instant with its UTC offset "
                                            "(2026-11-24T00:23:36+00:00)")
    return unix_seconds(when, source, text)


def unix_seconds(when: dt.datetime, source: str | None = None, text: str | None = None) -> int:
    """An instant with its UTC offset (a fit's ``created``; ``text`` as a file wrote it) as a
    block's ``calibrated_at`` (Unix s, u32).

    Raises
    ------
    InputError
        The instant is before 1970 or after 2106 (``created`` of ``source`` named).
    """
    seconds = int(when.timestamp())
    if not 0 <= seconds < 2**32:
        raise InputError(source, "created", f"{text or when.isoformat()!r}: outside what a block's calibrated_at "
                                            "carries (1970 .. 2106)")
    return seconds
