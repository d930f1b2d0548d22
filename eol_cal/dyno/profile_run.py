"""A test profile run on the dyno: every segment's capture read while the shaft turns on
(:func:`run_profile`), the windows joined into one :class:`~eol_cal.capture.data.Capture` whose
time axis keeps the real time between the segments' starts (:func:`assemble`), and the whole as one
call that checks the capture and writes it atomically (:func:`acquire`). The drive is left in the
safe state in every case (:meth:`eol_cal.dyno.client.DynoClient.safe_state`).
"""

from __future__ import annotations

import functools
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable, Sequence

import numpy as np

from eol_cal.capture import validate, write_capture
from eol_cal.capture.data import Capture
from eol_cal.domain.bench_mechanics import SIMULATED_BENCH_KEY
from eol_cal.dyno.client import DynoClient, DynoError
from eol_cal.dyno.registers import CaptureState, Command
from eol_cal.dyno.setpoints import DEFAULT_RATE_HZ, DynoSetpoint, lead_in_samples, lead_point_samples
from eol_cal.dyno.transfer import DynoConfig, ProgressFn
from eol_cal.errors import InputError, Interrupted

#: channels read by default (the packed digital channel is always read); the others on request
DEFAULT_CHANNELS = ("torque", "iq_ref", "iqc", "speed")
EXTRA_CHANNELS = ("temp", "iq", "id", "ia", "ib", "ic")
#: least gap between two windows in the joined capture (sample periods): a simulator captures
#: faster than real time, and a gap must stay visible to anyone who splits at gaps in ``t``
WINDOW_GAP_SAMPLES = 100


@dataclass
class DynoWindow:
    """One capture window as read from the dyno: the samples of one profile segment
    (arrays on the window's own time; ``t0`` in s from the first window's start)."""

    t0: float
    rate_hz: float
    channels: dict[str, np.ndarray] = field(default_factory=dict)


#: ``(index, window, t)``: a window just read, with its sample times (s) in the joined capture
WindowHook = Callable[[int, DynoWindow, np.ndarray], None]



def run_profile(
    client: DynoClient,
    segments: Sequence[DynoSetpoint],
    rate_hz: int = DEFAULT_RATE_HZ,
    channels: Sequence[str] = DEFAULT_CHANNELS,
    progress: ProgressFn | None = None,
    reset_faults: bool = False,
    before_capture: Callable[[], object] | None = None,
    after_capture: Callable[[], object] | None = None,
    on_window: WindowHook | None = None,
    lead_in_s: float = 0.0,
    lead_in_point: DynoSetpoint | None = None,
) -> tuple[list[DynoWindow], dict]:
    """Run every segment and read its capture; the drive is left in the safe state in every case.

    ``before_capture`` is called (and waited for, on a thread of its own while this one keeps the
    dyno's communication watchdog fed: :func:`_while_fed`) right before the first capture is armed,
    while the shaft ramps to the first segment; ``after_capture`` right after the last window was read
    and checked, while the shaft stops: work of the caller's that must bracket the captures (the
    ECU's state, :func:`eol_cal.station.acquisition.acquire_traced`) runs alongside the ramps, not
    after them. An exception from either ends the run like any other (safe state first). As soon
    as a capture is ready the shaft goes on to the next point (or stops after the last), while the
    capture's last samples are read: the next capture is armed once they are in. The first capture
    starts with a lead-in of ``lead_in_s`` (s) at the first segment's point, recorded by the dyno
    and never read: the shaft turns while the ECU settles after its reset
    (:func:`eol_cal.firmware.settling.settle_s`) without a wait between two captures (a dyno
    starts a capture itself at speed; a sleep would add a poll's latency). ``on_window(i,
    window, t)`` is called with each window as soon as it is read and checked, ``t`` its sample
    times in the joined capture (:func:`window_times`): the caller's work on it can start while
    the shaft turns on (it should hand the work to another thread and return).

    ``lead_in_point``: where the ECU settles faster than at the first segment's point (its
    identification at a higher speed, :func:`eol_cal.firmware.settling.lead_in_plan`), the shaft
    turns there first, for the point's ``seconds``, as a capture of its own the dyno records and
    the client does not read (:func:`lead_point_samples`; ``before_capture`` runs before it),
    then ramps to the first point, where ``lead_in_s`` follows as above.

    Returns the segments' data and the dyno's identification registers.
    Raises :class:`DynoError` on any failure (after the safe state was commanded).
    """
    known = client.regmap.channels
    unknown = [c for c in channels if c not in known]
    if unknown:
        raise InputError(client.regmap.source, "channels", f"the dyno records no channel(s) {unknown}; known: {sorted(known)}")
    for i, seg in enumerate(segments):
        # refuse a bad profile before the shaft turns
        if int(round(seg.seconds * rate_hz)) < 2:
            raise InputError(None, f"segment {i + 1}",
                             f"{seg.seconds:g} s of steady capture at {rate_hz} Hz is fewer than 2 samples")
        if seg.ramp_rpm_s <= 0 or not np.isfinite(seg.ramp_rpm_s):
            raise InputError(None, f"segment {i + 1}", f"ramp {seg.ramp_rpm_s} rpm/s must be positive")
    data: list[DynoWindow] = []
    t_first: float | None = None
    t_end = -np.inf  # the last sample time of the windows so far in the joined capture
    try:
        ident = client.connect()
        if reset_faults:
            client.write(fault_reset=Command.EXECUTE)
        ramp_s = client.set_point(segments[0] if lead_in_point is None else lead_in_point, wait=False)
        stopping = False

        def next_point(i: int, st: dict) -> None:
            # the capture is ready: the shaft goes on to the next point (or stops) while the
            # buffer's last samples are read
            nonlocal ramp_s, stopping
            if i + 1 < len(segments):
                ramp_s = client.set_point(segments[i + 1], wait=False, status=st)
            else:
                client.write(speed_setpoint=0.0)
                stopping = True

        for i, seg in enumerate(segments):
            if progress:
                progress(f"segment {i + 1}/{len(segments)}: {seg.speed_rpm:g} rpm", i, len(segments))
            n = int(round(seg.seconds * rate_hz))
            lead = lead_in_samples(lead_in_s, rate_hz) if i == 0 else 0
            if i == 0 and before_capture is not None:
                _while_fed(client, before_capture, "waiting to arm the first capture")
            if i == 0 and lead_in_point is not None:
                if progress:
                    progress(f"lead-in: {lead_in_point.speed_rpm:g} rpm", 0, len(segments))
                n_point = lead_point_samples(lead_in_point, rate_hz)
                client.record(n_point, rate_hz, channels, None, ramp_s, skip=n_point - 1,
                              on_ready=functools.partial(next_point, -1))  # on to the first point
                client.check_faults(client.status(), "the lead-in")
            t_start = time.monotonic() + lead / rate_hz
            chans = client.record(n + lead, rate_hz, channels, progress, ramp_s, skip=lead,
                                  on_ready=functools.partial(next_point, i))
            st = client.status()
            client.check_faults(st, "reading the capture")
            if int(st["capture_state"]) != CaptureState.READY:
                raise DynoError(f"{client.where}: capture buffer changed while it was read")
            bad = [c for c, v in chans.items() if not np.all(np.isfinite(v))]
            if bad:
                raise DynoError(f"{client.where}: segment {i + 1}: non-finite samples in {', '.join(bad)}")
            t_first = t_start if t_first is None else t_first
            data.append(DynoWindow(t_start - t_first, float(rate_hz), chans))
            if on_window is not None:
                t_window = _window_time(data[-1], t_end)
                t_end = float(t_window[-1])
                on_window(i, data[-1], t_window)
        if "sim_bench" in client.regmap:  # a simulator's claim of the path it simulated, known after a capture
            ident.update(client.read(["sim_bench"]))
        if after_capture is not None:
            after_capture()
        if progress:
            progress("stopping", len(segments), len(segments))
        if not stopping:
            client.write(speed_setpoint=0.0)
        client.wait_standstill(client.config.settle_timeout, "stopping")
    except BaseException as exc:
        why = client.safe_state()
        client.close()
        note = (
            "speed set to 0 and drive disabled"
            if why is None
            else f"safe state NOT confirmed ({why}); the dyno's watchdog stops the drive after {client.config.watchdog_ms} ms"
        )
        if isinstance(exc, DynoError):
            raise DynoError(f"{exc}; {note}") from exc
        if isinstance(exc, Interrupted):
            raise Interrupted(exc.signal_name, "the dyno profile", note) from None
        raise
    why = client.safe_state()
    client.close()
    if why is not None:
        raise DynoError(f"could not disable the drive after the run: {why}")
    return data, ident


def _while_fed(client: DynoClient, work: Callable[[], object], what: str) -> None:
    """``work()`` on a thread of its own, while this one reads the dyno's status every quarter of
    its communication watchdog and checks its faults.

    The drive is enabled and ramping meanwhile: a dyno that gets no request for its watchdog's time
    (a real one's: 2 s) stops and latches a fault, and every later motor's pre-flight refuses it until
    someone clears it. The station's work here reads the ECU's state: seconds where the ECU is slow
    to answer, or the station's process slow to start its bus. ``work``'s error is raised here as
    its own (the caller's safe state follows).
    """
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="before-capture")
    try:
        job = pool.submit(work)
        period = max(client.config.watchdog_ms / 4000.0, 0.01)
        while True:
            try:
                job.result(timeout=period)
                return
            except TimeoutError:  # concurrent.futures' since 3.11
                client.check_faults(client.status(), what)
    finally:
        pool.shutdown(wait=False)  # a dyno fault does not wait for the work (the safe state first)


def _window_time(d: DynoWindow, t_end: float) -> np.ndarray:
    n = len(next(iter(d.channels.values())))
    return max(d.t0, t_end + WINDOW_GAP_SAMPLES / d.rate_hz) + np.arange(n) / d.rate_hz


def window_times(data: Sequence[DynoWindow]) -> list[np.ndarray]:
    """Each window's sample times (s) in the joined capture (:func:`assemble`): from the wall-clock
    time of its capture start after the first one, but at least :data:`WINDOW_GAP_SAMPLES` sample
    periods after the previous window's last sample."""
    out: list[np.ndarray] = []
    for d in data:
        out.append(_window_time(d, out[-1][-1] if out else -np.inf))
    return out


def assemble(
    data: Sequence[DynoWindow],
    ident: dict,
    serial: str | None = None,
    extra_metadata: dict | None = None,
) -> Capture:
    """Join segment data into one capture.

    Window ``i`` starts at the wall-clock time of its capture start after the first one, but at
    least :data:`WINDOW_GAP_SAMPLES` sample periods after the previous window's last sample.
    """
    if not data:
        raise DynoError("no segments captured")
    names = sorted(set.intersection(*(set(d.channels) for d in data)))
    ts = window_times(data)
    chans: dict[str, list[np.ndarray]] = {n: [] for n in names}
    for d in data:
        for name in names:
            chans[name].append(d.channels[name])
    starts = [float(t[0]) for t in ts]
    metadata: dict[str, str | int | float] = {
        "serial": serial or str(ident.get("dut_serial") or ""),
        "poles": int(ident["dut_poles"]),
        "encoder_ppr": int(ident["dut_encoder_ppr"]),
        "kt": float(ident["dut_kt"]),
        "source": "dyno",
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "segments": len(data),
        "segment_starts": ",".join(f"{s:.6f}" for s in starts),
    }
    if ident.get("sim_bench"):  # a simulated dyno: the torque path its plant ran (docs/fit.md, "Model check")
        metadata[SIMULATED_BENCH_KEY] = str(ident["sim_bench"])
    metadata.update(extra_metadata or {})
    if not metadata["serial"]:
        raise InputError(None, "serial", "the dyno reports no DUT serial: give the motor's serial")
    channels = {}
    for name in names:
        v = np.concatenate(chans[name])
        channels[name] = v.astype(np.int64) if name in ("enc_a", "enc_b", "hall") else v
    return Capture(np.concatenate(ts), channels, metadata, source="dyno")


def acquire(
    config: DynoConfig,
    segments: Sequence[DynoSetpoint],
    out: str | Path | None = None,
    *,
    serial: str | None = None,
    rate_hz: int = DEFAULT_RATE_HZ,
    channels: Sequence[str] = DEFAULT_CHANNELS,
    progress: ProgressFn | None = None,
    extra_metadata: dict | None = None,
    reset_faults: bool = False,
    before_capture: Callable[[], object] | None = None,
    after_capture: Callable[[], object] | None = None,
    on_window: WindowHook | None = None,
    lead_in_s: float = 0.0,
    lead_in_point: DynoSetpoint | None = None,
) -> Capture:
    """Run a profile on the dyno, check the capture and write it atomically to ``out``.

    Parameters
    ----------
    config : DynoConfig
        Dyno address and timing.
    segments : sequence of DynoSetpoint
        The test profile.
    out : path, optional
        Capture file (``.csv`` or ``.mf4``); written only when everything succeeded.
    serial : str, optional
        Motor serial; default: the serial the dyno reports.
    rate_hz : int
        Capture sample rate (Hz).
    reset_faults : bool
        Clear faults latched before this run (a fault during the run still stops it).
    before_capture, after_capture : callable, optional
        Called right before the first capture is armed and right after the last window is read
        (:func:`run_profile`).
    on_window : callable, optional
        ``(index, window, t)`` for each window as soon as it is read (:func:`run_profile`).
    lead_in_s : float
        Time (s) the shaft turns at the first segment's point before its samples count
        (:func:`run_profile`); recorded in the capture's metadata as ``lead_in_s``.
    lead_in_point : DynoSetpoint, optional
        A point the shaft turns at first (:func:`run_profile`); recorded as ``lead_in_point_rpm``
        and ``lead_in_point_s``.

    Raises
    ------
    DynoError
        Any dyno or transfer failure (the drive was sent to the safe state; no file written).
    InputError
        A capture that fails validation (no file written).
    """
    if not segments:
        raise InputError(None, "profile", "no segments")
    client = DynoClient(config)
    data, ident = run_profile(client, segments, rate_hz, channels, progress, reset_faults, before_capture, after_capture,
                              on_window, lead_in_s, lead_in_point)
    lead = lead_in_samples(lead_in_s, rate_hz) / rate_hz
    meta = {**(extra_metadata or {}), **({"lead_in_s": lead} if lead or lead_in_point else {})}
    if lead_in_point is not None:
        meta |= {"lead_in_point_rpm": float(lead_in_point.speed_rpm),
                 "lead_in_point_s": lead_point_samples(lead_in_point, rate_hz) / rate_hz}
    capture = assemble(data, ident, serial, meta)
    capture = validate(capture)
    if out is not None:
        write_capture(capture, out)
    return capture
