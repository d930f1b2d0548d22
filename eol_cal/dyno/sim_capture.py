"""One capture of the simulated dyno (:mod:`eol_cal.dyno.sim_dyno`): what it asks its capture source to
record (:class:`CaptureRequest`, :data:`CaptureSource`), the source without JAX
(:func:`synthetic_source`; the rig's plant is :func:`eol_cal.sim.rig.plant_source`), the recording
encoded as the capture buffer's register words (:func:`capture_to_buffer`), and when it happened
(:class:`CaptureTiming`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from collections.abc import Callable

import numpy as np

from eol_cal.capture.data import Capture
from eol_cal.capture.synthetic import synthetic_capture
from eol_cal.dyno.registers import DutCmdKind
from eol_cal.dyno.regmap import RegisterMap
from eol_cal.domain.bench_mechanics import RIGID, SIMULATED_BENCH_KEY
from eol_cal.domain.motor_params import load_motor


@dataclass(frozen=True)
class CaptureRequest:
    """What the dyno asks its capture source to record (one capture window).

    Attributes
    ----------
    speed_rpm : float
        Shaft speed (rpm), signed (negative = reverse).
    dut_cmd_kind : DutCmdKind
        Whether ``dut_cmd`` is a torque or a current.
    dut_cmd : float
        Load command: shaft torque (N*m) or nominal q current i_qo (A).
    n_samples : int
        Samples to record.
    rate_hz : float
        Sample rate (Hz).
    serial : str
        Serial of the motor on the dyno.
    seed : int or None
        Motor variation seed (the same motor for every capture of one simulator).
    capture_index : int
        1 for the first capture since start-up, 2 for the next, ...
    partial : callable or None
        A source that computes the recording in pieces may call it (from its own thread) with
        each longer prefix of it (a :class:`Capture` of its first samples): in real time the
        simulator answers those samples as the shaft turns them out, as a real dyno's buffer
        fills, instead of holding the whole capture back until the source is done. Sources
        that compute it at once ignore it.
    gap_s : float or None
        In real time: the physical time (s) from the previous capture's end to this one's start,
        while the drive stayed enabled (the shaft turned on between them: ramps, a reversal); a
        source may go on from that capture (the rig's plant does). None for the first capture,
        after a failed one, after the drive was disabled since, or not in real time.
    """

    speed_rpm: float
    dut_cmd_kind: DutCmdKind
    dut_cmd: float
    n_samples: int
    rate_hz: float
    serial: str
    seed: int | None
    capture_index: int
    partial: Callable[[Capture], None] | None = field(default=None, compare=False, repr=False)
    gap_s: float | None = None

    @property
    def seconds(self) -> float:
        """Capture duration (s)."""
        return self.n_samples / self.rate_hz


#: a capture source: capture request -> capture at ``rate_hz`` with ``n_samples`` samples
CaptureSource = Callable[["CaptureRequest"], Capture]


@dataclass
class CaptureTiming:
    """When one capture of the simulator happened (monotonic s), for benchmarks and tests.

    Attributes
    ----------
    index : int
        The capture's :attr:`CaptureRequest.capture_index`.
    started : float
        The capture started (armed and at speed).
    physical_end : float
        ``started`` plus the capture's duration: when a real dyno's buffer is full.
    source_done : float or None
        The capture source returned the recording (None: not yet, or it failed).
    ready : float or None
        The capture became ready (None: not yet, or it failed or was aborted).
    early_reads : int
        Window reads answered while the capture was still running (a streaming client).
    computed : int
        Samples the source has handed over before it was done (:attr:`CaptureRequest.partial`).
    """

    index: int
    started: float
    physical_end: float
    source_done: float | None = None
    ready: float | None = None
    early_reads: int = 0
    computed: int = 0

    @property
    def source_late_s(self) -> float:
        """How long the source finished after the physical end (s; 0 when it computed ahead)."""
        return 0.0 if self.source_done is None else max(0.0, self.source_done - self.physical_end)



def i_qo_of(req: CaptureRequest, kt: float) -> float:
    """Nominal q current (A) a capture request asks for (``kt`` in N*m/A)."""
    return req.dut_cmd if req.dut_cmd_kind == DutCmdKind.IQ else req.dut_cmd / kt


def synthetic_source(req: CaptureRequest) -> Capture:
    """Capture source without JAX: the analytic model of :mod:`eol_cal.capture.synthetic` (the
    ``paper`` motor).

    It models quantisation ripple and the 6th harmonic but no ECU: a flash does not change what
    it shows (the rig's plant source does, :func:`eol_cal.sim.rig.plant_source`).
    """
    motor = load_motor("paper")
    cap = synthetic_capture(
        rpm=req.speed_rpm,
        i_qo=i_qo_of(req, motor.kt),
        seconds=req.n_samples / req.rate_hz,
        fs=req.rate_hz,
        seed=(req.seed or 0) * 1000 + req.capture_index,
        theta_r0=0.7 * req.capture_index,
        serial=req.serial,
    )
    # the shaft torque straight from the ripple model: the torque path it simulates is a rigid coupling
    cap.metadata[SIMULATED_BENCH_KEY] = RIGID
    return cap



def capture_to_buffer(capture: Capture, n_samples: int, regmap: RegisterMap) -> dict[int, np.ndarray]:
    """A capture -> register words per channel id (the dyno's capture buffer, encoded as ``regmap`` says).

    Raises ValueError when the capture lacks the digital channels or has the wrong length.
    """
    if len(capture.t) != n_samples:
        raise ValueError(f"capture source returned {len(capture.t)} samples, {n_samples} requested")
    ch = capture.channels
    if "enc_a" not in ch or "hall" not in ch:
        raise ValueError("capture source returned no enc_a/hall channels")
    buffer = {regmap.window.digital_id: regmap.pack_digital(ch["enc_a"], ch.get("enc_b"), ch["hall"])}
    for cid, name in regmap.analog_channels.items():
        if name in ch:
            buffer[cid] = regmap.analog_to_words(ch[name])
    return buffer
