"""Offline reconstruction of the electrical rotor angle theta_r from encoder edges and halls.

The whole record is known, so the angle is interpolated between encoder edges (non-causal),
unlike the firmware's estimator (seed eqs. 13-16) that extrapolates from the last edge.

Frame (see ``docs/angle-frame.md``): theta_r = 0 rad electrical where hall U rises in forward
rotation, i.e. where hall state 5 begins; forward rotation steps the halls 5, 1, 3, 2, 6, 4
and channel A leads channel B (firmware contract, section 2, hall convention). The returned
angle is unwrapped (continuous); take :func:`eol_cal.wrap.wrap_2pi` of it for the wrapped angle.

Steps
-----
1. Edges of A and B (rising and falling): exact times from ``Capture.events`` when present,
   else the midpoint between the two samples that straddle the level change.
2. Quadrature decoding gives a signed quarter-pitch count; an edge sits on the boundary
   between two count cells, at relative angle ``boundary * delta`` with
   ``delta = (P/2) * 2*pi / (4*N_enc)`` rad electrical. With channel A only, the edges are
   half a pitch apart and the direction comes from the hall sequence.
3. PCHIP (monotone cubic) of edge angle against edge time gives the relative angle at
   every sample; outside the first/last edge it is extrapolated at the end speed and kept
   inside the encoder cell the levels show.
4. The grid offset theta_0 (absolute angle of relative angle 0) is the least-squares
   (circular mean) fit of every hall transition's nominal angle against the relative angle
   at the transition's time.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Sequence

import numpy as np

from eol_cal.capture.model import Capture
from eol_cal.errors import InputError
from eol_cal.firmware.estimator import NOMINAL_HALL_ANGLE
from eol_cal.wrap import wrap_2pi, wrap_pi

if TYPE_CHECKING:
    from eol_cal.firmware.estimator import EstimatorConfig

TWO_PI = 2.0 * np.pi

#: Forward hall sequence (contract section 2): state 5 begins at 0 deg, 1 at 60 deg, ...
HALL_FORWARD_SEQUENCE: tuple[int, ...] = (5, 1, 3, 2, 6, 4)

#: Nominal electrical angle (rad) at which hall state s begins in forward rotation, index s-1
#: (the contract's nominal ``hall_angle``, defined once in the firmware reference).
NOMINAL_HALL_ANGLES: tuple[float, ...] = NOMINAL_HALL_ANGLE

# Gray-code position of the quadrature state (a, b) in forward rotation: 00 -> 10 -> 11 -> 01.
_QUAD_POS = {(0, 0): 0, (1, 0): 1, (1, 1): 2, (0, 1): 3}


@dataclass(frozen=True, eq=False)
class AngleResult:
    """Reconstructed electrical angle of a capture and the figures that qualify it.

    Attributes
    ----------
    theta_r : ndarray
        Electrical angle at every sample (rad), unwrapped, in the hall frame
        (0 where hall U rises in forward rotation).
    omega_r : ndarray
        Electrical angular speed at every sample (rad/s), derivative of the interpolant.
    t_edges : ndarray
        Encoder edge times used (s).
    theta_edges : ndarray
        Absolute electrical angle of each edge (rad), same frame as ``theta_r``.
    edge_step_rad : float
        Electrical angle between adjacent edges used (rad): ``pi*P/(4*N_enc)`` with A and B,
        twice that with A only.
    n_edges : int
        Number of encoder edges used.
    n_hall_edges : int
        Number of hall transitions in the offset fit (glitches that skip a state are left out).
    offset_rad : float
        Grid offset theta_0 (rad), wrapped to (-pi, pi]: absolute angle of the first edge cell's
        lower boundary, i.e. ``theta_r = theta_0 + boundary * edge_step_rad`` at each edge.
    hall_residual_rms_rad, hall_residual_max_rad : float
        RMS and max |nominal hall angle - reconstructed angle| over the hall transitions (rad).
    direction : int
        +1 forward, -1 reverse, 0 both directions occur.
    speed_rpm : float
        Mean mechanical speed over the edge span (rpm), signed.
    t_span : tuple[float, float]
        First and last edge time (s); outside, the angle is extrapolated.
    hall_begins : ndarray of int
        Per hall transition in the offset fit that lies within the encoder edges' span: the
        boundary crossed, named by the state that begins there in forward rotation (1..6).
    hall_theta : ndarray
        Reconstructed angle at those transitions (rad, [0, 2*pi)): where each boundary sits in
        this frame (:mod:`eol_cal.analysis.halls`).
    """

    theta_r: np.ndarray
    omega_r: np.ndarray
    t_edges: np.ndarray
    theta_edges: np.ndarray
    edge_step_rad: float
    n_edges: int
    n_hall_edges: int
    offset_rad: float
    hall_residual_rms_rad: float
    hall_residual_max_rad: float
    direction: int
    speed_rpm: float
    t_span: tuple[float, float]
    hall_begins: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    hall_theta: np.ndarray = field(default_factory=lambda: np.zeros(0))


def level_changes(
    t: np.ndarray, levels: np.ndarray, events: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Times and new levels of every change of a digital channel.

    Parameters
    ----------
    t : ndarray
        Sample times (s).
    levels : ndarray
        Channel levels at ``t``.
    events : (ndarray, ndarray), optional
        Exact change events (times (s), new levels). When given they are used instead of the
        samples; entries that repeat the previous level are dropped.

    Returns
    -------
    times : ndarray
        Change times (s); from samples, the midpoint of the two straddling samples (the
        unbiased estimate of a change that is uniformly distributed between them).
    new_levels : ndarray of int
        Level after each change.
    """
    levels = np.asarray(levels).astype(np.int64)
    if events is not None:
        ev_t = np.asarray(events[0], dtype=float)
        ev_v = np.asarray(events[1]).astype(np.int64)
        order = np.argsort(ev_t, kind="stable")
        ev_t, ev_v = ev_t[order], ev_v[order]
        previous = np.concatenate(([levels[0]], ev_v[:-1]))
        keep = ev_v != previous
        return ev_t[keep], ev_v[keep]
    idx = np.flatnonzero(levels[1:] != levels[:-1]) + 1
    return 0.5 * (t[idx - 1] + t[idx]), levels[idx]


def hall_transition_angles(
    old_states: np.ndarray, new_states: np.ndarray, hall_angles: Sequence[float] = NOMINAL_HALL_ANGLES
) -> tuple[np.ndarray, np.ndarray]:
    """Electrical angle and direction of hall transitions.

    Parameters
    ----------
    old_states, new_states : ndarray of int
        Hall state (1..6) before and after each transition.
    hall_angles : sequence of 6 float
        Angle (rad) at which state s begins in forward rotation, index s-1.

    Returns
    -------
    angle : ndarray
        Electrical angle of the boundary crossed (rad); NaN where the transition skips states.
    direction : ndarray of int
        +1 forward, -1 reverse, 0 a skipped state (glitch).
    """
    pos = np.full(8, -1)
    for i, s in enumerate(HALL_FORWARD_SEQUENCE):
        pos[s] = i
    step = np.mod(pos[new_states] - pos[old_states], 6)
    direction = np.where(step == 1, 1, np.where(step == 5, -1, 0))
    angle = np.asarray(hall_angles, dtype=float)[boundary_state(old_states, new_states, direction) - 1]
    return np.where(direction != 0, angle, np.nan), direction


def boundary_state(old_states: np.ndarray, new_states: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The hall boundary each transition crosses, named by the state that begins there going forward.

    ``new_states`` for a forward transition, ``old_states`` for a reverse one (and for a glitch,
    direction 0, whichever: its angle is not used).
    """
    return np.where(direction >= 0, new_states, old_states)


def quadrature_boundaries(
    times_a: np.ndarray,
    levels_a: np.ndarray,
    times_b: np.ndarray,
    levels_b: np.ndarray,
    a0: int,
    b0: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Decode A/B edges into boundary indices on the quarter-pitch grid.

    Parameters
    ----------
    times_a, levels_a, times_b, levels_b : ndarray
        Change times (s) and new levels of channels A and B.
    a0, b0 : int
        Levels before the first change.

    Returns
    -------
    times : ndarray
        Edge times (s), sorted.
    boundary : ndarray of int
        Index of the cell boundary each edge crosses: the edge between counts c and c+1 is
        boundary c+1 in either direction, so its angle is ``boundary * delta``.
    """
    times = np.concatenate((times_a, times_b))
    chan = np.concatenate((np.zeros(len(times_a), int), np.ones(len(times_b), int)))
    lev = np.concatenate((levels_a, levels_b))
    order = np.lexsort((chan, times))
    times, chan, lev = times[order], chan[order], lev[order]
    a, b = int(a0), int(b0)
    count = 0
    # Direction of the last few steps: one glitch step must not decide an ambiguous double step.
    recent = [1]
    boundary = np.empty(len(times), dtype=np.int64)
    out_t = np.empty(len(times))
    n_out = 0
    i = 0
    n = len(times)
    while i < n:
        # Edges of A and B in the same instant (same sample) are a double step whose order
        # the samples cannot tell: apply them in the order the recent direction implies.
        j = i + 1
        if j < n and times[j] == times[i] and chan[j] != chan[i]:
            group = [i, j]
            i_next = j + 1
        else:
            group = [i]
            i_next = j
        if len(group) == 2:
            q_old = _QUAD_POS[(a, b)]
            na, nb = a, b
            for g in group:
                if chan[g] == 0:
                    na = int(lev[g])
                else:
                    nb = int(lev[g])
            step = (_QUAD_POS[(na, nb)] - q_old) % 4
            trend = 1 if sum(recent) >= 0 else -1
            d = trend if step == 2 else (1 if step == 1 else -1 if step == 3 else 0)
            first = [g for g in group if (chan[g] == 0) == ((d > 0) == (a == b))]
            group = first + [g for g in group if g not in first]
        for g in group:
            q_old = _QUAD_POS[(a, b)]
            if chan[g] == 0:
                a = int(lev[g])
            else:
                b = int(lev[g])
            step = (_QUAD_POS[(a, b)] - q_old) % 4
            d = 1 if step == 1 else -1
            new = count + d
            # written in the order applied, so a double step's two edges come out in sequence
            out_t[n_out] = times[g]
            boundary[n_out] = max(count, new)
            n_out += 1
            count = new
            recent.append(d)
            if len(recent) > 8:
                recent.pop(0)
        i = i_next
    return out_t, boundary


def debounce_edges(times: np.ndarray, boundary: np.ndarray, bounce_frac: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Collapse chatter: consecutive edges on one boundary in quick succession.

    A run of consecutive edges on the same boundary, each within ``bounce_frac`` times the
    median edge interval of the next, is one crossing when the run is odd (chatter around a
    real edge: kept once, at the run's mean time) and none when it is even (a glitch pulse
    that returned to where it was: dropped). A real reversal inside a cell lasts far longer
    and is kept.

    Parameters
    ----------
    times : ndarray
        Edge times (s), sorted.
    boundary : ndarray of int
        Boundary index of each edge.
    bounce_frac : float
        Threshold as a fraction of the median edge interval; 0 disables.

    Returns
    -------
    times, boundary : ndarray
        The edges with chatter collapsed.
    """
    if bounce_frac <= 0 or len(times) < 3:
        return times, boundary
    gap = np.diff(times)
    limit = bounce_frac * float(np.median(gap))
    linked = (np.diff(boundary) == 0) & (gap < limit)
    if not linked.any():
        return times, boundary
    # run id: a new run starts wherever an edge is not linked to its predecessor
    run = np.concatenate(([0], np.cumsum(~linked)))
    counts = np.bincount(run)
    mean_t = np.bincount(run, weights=times) / counts
    first = np.concatenate(([True], ~linked))
    keep = first & (counts[run] % 2 == 1)
    return mean_t[run[keep]], boundary[keep]


def _direction_at(t_query: np.ndarray, t_hall: np.ndarray, dir_hall: np.ndarray) -> np.ndarray:
    """Direction (+1/-1) of the hall transition nearest before each query time (first one before)."""
    idx = np.clip(np.searchsorted(t_hall, t_query, side="right") - 1, 0, len(t_hall) - 1)
    return dir_hall[idx]


def reconstruct_angle(
    t: np.ndarray,
    enc_a: np.ndarray,
    hall: np.ndarray,
    poles: int,
    N_enc: int,
    enc_b: np.ndarray | None = None,
    events: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
    hall_angles: Sequence[float] = NOMINAL_HALL_ANGLES,
    source: str = "<memory>",
    bounce_frac: float = 0.2,
) -> AngleResult:
    """Electrical angle theta_r (rad) at every sample from encoder edges and hall transitions.

    Parameters
    ----------
    t : ndarray
        Sample times (s), increasing.
    enc_a : ndarray
        Encoder channel A levels (0/1).
    hall : ndarray
        Hall states (1..6; U = bit0, V = bit1, W = bit2).
    poles : int
        Number of poles P.
    N_enc : int
        Encoder pulses per mechanical revolution of channel A.
    enc_b : ndarray, optional
        Channel B levels (0/1); A leads B in forward rotation. Without it, the edges of A
        alone are used and the direction comes from the hall sequence.
    events : dict, optional
        Exact change events per channel (``Capture.events``), used where present.
    hall_angles : sequence of 6 float
        Angle (rad) at which hall state s begins in forward rotation, index s-1.
    source : str
        File name for error messages.
    bounce_frac : float
        Chatter on one boundary within this fraction of the median edge interval is collapsed
        (:func:`debounce_edges`); 0 keeps every edge.

    Returns
    -------
    AngleResult
    """
    from scipy.interpolate import PchipInterpolator

    t = np.asarray(t, dtype=float)
    events = events or {}
    hall = np.asarray(hall).astype(np.int64)
    bad = (hall < 1) | (hall > 6)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(source, "hall", f"invalid hall state {hall[i]} at t = {t[i]:.6g} s (valid: 1..6)")
    t_h, s_new = level_changes(t, hall, events.get("hall"))
    s_old = np.concatenate(([hall[0]], s_new[:-1]))
    if len(s_new) and ((s_new < 1) | (s_new > 6)).any():
        raise InputError(source, "hall", "invalid hall state (0 or 7) in the change events")
    hall_theta, hall_dir = hall_transition_angles(s_old, s_new, hall_angles)
    good = hall_dir != 0
    begins = boundary_state(s_old, s_new, hall_dir)[good]
    t_h, hall_theta, hall_dir = t_h[good], hall_theta[good], hall_dir[good]
    if len(t_h) < 2:
        raise InputError(source, "hall", "fewer than two hall transitions: no absolute angle reference")

    elec_per_mech = poles / 2.0
    ta, la = level_changes(t, enc_a, events.get("enc_a"))
    if len(ta) < 2:
        raise InputError(source, "enc_a", "encoder channel A never toggles")
    if enc_b is not None:
        tb, lb = level_changes(t, enc_b, events.get("enc_b"))
        if len(tb) < 1:
            raise InputError(source, "enc_b", "encoder channel B never toggles")
        t_e, boundary = quadrature_boundaries(ta, la, tb, lb, int(enc_a[0]), int(enc_b[0]))
        delta = elec_per_mech * TWO_PI / (4.0 * N_enc)
        # The quadrature direction must agree with the hall sequence, else B is swapped.
        enc_dir = np.sign(np.interp(t_h, t_e[1:], np.diff(boundary.astype(float)), left=0.0, right=0.0))
        judged = enc_dir != 0
        if judged.sum() >= 2 and np.mean(enc_dir[judged] == hall_dir[judged]) < 0.5:
            raise InputError(
                source, "enc_b",
                "quadrature direction contradicts the hall sequence (A and B swapped, or halls wired in another order)",
            )
    else:
        d = _direction_at(ta, t_h, hall_dir)
        count = np.concatenate(([0], np.cumsum(d)))
        boundary = np.maximum(count[:-1], count[1:])
        t_e = ta
        delta = elec_per_mech * TWO_PI / (2.0 * N_enc)

    t_e, boundary = debounce_edges(t_e, boundary, bounce_frac)
    if len(t_e) < 2:
        raise InputError(source, "enc_a", "fewer than two encoder edges after removing bounces")
    rel = boundary.astype(float) * delta
    # Two edges in one instant: keep one point at their mean angle so the knots stay unique.
    t_u, inv = np.unique(t_e, return_inverse=True)
    rel_u = np.bincount(inv, weights=rel) / np.bincount(inv)
    if len(t_u) < 2:
        raise InputError(source, "enc_a", "fewer than two distinct encoder edge times")
    interp = PchipInterpolator(t_u, rel_u, extrapolate=False)
    slope = interp.derivative()

    p = np.empty_like(t)
    w = np.empty_like(t)
    inside = (t >= t_u[0]) & (t <= t_u[-1])
    p[inside] = interp(t[inside])
    w[inside] = slope(t[inside])
    for mask, t_end, p_end in ((t < t_u[0], t_u[0], rel_u[0]), (t > t_u[-1], t_u[-1], rel_u[-1])):
        if mask.any():
            w_end = float(slope(t_end))
            raw = p_end + w_end * (t[mask] - t_end)
            # The levels say the rotor is still inside the cell next to the end edge.
            p[mask] = np.clip(raw, p_end - delta, p_end + delta)
            w[mask] = np.where(np.abs(raw - p_end) < delta, w_end, 0.0)

    # Hall transitions outside the edge span would be judged against an extrapolated angle.
    within = (t_h >= t_u[0]) & (t_h <= t_u[-1])
    if within.sum() >= 2:
        t_h, hall_theta, begins = t_h[within], hall_theta[within], begins[within]
    # the interpolant itself at the (possibly exact, event) hall times; the samples outside
    in_span = (t_h >= t_u[0]) & (t_h <= t_u[-1])
    rel_h = np.where(in_span, interp(np.clip(t_h, t_u[0], t_u[-1])), np.interp(t_h, t, p))
    theta0 = float(np.angle(np.mean(np.exp(1j * (hall_theta - rel_h)))))
    resid = wrap_pi(hall_theta - rel_h - theta0)
    theta0 = float(wrap_pi(theta0 + np.mean(resid)))
    resid = wrap_pi(hall_theta - rel_h - theta0)

    steps = np.diff(boundary)
    if np.all(steps >= 0):
        direction = 1
    elif np.all(steps <= 0):
        direction = -1
    else:
        direction = 0
    span = t_u[-1] - t_u[0]
    speed_rpm = float((rel_u[-1] - rel_u[0]) / span / elec_per_mech * 60.0 / TWO_PI) if span > 0 else 0.0

    return AngleResult(
        theta_r=p + theta0,
        omega_r=w,
        t_edges=t_e,
        theta_edges=rel + theta0,
        edge_step_rad=float(delta),
        n_edges=int(len(t_e)),
        n_hall_edges=int(len(t_h)),
        offset_rad=theta0,
        hall_residual_rms_rad=float(np.sqrt(np.mean(resid**2))),
        hall_residual_max_rad=float(np.max(np.abs(resid))),
        direction=direction,
        speed_rpm=speed_rpm,
        t_span=(float(t_u[0]), float(t_u[-1])),
        # only where the edges say the angle: an extrapolated one is up to a count off, which the
        # hall table measured from these (analysis.halls) must not average in
        hall_begins=begins[in_span].astype(np.int64),
        hall_theta=wrap_2pi(rel_h + theta0)[in_span],
    )


def capture_angle(capture: Capture, hall_angles: Sequence[float] = NOMINAL_HALL_ANGLES) -> AngleResult:
    """:func:`reconstruct_angle` on a :class:`~eol_cal.capture.model.Capture`.

    Parameters
    ----------
    capture : Capture
        Needs channels ``enc_a`` and ``hall`` (``enc_b`` used when present) and metadata
        ``poles`` and ``encoder_ppr``; one continuous window (a joined capture is refused:
        :func:`eol_cal.capture.windows.split_windows`).
    hall_angles : sequence of 6 float
        Angle (rad) at which hall state s begins in forward rotation, index s-1.
    """
    for name in ("enc_a", "hall"):
        if not capture.has(name):
            raise InputError(capture.source, name, "missing channel, needed for the angle")
    for key in ("poles", "encoder_ppr"):
        if key not in capture.metadata:
            raise InputError(capture.source, key, "missing metadata, needed for the angle")
    from eol_cal.capture.windows import window_spans

    n_windows = len(window_spans(capture))
    if n_windows > 1:
        # the encoder count is lost between two windows: one angle across a join is wrong there
        raise InputError(capture.source, "segment_starts" if "segment_starts" in capture.metadata else "t",
                         f"{n_windows} capture windows joined in one capture; reconstruct the angle per window "
                         "(eol_cal.capture.windows.split_windows)")
    return reconstruct_angle(
        capture.t,
        capture["enc_a"],
        capture["hall"],
        poles=capture.poles,
        N_enc=capture.encoder_ppr,
        enc_b=capture["enc_b"] if capture.has("enc_b") else None,
        events=capture.events,
        hall_angles=hall_angles,
        source=capture.source,
    )


@dataclass(frozen=True)
class FirmwareAngleDifference:
    """The firmware estimator's angle (what the ECU sees) against the offline angle.

    Attributes
    ----------
    mean_deg, rms_deg, max_deg : float
        Mean, RMS and max |.| of ``theta_hat - theta_r`` (electrical deg), wrapped, over the
        samples where the estimator is anchored, not at standstill and has a measured speed.
    raw_rms_deg, raw_max_deg : float
        RMS and max |.| of the firmware's raw edge angle ``theta_enc - theta_r`` (deg).
    phase6_shift_deg : float
        Shift of the 6th harmonic's phase that the mean difference causes, ``6 * mean`` (deg).
    n_ticks : int
        Samples judged.
    """

    mean_deg: float
    rms_deg: float
    max_deg: float
    raw_rms_deg: float
    raw_max_deg: float
    phase6_shift_deg: float
    n_ticks: int


def firmware_angle_difference(
    capture: Capture, angle: AngleResult | None = None, config: EstimatorConfig | None = None
) -> FirmwareAngleDifference:
    """Run the firmware's estimator over a capture and compare its angle with the offline one.

    Every sample is one estimator tick, so this is what the ECU sees when the capture was
    sampled at the ECU's tick rate (the PWM frequency, 20 kHz on the paper's bench).

    Parameters
    ----------
    capture : Capture
        Needs ``enc_a``, ``enc_b``, ``hall`` and metadata ``poles``, ``encoder_ppr``.
    angle : AngleResult, optional
        Offline angle; computed when not given.
    config : eol_cal.firmware.estimator.EstimatorConfig, optional
        Estimator configuration; default the paper's estimator at the capture's sample rate.

    Returns
    -------
    FirmwareAngleDifference
    """
    from eol_cal.firmware import estimator as est

    if not capture.has("enc_b"):
        raise InputError(capture.source, "enc_b", "missing channel, the firmware estimator needs it")
    if angle is None:
        angle = capture_angle(capture)
    if config is None:
        from eol_cal.analysis.fit.capture import firmware_config

        config = firmware_config(capture)
    out = est.run_jax_chunked(config, capture["enc_a"], capture["enc_b"], capture["hall"])
    status = np.asarray(out.status)
    judged = (status & (est.ST_NO_ANCHOR | est.ST_STANDSTILL | est.ST_NO_SPEED)) == 0
    judged &= (capture.t >= angle.t_span[0]) & (capture.t <= angle.t_span[1])
    if not judged.any():
        raise InputError(capture.source, "enc_a", "the firmware estimator never anchored on a moving rotor")
    d = np.rad2deg(wrap_pi(np.asarray(out.theta_hat, float)[judged] - angle.theta_r[judged]))
    raw = np.rad2deg(wrap_pi(np.asarray(out.theta_enc, float)[judged] - angle.theta_r[judged]))
    return FirmwareAngleDifference(
        mean_deg=float(d.mean()),
        rms_deg=float(np.sqrt(np.mean(d**2))),
        max_deg=float(np.max(np.abs(d))),
        raw_rms_deg=float(np.sqrt(np.mean(raw**2))),
        raw_max_deg=float(np.max(np.abs(raw))),
        phase6_shift_deg=float(6.0 * d.mean()),
        n_ticks=int(judged.sum()),
    )
