"""The fit's input of one motor: its captures cut into steady segments, where each segment came
from, and what the angle's frame and the fingerprint found (:class:`MotorInput`).

:mod:`eol_cal.analysis.fit.capture` builds it from captures; the fingerprint's angle
(:mod:`eol_cal.analysis.fit.fp_angle`), the solver's callers, the result and the plots read it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from eol_cal.analysis.fit import SteadySegments
from eol_cal.analysis.halls import HallAngles
from eol_cal.capture.data import Capture
from eol_cal.domain.bench_mechanics import BenchMechanics

if TYPE_CHECKING:
    from eol_cal.analysis.fingerprint import Fingerprint, WindowEdges


@dataclass
class SteadySegmentOrigin:
    """Where a steady segment came from: capture, sample range [start, stop), times (s), its
    load point i_qo (A) and speed (rpm); for the result and the plots."""

    source: str
    start: int
    stop: int
    t_start: float
    t_end: float
    i_qo: float
    speed_rpm: float


@dataclass
class MotorInput:
    """Everything the fit needs of one motor, and what the result reports about its inputs."""

    serial: str
    captures: list[Capture]
    angles: list
    segments: SteadySegments
    info: list[SteadySegmentOrigin]
    poles: int
    encoder_ppr: int
    kt: float
    kt_source: str
    capture_of_segment: list[int] = field(default_factory=list)
    frame: str = "offline"
    frame_offset_rad: float = 0.0
    mechanics: BenchMechanics | None = None
    hall: HallAngles | None = None
    frame_options: int = 0
    #: (source, reason) of each capture window that gave the fit no segment
    left_out: list[tuple[str, str]] = field(default_factory=list)
    #: each window's edges and the fingerprint (:func:`eol_cal.analysis.fit.fp_angle.measure_fingerprint`)
    prints: list[WindowEdges | None] | None = None
    fingerprint: Fingerprint | None = None
    #: how the segments' angle was corrected by the fingerprint, or why not
    angle_correction: str = "none: not measured"
    #: per capture window its part of the firmware frame offset (sum of exp(i (firmware - offline)), samples)
    frame_parts: list[tuple[complex, int] | None] | None = None
    #: the same per segment of each window (None: the window gave no part)
    frame_segment_parts: list[list[tuple[complex, int]] | None] | None = None
    #: per capture window the fraction (rad electrical) taken out of its angle to put it in the block's frame
    window_frac: list[float] | None = None
    #: standard error of ``frame_offset_rad`` (rad electrical; :func:`eol_cal.analysis.fit.fp_angle.frame_sd`)
    frame_sd_rad: float = 0.0
    #: how the ECU's own current ripple entered the fit (:func:`current_torque`): known from the
    #: ``iq`` channel, or why it is fitted as part of the motor's ripple
    current_ripple: str = "not measured"

    @property
    def sources(self) -> list[str]:
        return [c.source for c in self.captures]
