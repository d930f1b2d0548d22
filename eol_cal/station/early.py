"""The calibration capture's windows worked on as they arrive, while the dyno turns on.

The fit needs each window's angle (:func:`eol_cal.analysis.angle.capture_angle`) and p-p figure
(:func:`eol_cal.analysis.fit.motors.window_metrics`); neither depends on the other windows, so the
station computes them on a thread of its own as soon as the dyno client has read a window
(:func:`eol_cal.dyno.client.run_profile`, ``on_window``), and the first window also compiles the
firmware estimator's scan for the frame offset. What stays for the end is what needs every
window: the hall table, the firmware frame (run on :attr:`EarlyWindows.frame_workers` threads)
and the joint solve.

The fit asks for a window's figures with the window it cut from the joined capture
(:func:`eol_cal.capture.windows.split_windows`): they are handed out only when that window's
samples are exactly the ones worked on, else computed there and then, so the result is the one
``eol-cal fit`` gives on the capture file.
"""

from __future__ import annotations

import re
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

import numpy as np

from eol_cal.analysis.fit.motors import PreparedWindows, window_metrics
from eol_cal.capture.model import Capture

if TYPE_CHECKING:
    from eol_cal.analysis.angle import AngleResult
    from eol_cal.dyno.client import DynoWindow

#: threads for the firmware frame at the end (one window each)
FRAME_WORKERS = 4
_WINDOW_OF = re.compile(r"#(\d+)$")


class EarlyWindows(PreparedWindows):
    """Angles and p-p figures of a dyno capture's windows, computed as they arrive.

    Parameters
    ----------
    poles, encoder_ppr : int
        The motor type's (the capture's metadata will say the same, or the fit refuses it).
    estimator_options : int
        The estimator options the ECU runs (contract flags bits 2-5): the first window compiles
        the firmware estimator's scan with them.
    """

    frame_workers = FRAME_WORKERS

    def __init__(self, poles: int, encoder_ppr: int, estimator_options: int = 0) -> None:
        self.poles, self.encoder_ppr, self.estimator_options = poles, encoder_ppr, estimator_options
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="eol-cal-window")
        self._jobs: dict[int, Future] = {}
        self.used = 0
        """Windows whose early figures the fit took."""

    def on_window(self, index: int, window: DynoWindow, t: np.ndarray) -> None:
        """The dyno client's hook: start on window ``index`` (0-based) at once, on the helper thread."""
        self._jobs[index + 1] = self._pool.submit(self._prepare, index, window, t)

    def _prepare(self, index: int, window: DynoWindow, t: np.ndarray) -> tuple[Capture, AngleResult, dict[str, Any]]:
        from eol_cal.analysis.angle import capture_angle

        channels = {name: np.asarray(v).astype(np.int64) if name in ("enc_a", "enc_b", "hall") else v
                    for name, v in window.channels.items()}
        cap = Capture(t, channels, {"poles": self.poles, "encoder_ppr": self.encoder_ppr}, source=f"window {index + 1}")
        angle = capture_angle(cap)
        if index == 0:
            self._compile_estimator(cap, angle)
        return cap, angle, window_metrics(cap, angle)

    def _compile_estimator(self, cap: Capture, angle: AngleResult) -> None:
        """One throwaway run of the firmware estimator: the frame offset at the end then finds its
        scan compiled (one program for every window length and hall table)."""
        from eol_cal.analysis.firmware_angle import firmware_frame_offset

        try:
            firmware_frame_offset(cap, angle.theta_r, [(0, len(cap.t))], None, self.estimator_options)
        except Exception:  # noqa: BLE001 - only a warm-up: the fit reports a real failure
            pass

    def _early(self, capture: Capture) -> tuple[Capture, AngleResult, dict[str, Any]] | None:
        """The early work on ``capture`` when it holds exactly the samples worked on, else None."""
        m = _WINDOW_OF.search(capture.source or "")
        job = self._jobs.get(int(m.group(1))) if m else None
        if job is None or job.exception() is not None:
            return None
        cap, angle, metrics = job.result()
        same = (capture.metadata.get("poles") == self.poles and capture.metadata.get("encoder_ppr") == self.encoder_ppr
                and np.array_equal(capture.t, cap.t)
                and all(name in capture.channels and np.array_equal(capture.channels[name], v)
                        for name, v in cap.channels.items()))
        return (cap, angle, metrics) if same else None

    def angle_of(self, capture: Capture) -> AngleResult:
        early = self._early(capture)
        if early is None:
            return super().angle_of(capture)
        self.used += 1
        return early[1]

    def metrics_of(self, capture: Capture, angle: AngleResult) -> dict[str, Any]:
        early = self._early(capture)
        if early is None or early[1] is not angle:
            return super().metrics_of(capture, angle)
        return {**early[2], "source": capture.source}

    def wait(self) -> None:
        """Until every window handed in is worked on (the fit then takes them without waiting)."""
        for job in list(self._jobs.values()):
            job.exception()

    def close(self) -> None:
        self._pool.shutdown(wait=True)
