"""The calibration capture's windows worked on as they arrive, while the dyno turns on.

The fit needs each window's angle (:func:`eol_cal.analysis.angle.capture_angle`) and p-p figure
(:func:`eol_cal.analysis.fit.capture.window_metrics`); neither depends on the other windows, so the
station computes them on a thread of its own as soon as the dyno client has read a window
(:func:`eol_cal.dyno.profile_run.run_profile`, ``on_window``), and the first window also readies
the firmware estimator's scan for the frame offset (the program of as many lanes as the capture
has windows). The firmware frame needs every window (the hall table is measured on all of them):
it is computed as soon as the last window is in, every window in one batched scan
(:func:`eol_cal.analysis.firmware_angle.firmware_frame_parts`), while the shaft stops and the ECU's
state is read. (One window a thread, four threads, cost 5x the CPU of the batched scan on the
station's 8 windows, 0.25-0.6 against 0.05 CPU s, and on two cores held the fit back: the same
numbers, bit for bit.)
What the fit itself does at the end is the hall table again and the joint solve.

The fit asks for a window's figures with the window it cut from the joined capture
(:func:`eol_cal.capture.windows.split_windows`): they are handed out only when that window's
samples are exactly the ones worked on, else computed there and then, so the result is the one
``eol-cal fit`` gives on the capture file.
"""

from __future__ import annotations

import os
import re
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any
from collections.abc import Callable, Sequence

import numpy as np

from eol_cal.analysis.fit.capture import PreparedWindows, capture_segments, window_metrics
from eol_cal.capture.data import Capture

if TYPE_CHECKING:
    from eol_cal.analysis.angle import AngleResult
    from eol_cal.analysis.firmware_angle import FrameJob
    from eol_cal.dyno.profile_run import DynoWindow

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
    pool : ThreadPoolExecutor, optional
        Where the work runs (the station cycle's helper thread, behind its pre-warming); default
        a thread of its own.
    cache_dir : path, optional
        The fit's cache directory: JAX's persistent compilation cache is switched on there before
        the estimator is compiled (:func:`eol_cal.analysis.fit.cache.enable_compile_cache`).
    n_windows : int, optional
        Windows the capture will have: when the last is in, the firmware frame is computed with
        the hall table measured on all of them and the fit's segments of ``settle_s`` and
        ``min_revs`` (the fit's defaults, :class:`eol_cal.analysis.fit.motors.FitOptions`); the
        first window compiles the firmware estimator for it.
    measure : callable
        ``(window, angle) -> figures`` computed for each window (default the fit's p-p figures,
        :func:`~eol_cal.analysis.fit.capture.window_metrics`; the verification's: the ripple at
        the operating point, :func:`eol_cal.analysis.point_metrics.point_ripple`).
    """

    def __init__(self, poles: int, encoder_ppr: int, estimator_options: int = 0, *,
                 pool: ThreadPoolExecutor | None = None, cache_dir: str | os.PathLike[str] | None = None,
                 n_windows: int | None = None, settle_s: float = 0.1, min_revs: int = 1,
                 measure: Callable[[Capture, AngleResult], Any] = window_metrics) -> None:
        self.poles, self.encoder_ppr, self.estimator_options = poles, encoder_ppr, estimator_options
        self.measure = measure
        self.cache_dir = cache_dir
        self.n_windows, self.settle_s, self.min_revs = n_windows, settle_s, min_revs
        self._frames: Future | None = None
        self._own = pool is None
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="eol-cal-window") if pool is None else pool
        self._jobs: dict[int, Future] = {}
        # the fit asks several times about one window's capture (its angle, its frame, its figures):
        # compared once (the capture held, so that its id is not another's)
        self._compared: dict[int, tuple[Capture, bool]] = {}
        self.used = 0
        """Windows whose early angle the fit took."""
        self.frames_used = 0
        """Windows whose early part of the firmware frame the fit took."""

    def on_window(self, index: int, window: DynoWindow, t: np.ndarray) -> None:
        """The dyno client's hook: start on window ``index`` (0-based) at once, on the helper thread."""
        self._jobs[index + 1] = self._pool.submit(self._prepare, index, window, t)
        if self.n_windows is not None and index + 1 == self.n_windows:
            self._frames = self._pool.submit(self._frame_offsets)

    def _frame_offsets(self) -> dict[int, tuple[tuple, list, list[tuple[complex, int]]]]:
        """Every window's part of the firmware frame, as :func:`motor_inputs` will ask for it:
        ``{window: (hall_angle, ranges, [(sum, n) per range])}`` (empty when a window has no ``enc_b``)."""
        from eol_cal.analysis.firmware_angle import firmware_frame_parts
        from eol_cal.analysis.halls import measure_hall_angles

        done = {k: job.result() for k, job in sorted(self._jobs.items())}
        if any("enc_b" not in cap.channels for cap, _a, _m in done.values()):
            return {}
        hall = measure_hall_angles([a.hall_begins for _c, a, _m in done.values()],
                                   [a.hall_theta for _c, a, _m in done.values()])
        table = tuple(hall.hall_angle)
        ranges = {k: capture_segments(cap.t, a.theta_r, a.omega_r, np.asarray(cap.iq_ref(), dtype=float),
                                      settle_s=self.settle_s, min_revs=self.min_revs) for k, (cap, a, _m) in done.items()}
        keys = [k for k in done if ranges[k]]
        sums = firmware_frame_parts([(done[k][0], done[k][1].theta_r, ranges[k], table, self.estimator_options)
                                     for k in keys])
        return {k: (table, ranges[k], parts) for k, parts in zip(keys, sums, strict=True)}

    def _prepare(self, index: int, window: DynoWindow, t: np.ndarray) -> tuple[Capture, AngleResult, dict[str, Any]]:
        from eol_cal.analysis.angle import capture_angle

        channels = {name: np.asarray(v).astype(np.int64) if name in ("enc_a", "enc_b", "hall") else v
                    for name, v in window.channels.items()}
        cap = Capture(t, channels, {"poles": self.poles, "encoder_ppr": self.encoder_ppr}, source=f"window {index + 1}")
        angle = capture_angle(cap)
        if index == 0 and self.n_windows is not None:
            self._compile_estimator(cap, angle)
        return cap, angle, self.measure(cap, angle)

    def _compile_estimator(self, cap: Capture, angle: AngleResult) -> None:
        """One throwaway run of the firmware estimator, this window in each of the capture's lanes:
        the frame at the end then finds its scan compiled (one program per lane count for every
        window length and hall table)."""
        from eol_cal.analysis.firmware_angle import firmware_frame_parts
        from eol_cal.analysis.fit.cache import enable_compile_cache

        try:
            enable_compile_cache(self.cache_dir)
            job = (cap, angle.theta_r, [(0, len(cap.t))], None, self.estimator_options)
            firmware_frame_parts([job] * max(1, self.n_windows or 1))
        except Exception:  # noqa: BLE001 - only a warm-up: the fit reports a real failure
            pass

    def _window(self, capture: Capture) -> int | None:
        m = _WINDOW_OF.search(capture.source or "")
        return int(m.group(1)) if m else None

    def _early(self, capture: Capture) -> tuple[Capture, AngleResult, dict[str, Any]] | None:
        """The early work on ``capture`` when it holds exactly the samples worked on, else None."""
        window = self._window(capture)
        job = self._jobs.get(window) if window is not None else None
        if job is None or job.exception() is not None:
            return None
        cap, angle, metrics = job.result()
        known = self._compared.get(id(capture))
        if known is None or known[0] is not capture:
            same = (capture.metadata.get("poles") == self.poles
                    and capture.metadata.get("encoder_ppr") == self.encoder_ppr
                    and np.array_equal(capture.t, cap.t)
                    and all(name in capture.channels and np.array_equal(capture.channels[name], v)
                            for name, v in cap.channels.items()))
            known = self._compared[id(capture)] = (capture, same)
        return (cap, angle, metrics) if known[1] else None

    def angle_of(self, capture: Capture) -> AngleResult:
        early = self._early(capture)
        if early is None:
            return super().angle_of(capture)
        self.used += 1
        return early[1]

    def frame_parts(self, jobs: Sequence[FrameJob]) -> list[list[tuple[complex, int]]]:
        out: list[list[tuple[complex, int]] | None] = [self._early_frame(*job) for job in jobs]
        missing = [i for i, got in enumerate(out) if got is None]
        for i, got in zip(missing, super().frame_parts([jobs[i] for i in missing]), strict=True):
            out[i] = got
        return out  # type: ignore[return-value]

    def _early_frame(self, capture: Capture, theta_r: np.ndarray, ranges: Sequence[tuple[int, int]],
                     hall_angle: Sequence[float] | None, options: int) -> list[tuple[complex, int]] | None:
        """A window's part of the firmware frame computed when the last window came in, when it
        was computed from exactly these inputs; else None."""
        early = self._early(capture)
        frames = self._frames
        if (early is None or frames is None or frames.exception() is not None
                or not np.array_equal(theta_r, early[1].theta_r)):
            return None
        got = frames.result().get(self._window(capture))
        if (got is None or hall_angle is None or got[0] != tuple(hall_angle) or got[1] != list(ranges)
                or options != self.estimator_options):
            return None
        self.frames_used += 1
        return got[2]

    def metrics_of(self, capture: Capture, angle: AngleResult) -> dict[str, Any]:
        early = self._early(capture)
        if early is None or early[1] is not angle or self.measure is not window_metrics:
            return super().metrics_of(capture, angle)
        return {**early[2], "source": capture.source}

    def measured(self, capture: Capture) -> Any:
        """``measure(capture, its angle)``: what was computed as the window arrived, when
        ``capture`` holds exactly its samples; else computed now."""
        early = self._early(capture)
        if early is not None:
            return early[2]
        return self.measure(capture, self.angle_of(capture))

    def wait(self) -> None:
        """Until every window handed in is worked on (the fit then takes them without waiting)."""
        for job in [*self._jobs.values(), *([self._frames] if self._frames is not None else [])]:
            job.exception()

    def close(self) -> None:
        """Wait for the work handed in; stop the thread when it is this object's own."""
        self.wait()
        if self._own:
            self._pool.shutdown(wait=True)
