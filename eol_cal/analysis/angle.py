"""Offline reconstruction of the electrical rotor angle theta_r from encoder edges and halls.

The whole record is known, so the angle is interpolated between encoder edges (non-causal),
unlike the firmware's estimator (seed eqs. 13-16) that extrapolates from the last edge.

Frame (see ``docs/angle-frame.md``): theta_r = 0 rad electrical where hall U rises in forward
rotation, i.e. where hall state 5 begins; forward rotation steps the halls 5, 1, 3, 2, 6, 4
and channel A leads channel B (firmware contract, section 2, hall convention). The returned
angle is unwrapped (continuous); take :func:`eol_cal.numerics.wrap.wrap_2pi` of it for the wrapped angle.

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

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from eol_cal.analysis.edges import boundary_state, debounce_edges, level_changes, quadrature_boundaries
from eol_cal.capture.data import Capture
from eol_cal.capture.windows import window_spans
from eol_cal.errors import InputError
from eol_cal.firmware.contract import HALL_FORWARD_SEQUENCE, NOMINAL_HALL_ANGLE
from eol_cal.numerics.pchip import pchip
from eol_cal.numerics.wrap import wrap_2pi, wrap_pi

TWO_PI = 2.0 * np.pi

#: Nominal electrical angle (rad) at which hall state s begins in forward rotation, index s-1
#: (the contract's nominal ``hall_angle``, defined once in the firmware reference).
NOMINAL_HALL_ANGLES: tuple[float, ...] = NOMINAL_HALL_ANGLE


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
    hall_events : (ndarray, ndarray, ndarray), optional
        Every hall transition of the capture, whatever the span: times (s), direction (+1/-1) and
        the boundary crossed (1..6), as :func:`hall_transitions` found them for the angle, kept for
        its other readers (:func:`nominal_transitions`: found once a capture, not twice).
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
    hall_events: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False)


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


def hall_transitions(
    t: np.ndarray,
    hall: np.ndarray,
    events: tuple[np.ndarray, np.ndarray] | None = None,
    hall_angles: Sequence[float] = NOMINAL_HALL_ANGLES,
    source: str = "<memory>",
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every hall transition between neighbouring states (glitches that skip a state left out).

    Parameters
    ----------
    t : ndarray
        Sample times (s).
    hall : ndarray
        Hall states (1..6).
    events : (ndarray, ndarray), optional
        The hall channel's exact change events (``Capture.events["hall"]``).
    hall_angles : sequence of 6 float
        Angle (rad) at which hall state s begins in forward rotation, index s-1.
    source : str
        File name for error messages.

    Returns
    -------
    t_h : ndarray
        Transition times (s).
    angle : ndarray
        Electrical angle of the boundary crossed (rad).
    direction : ndarray of int
        +1 forward, -1 reverse.
    begins : ndarray of int
        The boundary crossed, named by the state that begins there in forward rotation (1..6).
    """
    hall = np.asarray(hall)
    if hall.dtype.kind not in "iu":  # integer states are checked as they are (a capture's int8)
        hall = hall.astype(np.int64)
    bad = (hall < 1) | (hall > 6)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(source, "hall", f"invalid hall state {hall[i]} at t = {t[i]:.6g} s (valid: 1..6)")
    t_h, s_new = level_changes(t, hall, events)
    s_old = np.concatenate(([int(hall[0])], s_new[:-1]))
    if len(s_new) and ((s_new < 1) | (s_new > 6)).any():
        raise InputError(source, "hall", "invalid hall state (0 or 7) in the change events")
    angle, direction = hall_transition_angles(s_old, s_new, hall_angles)
    good = direction != 0
    begins = boundary_state(s_old, s_new, direction)[good]
    return t_h[good], angle[good], direction[good], begins


def _direction_at(t_query: np.ndarray, t_hall: np.ndarray, dir_hall: np.ndarray) -> np.ndarray:
    """Direction (+1/-1) of the hall transition nearest before each query time (first one before)."""
    idx = np.clip(np.searchsorted(t_hall, t_query, side="right") - 1, 0, len(t_hall) - 1)
    return dir_hall[idx]


def edge_knots(t_e: np.ndarray, rel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The interpolant's knots from sorted edge times ``t_e`` (s) and their angles ``rel`` (rad):
    two edges in one instant give one knot at their mean angle, so the knots stay unique.

    The edges come sorted: where no two share an instant (the rule) they are the knots as they
    are, the values ``np.unique`` and the means of one would give (tests/test_angle_edges.py),
    without their sort."""
    if np.all(t_e[1:] > t_e[:-1]):
        return t_e, rel
    t_u, inv = np.unique(t_e, return_inverse=True)
    return t_u, np.bincount(inv, weights=rel) / np.bincount(inv)


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
        Sample times (s), increasing (the samples between two instants are one slice).
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
    t = np.asarray(t, dtype=float)
    events = events or {}
    t_h, hall_theta, hall_dir, begins = hall_transitions(t, hall, events.get("hall"), hall_angles, source)
    every = (t_h, hall_dir, begins)
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
    t_u, rel_u = edge_knots(t_e, rel)
    if len(t_u) < 2:
        raise InputError(source, "enc_a", "fewer than two distinct encoder edge times")
    interp = pchip(t_u, rel_u)  # scipy's PchipInterpolator(extrapolate=False), bit for bit

    p = np.empty_like(t)
    w = np.empty_like(t)
    # t increasing: the samples inside the edges' span are one slice, those before and after two
    lo, hi = int(np.searchsorted(t, t_u[0], side="left")), int(np.searchsorted(t, t_u[-1], side="right"))
    # the slope at both ends in the same evaluation, at the end knots around the slice (still
    # increasing and inside; each query's value is its own elementwise arithmetic, as alone)
    w_ends = None
    if lo > 0 or hi < len(t):
        p_q, w_q = interp.with_slope(np.concatenate((t_u[:1], t[lo:hi], t_u[-1:])), sorted_inside=True)
        assert w_q is not None  # asked for (slope=True)
        p[lo:hi], w[lo:hi], w_ends = p_q[1:-1], w_q[1:-1], w_q[[0, -1]]
    else:
        p[lo:hi], w[lo:hi] = interp.with_slope(t[lo:hi], sorted_inside=True)
    before, after = slice(0, lo), slice(hi, len(t))
    for mask, t_end, p_end, e in ((before, t_u[0], rel_u[0], 0), (after, t_u[-1], rel_u[-1], 1)):
        if mask.stop > mask.start:
            assert w_ends is not None  # set when either end has samples
            w_end = float(w_ends[e])
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
    theta0 = float(wrap_pi(theta0 + float(np.mean(resid))))
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
        hall_theta=np.asarray(wrap_2pi(rel_h + theta0))[in_span],  # numpy in, numpy out
        hall_events=every,
    )


def nominal_transitions(capture: Capture, angle: AngleResult) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`hall_transitions` of ``capture`` at the nominal hall angles, from what its ``angle``
    kept (``hall_events``; found here when it kept none): ``(t_h, nominal angle, direction, begins)``.
    The boundary crossed names the nominal angle (:func:`hall_transition_angles`), the same values."""
    if angle.hall_events is None:
        t = np.asarray(capture.t, dtype=float)
        return hall_transitions(t, capture["hall"], capture.events.get("hall"), source=capture.source)
    t_h, direction, begins = angle.hall_events
    return t_h, np.asarray(NOMINAL_HALL_ANGLES, dtype=float)[begins - 1], direction, begins


def capture_angle(capture: Capture, hall_angles: Sequence[float] = NOMINAL_HALL_ANGLES) -> AngleResult:
    """:func:`reconstruct_angle` on a :class:`~eol_cal.capture.data.Capture`.

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


