"""From captures to the fit's segments: angle, segmentation, grouping by serial.

Segments (documented in ``docs/fit.md``): a capture is split where the direction of rotation
changes, then into runs of whole electrical revolutions at a steady speed and a steady i_qo
(:func:`eol_cal.analysis.steady.steady_runs`, the same rule the p-p metric uses); the first
``settle_s`` of every run is dropped (current and speed transients after a step). Each run of at
least ``min_revs`` revolutions is one segment: one load point x speed x direction.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from collections.abc import Sequence

import numpy as np

from eol_cal.analysis.angle import capture_angle
from eol_cal.analysis.firmware_angle import FrameJob, StartedFrameParts, firmware_frame_parts, frame_total
from eol_cal.analysis.fit import SteadySegments
from eol_cal.analysis.fit.fp_angle import frame_sd, measure_fingerprint
from eol_cal.analysis.fit.motor_input import MotorInput, SteadySegmentOrigin
from eol_cal.analysis.halls import measure_hall_angles, nominal_hall_angles
from eol_cal.analysis.steady import IQ_TOL_A, IQ_TOL_REL, STANDSTILL_RAD_S, direction_pieces, revolution_bounds, steady_runs
from eol_cal.capture.data import Capture
from eol_cal.errors import InputError
from eol_cal.domain.bench_mechanics import BenchMechanics, shaft_response, torsion_response
from eol_cal.domain.motor_params import MotorParams, load_motor

if TYPE_CHECKING:
    from eol_cal.analysis.angle import AngleResult


@dataclass(frozen=True)
class SteadyRun:
    """One steady run of a capture (one load point, speed and direction) and what settling leaves.

    ``start``, ``stop``: the sample range of the revolutions kept after settling (empty when none
    is); ``kept``: how many whole electrical revolutions that is; ``revs``: the run's revolutions
    before settling; ``rev_s``: one revolution's duration (s)."""

    start: int
    stop: int
    kept: int
    revs: int
    rev_s: float


def steady_runs_of(
    t: np.ndarray,
    theta_r: np.ndarray,
    omega_r: np.ndarray,
    i_qo: np.ndarray,
    *,
    settle_s: float = 0.1,
    speed_tol: float = 0.02,
    iq_tol_a: float = IQ_TOL_A,
    iq_tol_rel: float = IQ_TOL_REL,
) -> list[SteadyRun]:
    """Every steady run of whole electrical revolutions, with the revolutions settling leaves
    (arguments as :func:`capture_segments`)."""
    out: list[SteadyRun] = []
    for a, b in direction_pieces(omega_r):
        bounds = revolution_bounds(theta_r[a:b])
        if len(bounds) < 2:
            continue
        tt = t[a:b]
        for run in steady_runs(tt, bounds, i_qo[a:b], speed_tol, iq_tol_a, iq_tol_rel):
            t0 = tt[bounds[run[0]]]
            kept = [k for k in run if tt[bounds[k]] - t0 >= settle_s - 1e-12]
            rev_s = float(tt[bounds[run[-1] + 1]] - t0) / len(run)
            lo, hi = (a + int(bounds[kept[0]]), a + int(bounds[kept[-1] + 1])) if kept else (a, a)
            out.append(SteadyRun(lo, hi, len(kept), len(run), rev_s))
    return out


def capture_segments(
    t: np.ndarray,
    theta_r: np.ndarray,
    omega_r: np.ndarray,
    i_qo: np.ndarray,
    *,
    settle_s: float = 0.1,
    min_revs: int = 1,
    speed_tol: float = 0.02,
    iq_tol_a: float = IQ_TOL_A,
    iq_tol_rel: float = IQ_TOL_REL,
) -> list[tuple[int, int]]:
    """Sample ranges of one load point x speed x direction each, whole electrical revolutions.

    Parameters
    ----------
    t : ndarray
        Sample times (s).
    theta_r : ndarray
        Unwrapped electrical angle (rad).
    omega_r : ndarray
        Electrical speed (rad/s), for the direction.
    i_qo : ndarray
        Nominal q current per sample (A).
    settle_s : float
        Dropped at the start of every steady run (s).
    min_revs : int
        Fewest electrical revolutions a segment must keep.
    speed_tol, iq_tol_a, iq_tol_rel
        Steadiness tolerances, as in :func:`eol_cal.analysis.steady.steady_runs`.

    Returns
    -------
    list of (start, stop)
        Half-open sample ranges.
    """
    runs = steady_runs_of(t, theta_r, omega_r, i_qo, settle_s=settle_s, speed_tol=speed_tol, iq_tol_a=iq_tol_a,
                          iq_tol_rel=iq_tol_rel)
    return [(r.start, r.stop) for r in runs if r.kept >= max(min_revs, 1)]


def left_out_reason(t: np.ndarray, theta_r: np.ndarray, omega_r: np.ndarray, i_qo: np.ndarray, pole_pairs: int, *,
                    settle_s: float = 0.1, min_revs: int = 1) -> str:
    """Why a capture gives the fit no segment (:func:`capture_segments` found none), in words
    that name its real cause: no rotation, no steady run, or too short for settling plus
    ``min_revs`` whole electrical revolutions at its speed."""
    runs = steady_runs_of(t, theta_r, omega_r, i_qo, settle_s=settle_s)
    if not direction_pieces(omega_r):
        return f"the shaft does not turn (electrical speed below {STANDSTILL_RAD_S:g} rad/s throughout)"
    if not runs:
        span = float(abs(theta_r[-1] - theta_r[0])) / (2 * math.pi)
        what = "too short: less than" if span < 1.0 else "no steady run:"
        return (f"{what} one whole electrical revolution at constant speed, direction and iq_ref "
                f"({span:.2f} revolutions in {float(t[-1] - t[0]):.3g} s)")
    best = max(runs, key=lambda r: (r.kept, r.revs))
    rpm = 60.0 / (best.rev_s * pole_pairs)
    return (f"too short: its longest steady run ({rpm:.4g} rpm) holds {best.revs} whole electrical revolution(s) of "
            f"{best.rev_s:.3g} s, {best.kept} after the {settle_s:g} s settling, fewer than the {min_revs} a segment "
            f"needs (capture at least {settle_s + (min_revs + 1) * best.rev_s:.3g} s at this speed)")


def window_metrics(capture: Capture, angle: AngleResult) -> dict[str, Any]:
    """p-p ripple of one window (``metrics.captures[i]`` of a record); ``error`` when it has none."""
    from eol_cal.analysis.metrics import capture_ripple_pp
    from eol_cal.errors import InputError

    try:
        pp = capture_ripple_pp(capture, angle)
    except InputError as exc:
        return {"source": capture.source, "error": exc.reason}
    return {
        "source": capture.source,
        "pp_raw_pct": pp.raw_pct,
        "pp_filtered_pct": pp.filtered_pct,
        "pp_filtered_nm": pp.filtered_pp_nm,
        "T_avg_nm": pp.T_avg_nm,
        "speed_rpm": pp.speed_rpm,
    }


class PreparedWindows:
    """Where the fit's per-window figures come from: plain calls here. The station's subclass
    (:class:`eol_cal.station.early.EarlyWindows`) hands in what it computed while the windows
    arrived, for exactly the inputs it was computed from, and computes anything else here."""

    def angle_of(self, capture: Capture) -> AngleResult:
        """A window's angle (:func:`capture_angle`)."""
        return capture_angle(capture)

    def frame_parts(self, jobs: Sequence[FrameJob]) -> list[list[tuple[complex, int]]]:
        """The windows' parts of the firmware frame offset, per segment range (:func:`firmware_frame_parts`)."""
        return firmware_frame_parts(jobs)

    def metrics_of(self, capture: Capture, angle: AngleResult) -> dict:
        """A window's p-p figures (:func:`window_metrics`)."""
        return window_metrics(capture, angle)


def _kt_of(captures: list[Capture], motor: MotorParams) -> tuple[float, str]:
    values = {float(c.metadata["kt"]) for c in captures if "kt" in c.metadata}
    if len(values) > 1:
        raise InputError(", ".join(c.source for c in captures), "kt", f"captures of one motor disagree: {sorted(values)}")
    if values:
        return values.pop(), "metadata"
    return motor.kt, f"preset {motor.name}"


def motor_inputs(
    captures: list[Capture],
    motor: MotorParams | None = None,
    settle_s: float = 0.1,
    min_revs: int = 1,
    frame: str = "firmware",
    mechanics: BenchMechanics | None = None,
    hall_angle: str = "measured",
    estimator_options: int = 0,
    prepared: PreparedWindows | None = None,
) -> list[MotorInput]:
    """Split captures into windows, group them by serial, reconstruct the angle, cut segments.

    Parameters
    ----------
    captures : list of Capture
        Any number of motors, any number of captures each. A joined capture (a dyno capture:
        ``segment_starts``, or gaps in ``t``) is split into its windows first
        (:func:`eol_cal.capture.windows.split_windows`): no angle is reconstructed across a join.
    motor : MotorParams, optional
        Fallback for kt when the captures carry no ``kt`` metadata, and the rotor inertia and
        friction of the bench's shaft response (default: the paper preset).
    settle_s : float
        Settling time dropped after each step (s).
    min_revs : int
        Fewest electrical revolutions per segment.
    frame : {"firmware", "offline"}
        ``firmware``: measure where the firmware estimator's angle frame sits against the offline
        angle (:func:`firmware_frame_offset`), so that phases can be given in the frame the ECU
        evaluates its table in; captures without ``enc_b`` fall back to ``offline`` (the hall
        frame of :mod:`eol_cal.analysis.angle`).
    mechanics : BenchMechanics, optional
        The dyno bench the captures come from; the fit then divides its shaft response
        (:func:`eol_cal.domain.bench_mechanics.shaft_response`) out of the measured ripple. ``None``: rigid coupling.
    hall_angle : {"measured", "nominal"}
        The hall table the block will carry (:mod:`eol_cal.analysis.halls`): ``measured`` from
        the motor's own transitions (nominal, with the reason, when they do not suffice). The
        firmware frame is measured with that table, so the phases match the block.
    estimator_options : int
        The estimator options (contract flags bits 2-5) the ECU ran during the captures: the
        firmware frame is measured with that estimator (0: the paper's).
    prepared : PreparedWindows, optional
        Where each window's angle and firmware frame offset come from (default: computed here);
        the station hands in what it computed while the dyno was still turning
        (:mod:`eol_cal.station.early`).

    Returns
    -------
    list of MotorInput
        In order of first appearance of each serial; ``captures`` and ``angles`` are per window.
    """
    if frame not in ("firmware", "offline"):
        raise InputError(None, "frame", f"unknown value {frame!r}; known: firmware, offline")
    inputs = segment_motors(captures, motor, settle_s=settle_s, min_revs=min_revs, hall_angle=hall_angle,
                            mechanics=mechanics, prepared=prepared)
    if frame == "firmware":
        measure_firmware_frames(inputs, [estimator_options] * len(inputs), prepared)
    return inputs


def segment_motors(
    captures: list[Capture],
    motor: MotorParams | None = None,
    settle_s: float = 0.1,
    min_revs: int = 1,
    hall_angle: str = "measured",
    mechanics: BenchMechanics | None = None,
    prepared: PreparedWindows | None = None,
) -> list[MotorInput]:
    """:func:`motor_inputs` up to the firmware frame: every motor's inputs in the offline frame,
    for :func:`measure_firmware_frames` (which measures the frames of many motors in one batch)."""
    from eol_cal.capture.windows import split_windows

    if hall_angle not in ("measured", "nominal"):
        raise InputError(None, "hall_angle", f"unknown value {hall_angle!r}; known: measured, nominal")
    prepared = prepared or PreparedWindows()
    captures = [w for c in captures for w in split_windows(c)]

    motor = motor or load_motor("paper")
    groups: dict[str, list[Capture]] = {}
    for c in captures:
        if "serial" not in c.metadata:
            raise InputError(c.source, "serial", "missing metadata: captures are grouped by serial")
        groups.setdefault(c.serial, []).append(c)
    return [_segment_motor(serial, caps, motor, settle_s, min_revs, hall_angle, mechanics, prepared)
            for serial, caps in groups.items()]


def _segment_motor(serial: str, caps: list[Capture], motor: MotorParams, settle_s: float, min_revs: int,
                   hall_angle: str, mechanics: BenchMechanics | None, prepared: PreparedWindows) -> MotorInput:
    poles = {c.poles for c in caps}
    ppr = {c.encoder_ppr for c in caps}
    if len(poles) > 1 or len(ppr) > 1:
        raise InputError(", ".join(c.source for c in caps), "poles", f"captures of {serial} disagree on poles/encoder_ppr")
    P = poles.pop()
    thetas, ts, ys, iqs, omegas, labels, infos, cap_idx, angles = [], [], [], [], [], [], [], [], []
    left_out: list[tuple[str, str]] = []
    used: list[Capture] = []
    for c in caps:
        if not c.has("torque"):
            raise InputError(c.source, "torque", "missing channel, needed for the fit")
        if "iq_ref" not in c.channels and "iq_ref" not in c.metadata:
            raise InputError(c.source, "iq_ref", "missing channel or metadata, needed for the fit (the load point)")
        try:
            ang = prepared.angle_of(c)
        except InputError as exc:  # its angle cannot be reconstructed (too short, no hall state seen...)
            left_out.append((c.source, f"no angle: {exc.reason}"))
            continue
        ci = len(used)
        used.append(c)
        angles.append(ang)
        i_qo = np.asarray(c.iq_ref(), dtype=float)
        ranges = capture_segments(c.t, ang.theta_r, ang.omega_r, i_qo, settle_s=settle_s, min_revs=min_revs)
        if not ranges:
            left_out.append((c.source, left_out_reason(c.t, ang.theta_r, ang.omega_r, i_qo, P // 2, settle_s=settle_s,
                                                       min_revs=min_revs)))
        for a, b in ranges:
            th = ang.theta_r[a:b]
            tt = c.t[a:b]
            omega = float(th[-1] - th[0]) / float(tt[-1] - tt[0])
            thetas.append(th)
            ts.append(tt)
            ys.append(np.asarray(c["torque"][a:b], dtype=float))
            iqs.append(float(i_qo[a:b].mean()))
            omegas.append(omega)
            rpm = omega / (P / 2) * 60.0 / (2 * math.pi)
            labels.append(f"{c.source}[{a}:{b}]")
            infos.append(SteadySegmentOrigin(c.source, a, b, float(tt[0]), float(tt[-1]), iqs[-1], rpm))
            cap_idx.append(ci)
    if not thetas:
        raise InputError(
            ", ".join(c.source for c in caps),
            "segments",
            f"motor {serial}: no steady segment of at least {min_revs} electrical revolution(s) after "
            f"{settle_s} s settling (constant speed, direction and iq_ref): "
            + "; ".join(f"{src}: {why}" for src, why in left_out),
        )
    caps = used
    if hall_angle == "measured":
        hall = measure_hall_angles([a.hall_begins for a in angles], [a.hall_theta for a in angles])
    else:
        hall = nominal_hall_angles("asked for")
    kt, kt_source = _kt_of(caps, motor)
    kt_iq, current = current_torque(caps, infos, cap_idx, kt)
    response = None if mechanics is None else bench_path(motor, mechanics, current_known=kt_iq is not None)
    seg = SteadySegments(thetas, ts, ys, np.array(iqs), np.array(omegas), P // 2, labels, response, kt_iq)
    return MotorInput(serial, caps, angles, seg, infos, P, ppr.pop(), kt, kt_source, cap_idx, mechanics=mechanics,
                      hall=hall, left_out=left_out, current_ripple=current)


def bench_path(motor: MotorParams, mechanics: BenchMechanics, current_known: bool) -> functools.partial:
    """The torque path the fit divides out (``SteadySegments.path_response``).

    With the current known (``kt * i_q`` measured, :func:`current_torque`) the air-gap torque
    already holds the current loop's reaction to the speed ripple: the path is the shaft line
    alone (:func:`eol_cal.domain.bench_mechanics.torsion_response`). Without it that reaction is modelled on top
    (:func:`eol_cal.domain.bench_mechanics.shaft_response`); taking both would count it twice (k6 +0.12 % on
    the paper bench, noise-free plant motors).
    """
    if current_known:
        return functools.partial(torsion_response, J=motor.J, B=motor.B, mechanics=mechanics)
    return functools.partial(shaft_response, motor=motor, mechanics=mechanics)


def current_torque(caps: list[Capture], infos: list[SteadySegmentOrigin], cap_idx: list[int],
                   kt: float) -> tuple[list[np.ndarray] | None, str]:
    """Per segment ``kt * i_q`` (N*m) from the captures' ``iq`` channel (the ECU's measured q
    current), and how the fit uses it (:attr:`eol_cal.analysis.fit.SteadySegments.kt_iq`).

    The current loop leaves a 6th-order ripple of its own in ``i_q`` (its angle estimate's errors,
    the back-EMF's reaction to the speed ripple): torque on the shaft that no fit of the torque
    alone can tell from the motor's k6. Known from the current, it is taken out and k6 is the
    motor's own. Without an ``iq`` channel in every capture the fit falls back to the torque
    alone, and says so (the string, the result's ``model.current_ripple``).
    """
    missing = [c.source for c in caps if not c.has("iq")]
    if missing:
        return None, (f"fitted as the motor's: no iq channel in {', '.join(missing)} (the ECU's own current ripple "
                      "is in c6/k6; acquire the iq channel to take it out)")
    kt_iq = [kt * np.asarray(caps[ci]["iq"][o.start:o.stop], dtype=float) for o, ci in zip(infos, cap_idx, strict=True)]
    return kt_iq, "taken out: kt * iq known from the iq channel (c6/k6 are the motor's own)"


def frame_jobs(inputs: Sequence[MotorInput], estimator_options: Sequence[int]
               ) -> tuple[list[FrameJob], list[tuple[int, int]]]:
    """The firmware frame's estimator jobs of every motor's captures (:data:`FrameJob`: each
    capture with a segment) and, per job, ``(motor, capture)`` it belongs to; a motor whose
    captures lack ``enc_b`` has none."""
    jobs: list[FrameJob] = []
    owner: list[tuple[int, int]] = []
    for k, (mi, options) in enumerate(zip(inputs, estimator_options, strict=True)):
        if not all(c.has("enc_b") for c in mi.captures):
            continue
        for ci, (c, ang) in enumerate(zip(mi.captures, mi.angles, strict=True)):
            ranges = [(o.start, o.stop) for o, j in zip(mi.info, mi.capture_of_segment, strict=True) if j == ci]
            if ranges:
                # _segment_motor, the only maker of a MotorInput, always sets its hall table
                assert mi.hall is not None
                jobs.append((c, ang.theta_r, ranges, mi.hall.hall_angle, options))
                owner.append((k, ci))
    return jobs, owner


class StartedFrames(PreparedWindows):
    """Windows whose firmware frame parts were started ahead (:func:`start_firmware_frames`):
    :func:`measure_firmware_frames` of the same inputs takes them, and computes any other jobs."""

    def __init__(self, started: StartedFrameParts) -> None:
        self.started = started

    def frame_parts(self, jobs: Sequence[FrameJob]) -> list[list[tuple[complex, int]]]:
        ahead = self.started.jobs
        same = len(jobs) == len(ahead) and all(
            a[0] is b[0] and a[1] is b[1] and a[3] is b[3] and list(a[2]) == list(b[2]) and a[4] == b[4]
            for a, b in zip(jobs, ahead, strict=True))
        return self.started.result() if same else super().frame_parts(jobs)


def start_firmware_frames(inputs: list[MotorInput], estimator_options: list[int]) -> StartedFrames:
    """The estimator runs of :func:`measure_firmware_frames` for ``inputs`` dispatched now (JAX
    computes them on its own thread); pass the result as its ``prepared`` to wait for them."""
    return StartedFrames(StartedFrameParts(frame_jobs(inputs, estimator_options)[0]))


def measure_firmware_frames(inputs: list[MotorInput], estimator_options: list[int],
                            prepared: PreparedWindows | None = None) -> None:
    """Measure every motor's firmware frame (:func:`firmware_frame_offsets`, all captures of all
    motors in one batched estimator run) and set ``frame``, ``frame_offset_rad`` and
    ``frame_options`` of each ``MotorInput`` in place.

    ``estimator_options``: per motor, the options (contract flags bits 2-5) its ECU ran. A motor
    whose captures lack ``enc_b``, or whose estimator never anchored on a segment sample, keeps
    the offline frame (and says why). ``prepared``: where the captures' parts come from (default
    computed here). Then each motor's fingerprint is measured and its segments' angle corrected
    by it (:func:`eol_cal.analysis.fit.fp_angle.measure_fingerprint`).
    """
    prepared = prepared or PreparedWindows()
    jobs, owner = frame_jobs(inputs, estimator_options)
    parts = prepared.frame_parts(jobs)
    for k, (mi, options) in enumerate(zip(inputs, estimator_options, strict=True)):
        fw_sum, fw_n = 0j, 0
        mi.frame_parts = [None] * len(mi.captures)
        mi.frame_segment_parts = [None] * len(mi.captures)
        for got, (o, ci) in zip(parts, owner, strict=True):
            if o == k:
                s_, n_ = frame_total(got)
                fw_sum, fw_n = fw_sum + s_, fw_n + n_
                mi.frame_parts[ci] = (s_, n_)
                mi.frame_segment_parts[ci] = got
        if fw_n:
            mi.frame, mi.frame_offset_rad = "firmware", float(np.angle(fw_sum))
            mi.frame_options = options
        else:
            mi.frame = "offline (firmware frame needs enc_b and an anchored estimator)"
        measure_fingerprint(mi)
        if mi.frame == "firmware":
            mi.frame_sd_rad = frame_sd(mi)
