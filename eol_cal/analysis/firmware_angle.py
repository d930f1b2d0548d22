"""The firmware estimator's angle against the offline angle: the estimator configured for a capture,
the frame offset the fit reports its phases in, and the tick-by-tick difference (docs/angle-frame.md)."""

from __future__ import annotations

# One code path for numpy and jax.numpy (xp): arrays typed np.ndarray | jax.Array | float, a union mypy
# cannot narrow per backend; shapes and dtypes are the golden vectors' and the C reference's to check.
# mypy: disable-error-code="arg-type,operator"

from dataclasses import dataclass
from collections.abc import Sequence

import numpy as np

from eol_cal.analysis.angle import AngleResult, capture_angle
from eol_cal.capture.data import Capture
from eol_cal.errors import InputError
from eol_cal.firmware import estimator as est
from eol_cal.firmware.contract import FLAG_INTERP_ENABLE
from eol_cal.numerics.wrap import wrap_pi

def firmware_config(capture: Capture, options: int = 0) -> est.EstimatorConfig:
    """The firmware estimator's configuration at a capture's poles, encoder and sample rate.

    ``options``: the estimator option bits (contract flags bits 2-5) the ECU ran when the capture
    was taken; 0 = the paper's estimator."""
    # the mean rate differs in its last bits from window to window; the firmware's tick is a
    # binary32 period, so six significant digits lose nothing and keep one compiled scan per rate
    tick_hz = float(f"{capture.sample_rate:.6g}")
    return est.EstimatorConfig.from_flags(FLAG_INTERP_ENABLE | options, poles=capture.poles,
                                          N_enc=capture.encoder_ppr, tick_hz=tick_hz)


#: one capture's part of the firmware frame: the capture, its offline angle theta_r (rad), the
#: segments' sample ranges, the hall table (rad, entry s-1; ``None``: nominal) and the estimator
#: options the ECU ran (contract flags bits 2-5)
FrameJob = tuple[Capture, np.ndarray, Sequence[tuple[int, int]], Sequence[float] | None, int]


def firmware_frame_offset(capture: Capture, theta_r: np.ndarray, ranges: list[tuple[int, int]],
                          hall_angle: tuple[float, ...] | None = None, options: int = 0) -> tuple[complex, int]:
    """Where the firmware's angle frame sits against the offline angle, over the fit's segments.

    Runs the firmware estimator over the capture (:func:`eol_cal.firmware.estimator.run_jax_batch`:
    one compiled program for every capture length and hall table) with the block's ``hall_angle``
    (rad, entry s-1; default nominal) and the estimator ``options`` the ECU ran (contract flags
    bits 2-5; 0 = the paper's estimator), and sums ``exp(i (theta_hat - theta_r))`` over the segment
    samples at which it is anchored, moving and has a speed.

    Returns
    -------
    (complex, int)
        The sum and the number of samples in it; ``angle(sum)`` is the offset (rad, electrical).
    """
    return firmware_frame_offsets([(capture, theta_r, ranges, hall_angle, options)])[0]


def firmware_frame_offsets(jobs: Sequence[FrameJob]) -> list[tuple[complex, int]]:
    """:func:`firmware_frame_offset` of many captures (:func:`firmware_frame_parts`, each capture's
    ranges summed)."""
    return [frame_total(parts) for parts in firmware_frame_parts(jobs)]


def frame_total(parts: Sequence[tuple[complex, int]]) -> tuple[complex, int]:
    """One capture's part of the frame from its ranges' parts: the sums and the samples added."""
    return complex(sum(s for s, _ in parts)), int(sum(n for _, n in parts))


#: ticks of one compiled call of the estimator's scan for a batch whose longest capture has at
#: least this many (:func:`scan_chunk`)
LONG_CHUNK = 8192


def scan_chunk(n_ticks: int) -> int:
    """The ticks of one compiled call of the estimator's scan for a batch whose longest capture has
    ``n_ticks``: :data:`LONG_CHUNK` from that many on, else the estimator's own ``JAX_CHUNK``.

    A call costs ~0.3 ms CPU beside its ticks' (the program's look-up, the arguments' transfer):
    a station's 172 000-sample capture ran 168 calls of 1024 ticks in 71 ms, 21 of 8192 in 27 ms;
    a refit's batches of 48 captures of 7000 ticks cost the same at either (their ticks dominate,
    and they keep the 1024 programs). The results are the same bit for bit (the state is carried
    from call to call; test). Two sizes only: each is a compiled program of its own."""
    return LONG_CHUNK if n_ticks >= LONG_CHUNK else est.JAX_CHUNK


def firmware_frame_parts(jobs: Sequence[FrameJob]) -> list[list[tuple[complex, int]]]:
    """Per capture and per segment range, :func:`firmware_frame_offset`'s sum and samples, the
    estimator run over all captures at once.

    The captures that share an estimator configuration (poles, encoder, tick rate, options) run
    side by side in one batched scan (:func:`eol_cal.firmware.estimator.run_jax_batch`), each as
    far as its last segment sample (the estimator is causal: what comes later changes nothing
    before it). The results are those of one capture at a time, bit for bit.

    Parameters
    ----------
    jobs : sequence of FrameJob
        ``(capture, theta_r, ranges, hall_angle, options)`` per capture.

    Returns
    -------
    list of list of (complex, int)
        Per job, per range of its ``ranges``, as :func:`firmware_frame_offset` of that range: the
        ranges' scatter tells the frame's uncertainty (:func:`eol_cal.analysis.fit.fp_angle.frame_sd`).
    """
    return StartedFrameParts(jobs).result()


class StartedFrameParts:
    """:func:`firmware_frame_parts` of ``jobs`` with the estimator's runs dispatched at once
    (:func:`eol_cal.firmware.estimator.start_jax_batch`): JAX computes them on its own thread
    until :meth:`result` is asked for (a lot refit reads and segments its next motors meanwhile)."""

    def __init__(self, jobs: Sequence[FrameJob]) -> None:
        self.jobs = list(jobs)
        by_cfg: dict[est.EstimatorConfig, list[int]] = {}
        for i, (capture, _, _, _, options) in enumerate(self.jobs):
            by_cfg.setdefault(firmware_config(capture, options), []).append(i)
        self._runs = []
        for cfg, idx in by_cfg.items():
            ends = [max((b for _, b in self.jobs[i][2]), default=1) for i in idx]
            signals = [tuple(np.asarray(self.jobs[i][0][name])[:m] for name in ("enc_a", "enc_b", "hall"))
                       for i, m in zip(idx, ends, strict=True)]
            self._runs.append((idx, est.start_jax_batch(cfg, signals, [self.jobs[i][3] for i in idx],
                                                        chunk=scan_chunk(max(ends)))))

    def result(self) -> list[list[tuple[complex, int]]]:
        """Per job, per range, the frame's sum and samples (:func:`firmware_frame_parts`')."""
        out: list[list[tuple[complex, int]]] = [[] for _ in self.jobs]
        for idx, started in self._runs:
            for i, run in zip(idx, started.result(), strict=True):
                out[i] = _frame_sums(run, self.jobs[i][1], self.jobs[i][2])
        return out


def _frame_sums(out: est.EstimatorOut, theta_r: np.ndarray, ranges: Sequence[tuple[int, int]]
                ) -> list[tuple[complex, int]]:
    ok = np.asarray((out.status & (est.ST_NO_ANCHOR | est.ST_STANDSTILL | est.ST_NO_SPEED)) == 0)
    theta_hat = np.asarray(out.theta_hat, float)
    sums = []
    for a, b in ranges:
        b = min(b, len(ok))
        sel = np.flatnonzero(ok[a:b]) + a
        d = theta_hat[sel] - theta_r[sel]
        sums.append((complex(np.exp(1j * d).sum()), int(len(sel))))
    return sums


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
    capture: Capture, angle: AngleResult | None = None, config: est.EstimatorConfig | None = None
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
    if not capture.has("enc_b"):
        raise InputError(capture.source, "enc_b", "missing channel, the firmware estimator needs it")
    if angle is None:
        angle = capture_angle(capture)
    if config is None:
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
