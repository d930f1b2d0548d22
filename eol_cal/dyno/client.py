"""Dyno client: drive a Modbus TCP dyno through a test profile and read the captures.

The sequence per segment: set the load command, direction and speed set point, enable, wait
until the dyno reports "at speed", start a capture, poll until the buffer is ready, read every
channel through the paged window and check it. Which registers those are, and how their values
are encoded, is the dyno's register map (:mod:`.regmap`, from a map file: ``DynoConfig.register_map``).
The segments are joined into one :class:`~eol_cal.capture.model.Capture` whose time axis keeps the
real time between the segments' starts (so the gaps are visible: the windows are not one continuous
recording).

Safety: whatever goes wrong (timeout, lost connection, fault bit, bad data, Ctrl-C) the client
sets the speed to zero and disables the drive in a ``finally`` and raises :class:`DynoError`;
the capture file is written (atomically) only after every segment was read and validated.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from eol_cal.address import parse_modbus_address
from eol_cal.capture.model import Capture
from eol_cal.dyno import registers as rm
from eol_cal.dyno.regmap import READ_FC
from eol_cal.dyno.registers import (CaptureCommand, CaptureState, Command, Direction, DriveState, DutCmdKind, Mode, Switch,
                                    fault_names)
from eol_cal.errors import EolCalError, InputError, Interrupted
from eol_cal.exchange_log import log_modbus
from eol_cal.plant.profile import Profile
from eol_cal.dyno.transfer import BufferFill, BufferReader, DynoConfig, ProgressFn, Stream, TransferError, read_capture_buffer
from eol_cal.retry import RetriesExhausted, retry_call

if TYPE_CHECKING:
    from pymodbus.pdu import ModbusPDU

#: channels read by default (the packed digital channel is always read); the others on request
DEFAULT_CHANNELS = ("torque", "iq_ref", "iqc", "speed")
EXTRA_CHANNELS = ("temp", "iq", "id", "ia", "ib", "ic")
#: a heartbeat that does not change for this long means the dyno's controller stopped (s)
HEARTBEAT_STALL_S = 1.0
#: least gap between two windows in the joined capture (sample periods): a simulator captures
#: faster than real time, and a gap must stay visible to anyone who splits at gaps in ``t``
WINDOW_GAP_SAMPLES = 100
#: status poll period (s) when a capture is about to be ready
READY_POLL_S = 0.002
#: capture rate (Hz) when the profile gives none
DEFAULT_RATE_HZ = 10000


class DynoError(EolCalError):
    """The dyno run failed; the drive was sent to the safe state (exit code 2)."""


@dataclass(frozen=True)
class DynoSetpoint:
    """One steady operating point of a test profile (one profile segment), as the dyno runs it.

    Attributes
    ----------
    speed_rpm : float
        Shaft speed (rpm), signed: negative runs in reverse.
    seconds : float
        Capture duration at this point (s).
    torque_nm : float or None
        Load as shaft torque command (N*m) ...
    iq : float or None
        ... or as nominal q current i_qo (A); exactly one of the two is given.
    ramp_rpm_s : float
        Speed ramp rate to reach this point (rpm/s).
    """

    speed_rpm: float
    seconds: float
    torque_nm: float | None = None
    iq: float | None = None
    ramp_rpm_s: float = 1000.0

    def command(self) -> tuple[DutCmdKind, float]:
        """(kind, value) of the load command: torque (N*m) or i_qo (A)."""
        if self.iq is not None:
            return DutCmdKind.IQ, float(self.iq)
        return DutCmdKind.TORQUE, float(self.torque_nm or 0.0)


#: ramp rate (rpm/s) for a segment that gives no ramp time (a step on the plant)
DEFAULT_RAMP_RPM_S = 1000.0


def setpoints_from_profile(profile: Profile) -> list[DynoSetpoint]:
    """A test profile (:class:`eol_cal.plant.profile.Profile`) as the dyno's set points, one per
    profile segment.

    The dyno captures only the steady part of a segment: ``seconds - ramp_s``; the ramp rate is
    the speed change over ``ramp_s`` (or :data:`DEFAULT_RAMP_RPM_S` without a ramp time).
    """
    out: list[DynoSetpoint] = []
    prev = 0.0
    for seg in profile.segments:
        delta = abs(seg.speed_rpm - prev)
        ramp = delta / seg.ramp_s if seg.ramp_s > 0.0 and delta > 0.0 else DEFAULT_RAMP_RPM_S
        out.append(DynoSetpoint(seg.speed_rpm, seg.seconds - seg.ramp_s, seg.torque_nm, seg.iq, ramp))
        prev = seg.speed_rpm
    return out


def physical_seconds(segments: Sequence[DynoSetpoint], rate_hz: int = DEFAULT_RATE_HZ, lead_in_s: float = 0.0,
                     lead_in_point: DynoSetpoint | None = None) -> float:
    """How long the shaft must turn for ``segments`` (s), from standstill back to standstill: what
    no tool can take off a station's cycle.

    Each segment's ramp at its rate until the dyno reports at speed (within its tolerance), a
    reversal's stop at the previous ramp rate first, the capture's ``round(seconds * rate_hz)``
    samples (the first segment's ``lead_in_samples(lead_in_s, rate_hz)`` more; a
    ``lead_in_point`` first, with its :func:`lead_point_samples`), and the stop at the end, as
    :func:`run_profile` commands them.
    """
    from eol_cal.dyno.sim import SPEED_TOL_REL, SPEED_TOL_RPM

    points = [(lead_in_point, lead_point_samples(lead_in_point, rate_hz))] if lead_in_point and segments else []
    points += [(seg, int(round(seg.seconds * rate_hz))) for seg in segments]
    total, speed, ramp = 0.0, 0.0, DEFAULT_RAMP_RPM_S
    for seg, n in points:
        if abs(speed) > rm.STANDSTILL_RPM and (seg.speed_rpm < 0) != (speed < 0):
            total += (abs(speed) - rm.STANDSTILL_RPM) / ramp
            speed = math.copysign(rm.STANDSTILL_RPM, speed)
        ramp = seg.ramp_rpm_s
        tol = max(SPEED_TOL_RPM, SPEED_TOL_REL * abs(seg.speed_rpm))
        total += max(0.0, abs(seg.speed_rpm - speed) - tol) / ramp
        total += n / rate_hz
        speed = seg.speed_rpm
    total += lead_in_samples(lead_in_s, rate_hz) / rate_hz if segments else 0.0
    return total + max(0.0, abs(speed) - rm.STANDSTILL_RPM) / ramp


def lead_in_samples(lead_in_s: float, rate_hz: float) -> int:
    """Samples of a lead-in of ``lead_in_s`` (s) at ``rate_hz`` (Hz): captured and never read."""
    return int(math.ceil(max(0.0, lead_in_s) * rate_hz - 1e-9))


def lead_point_samples(point: DynoSetpoint, rate_hz: float) -> int:
    """Samples the dyno captures at a lead-in point (:func:`run_profile`): its ``seconds`` and the one
    sample read to close the capture (a capture reads at least one)."""
    return lead_in_samples(point.seconds, rate_hz) + 1


def parse_address(text: str) -> tuple[str, int]:
    """The dyno's ``HOST`` or ``HOST:PORT`` -> (host, port), Modbus TCP's port 502 when none is
    given; a bad address is an :class:`InputError`."""
    return parse_modbus_address(text, "address")


@dataclass
class DynoWindow:
    """One capture window as read from the dyno: the samples of one profile segment
    (arrays on the window's own time; ``t0`` in s from the first window's start)."""

    t0: float
    rate_hz: float
    channels: dict[str, np.ndarray] = field(default_factory=dict)


#: ``(index, window, t)``: a window just read, with its sample times (s) in the joined capture
WindowHook = Callable[[int, DynoWindow, np.ndarray], None]


#: what the dyno means by each Modbus exception code (docs/dyno.md, "Encoding")
_EXCEPTION_MEANING = {
    1: "illegal function",
    2: "illegal data address: read-only register, part of a value or a gap in the map",
    3: "illegal data value: out of range or not allowed in the dyno's present state",
    4: "device failure",
    6: "device busy",
}


class DynoClient:
    """A connection to one dyno; see the module doc for the sequence.

    Parameters
    ----------
    config : DynoConfig
        Address, timeouts and retries.
    """

    def __init__(self, config: DynoConfig) -> None:
        from pymodbus.client import ModbusTcpClient

        self.config = config
        self.regmap = config.regmap
        self._client = ModbusTcpClient(config.host, port=config.port, timeout=config.timeout, retries=0, reconnect_delay=0)
        self._reconnects = 0
        self._reader: BufferReader | None = None  # the streamed buffer reads, opened at the first capture
        self._heartbeat = (-1, time.monotonic())
        #: the dyno's identification matched the register map: only then is anything written
        self.identified = False
        #: the direction this client last enabled the drive in (speed mode), while it ran since
        self._running_in: Direction | None = None

    # ------------------------------------------------------------ transport
    @property
    def where(self) -> str:
        return f"dyno {self.config.host}:{self.config.port}"

    def _call(self, what: str, fn: Callable[[], ModbusPDU], request: tuple[int, int, int, list[int] | None]
              ) -> ModbusPDU:
        """Run one request with :func:`eol_cal.retry.retry_call`: reconnect on lost connections
        and timeouts; a Modbus exception answer is a refusal, not retried.

        ``request`` is (function code, address, count, words written) for the exchange log.
        """
        from pymodbus.exceptions import ModbusException

        fc, address, count, written = request
        where = f"{self.config.host}:{self.config.port}"

        def attempt(n: int) -> ModbusPDU:
            if not self._client.connected:
                if n:
                    self._reconnects += 1
                if not self._client.connect():
                    raise ConnectionError("cannot connect")
            return fn()

        try:
            # a late answer to a timed-out request would be taken for the next one: start over
            response = retry_call(attempt, retries=self.config.retries, delay_s=self.config.retry_delay,
                                  retry_on=(ModbusException, ConnectionError, OSError),
                                  before_retry=lambda _n, _exc: self._client.close())
        except RetriesExhausted as exc:
            self._client.close()
            log_modbus(where, fc, address, count, written, exception=f"none after {exc.attempts} attempts: {exc.last}")
            raise DynoError(f"{self.where}: {what} failed after {exc.attempts} attempts: {exc.last}") from None
        if response.isError():
            code = getattr(response, "exception_code", None)
            log_modbus(where, fc, address, count, written, exception=code)
            why = _EXCEPTION_MEANING.get(code, "") if code is not None else ""
            raise DynoError(f"{self.where}: {what} refused (Modbus exception {code}{': ' + why if why else ''})")
        log_modbus(where, fc, address, count, written if written is not None else getattr(response, "registers", None))
        return response

    def connect(self) -> dict[str, float | int | str]:
        """Connect and read the identification registers (checking the map version the map expects)."""
        self._running_in = None
        try:
            ident = self.read(self.regmap.group("identification"))
        except DynoError as exc:
            if "refused" not in str(exc):
                raise
            raise DynoError(f"{exc}; is {self.regmap.source} this dyno's register map?") from None
        expected = self.regmap.map_version
        if expected is not None and ident["map_version"] != expected:
            raise DynoError(f"{self.where}: register map version {ident['map_version']}, the register map "
                            f"{self.regmap.name!r} ({self.regmap.source}) expects {expected}")
        self.identified = True
        return ident

    @property
    def reconnects(self) -> int:
        """Connections opened again after a loss (requests and buffer reads)."""
        return self._reconnects + (self._reader.reconnects if self._reader is not None else 0)

    def close(self) -> None:
        self._client.close()
        if self._reader is not None:
            self._reader.close()
            self._reconnects += self._reader.reconnects
            self._reader = None

    def read(self, names: Sequence[str]) -> dict[str, float | int | str]:
        """Read registers ``names`` (neighbours of one table in one request) and decode them."""
        out: dict[str, float | int | str] = {}
        for table, address, count, run in self.regmap.read_runs(names):
            fc = READ_FC[table]
            read = self._client.read_input_registers if fc == 4 else self._client.read_holding_registers
            r = self._call(f"read {','.join(run)}",
                           functools.partial(read, address, count=count, device_id=self.config.device_id),
                           (fc, address, count, None))
            try:
                out.update(self.regmap.unpack(address, r.registers, run))
            except ValueError as exc:
                raise DynoError(f"{self.where}: {exc} (register map {self.regmap.source})") from None
        return out

    def write(self, **values: float | int) -> None:
        """Write registers by name (physical or semantic values); neighbours go out in one FC 16 request."""
        try:
            runs = self.regmap.write_runs(values)
        except ValueError as exc:
            raise DynoError(f"{self.where}: cannot write {exc} (register map {self.regmap.source})") from None
        for address, words, names in runs:
            self._call(f"write {','.join(names)}",
                       functools.partial(self._client.write_registers, address, words, device_id=self.config.device_id),
                       (16, address, len(words), words))

    def status(self) -> dict[str, float | int | str]:
        """The status registers; raises when the dyno's heartbeat stopped for ``HEARTBEAT_STALL_S``."""
        st = self.read(self.regmap.group("status"))
        now = time.monotonic()
        if st["heartbeat"] != self._heartbeat[0]:
            self._heartbeat = (int(st["heartbeat"]), now)
        elif now - self._heartbeat[1] > HEARTBEAT_STALL_S:
            raise DynoError(f"{self.where}: dyno controller not running "
                            f"(heartbeat stuck at {st['heartbeat']} for {now - self._heartbeat[1]:.1f} s)")
        return st

    def check_faults(self, st: dict, what: str) -> None:
        faults = int(st["faults"])
        if faults:
            raise DynoError(f"{self.where}: fault {'+'.join(fault_names(faults))} while {what} (faults=0x{faults:04x})")
        if st["drive_state"] == DriveState.TRIPPED:
            raise DynoError(f"{self.where}: drive tripped while {what}")

    # ------------------------------------------------------------ operations
    def set_point(self, seg: DynoSetpoint, wait: bool = True, status: dict | None = None) -> float:
        """Command one segment's load, direction and speed; return when the dyno is at speed
        (``wait``), else at once (a capture armed next starts by itself at speed).

        ``status``: the status registers just read (else they are read). A drive this client
        enabled in the same direction and that runs since (ramping or at speed) gets the new
        speed and load alone: mode, direction, enable and watchdog stand (three requests fewer
        between two segments, each a round trip on the dyno's network). Returns the time the
        ramp takes (s), from the speed the dyno had.
        """
        cfg = self.config
        st = self.status() if status is None else status
        self.check_faults(st, "preparing")
        direction = Direction.REVERSE if seg.speed_rpm < 0 else Direction.FORWARD
        kind, value = seg.command()
        current_dir = Direction.REVERSE if float(st["speed"]) < 0 else Direction.FORWARD
        running = int(st["drive_state"]) in (DriveState.RAMPING, DriveState.AT_SPEED)
        if abs(float(st["speed"])) > rm.STANDSTILL_RPM and direction != current_dir:
            # reversing goes through standstill; the dyno refuses a direction flip while spinning
            self.write(speed_setpoint=0.0)
            self.wait_standstill(abs(float(st["speed"])) / seg.ramp_rpm_s + cfg.settle_timeout, "stopping to reverse",
                                 float(st["speed"]))
        same = running and self._running_in == direction
        self._running_in = None  # until the drive is enabled again below
        if not same:
            self.write(mode=Mode.SPEED, direction=direction)
        self.write(speed_setpoint=abs(seg.speed_rpm), ramp=seg.ramp_rpm_s, dut_cmd_kind=int(kind), dut_cmd=value)
        if not same:
            self.write(enable=Switch.ON, watchdog_ms=cfg.watchdog_ms)
        self._running_in = direction
        ramp_time = abs(seg.speed_rpm - float(st["speed"])) / seg.ramp_rpm_s
        if wait:
            self.wait(lambda s: s["drive_state"] == DriveState.AT_SPEED, ramp_time + cfg.settle_timeout,
                      f"ramping to {seg.speed_rpm:g} rpm")
        return ramp_time

    def wait(self, cond: Callable[[dict], bool], timeout: float, what: str,
             interval: Callable[[dict], float] | None = None) -> dict:
        """Poll the status until ``cond(status)``; every ``poll_interval`` s, or as ``interval(status)`` says."""
        end = time.monotonic() + timeout
        while True:
            st = self.status()
            self.check_faults(st, what)
            if cond(st):
                return st
            if time.monotonic() > end:
                raise DynoError(f"{self.where}: timeout after {timeout:.1f} s {what} (speed {float(st['speed']):.1f} rpm, "
                                f"drive state {DriveState(int(st['drive_state'])).name})")
            time.sleep(self.config.poll_interval if interval is None else interval(st))

    def wait_standstill(self, timeout: float, what: str, speed: float | None = None) -> dict:
        """Poll until the shaft is within :data:`~eol_cal.dyno.registers.STANDSTILL_RPM` of zero;
        faster as it gets near, when the ramp rate it stops at is known from two polls."""
        seen: list[tuple[float, float]] = [] if speed is None else [(time.monotonic(), abs(speed))]

        def interval(s: dict) -> float:
            now, v = time.monotonic(), abs(float(s["speed"]))
            seen.append((now, v))
            (t0, v0), (t1, v1) = seen[0], seen[-1]
            if t1 <= t0 or v1 >= v0:
                return self.config.poll_interval
            left = (v1 - rm.STANDSTILL_RPM) * (t1 - t0) / (v0 - v1)
            return min(self.config.poll_interval, max(left - self.config.poll_interval / 2, READY_POLL_S))

        return self.wait(lambda s: abs(float(s["speed"])) <= rm.STANDSTILL_RPM, timeout, what, interval)

    def capture(self, n_samples: int, rate_hz: int) -> dict:
        """Start a capture of ``n_samples`` at ``rate_hz`` (Hz) and wait until it is ready."""
        self.write(capture_rate=rate_hz, capture_length=n_samples)
        self.write(capture_start=CaptureCommand.ARM)

        def ready(s: dict) -> bool:
            if s["capture_state"] == CaptureState.ERROR:
                raise DynoError(f"{self.where}: capture ended in the error state")
            return s["capture_state"] == CaptureState.READY

        st = self.wait(ready, n_samples / rate_hz + self.config.capture_timeout, "capturing")
        if int(st["capture_count"]) != n_samples:
            raise DynoError(f"{self.where}: capture holds {st['capture_count']} samples, {n_samples} requested")
        return st

    def arm(self, n_samples: int, rate_hz: int) -> None:
        """Set the capture's rate (Hz) and length and arm it: one request where the map places the
        start right after the other two (a request's registers are written in address order),
        else the start in a request of its own after them."""
        values = {"capture_rate": rate_hz, "capture_length": n_samples, "capture_start": CaptureCommand.ARM}
        try:
            runs = self.regmap.write_runs(values)
        except ValueError:  # a register the map lacks: write() below says which
            runs = []
        if len(runs) == 1 and runs[0][2][-1] == "capture_start":
            self.write(**values)
        else:
            self.write(capture_rate=rate_hz, capture_length=n_samples)
            self.write(capture_start=CaptureCommand.ARM)

    def record(self, n_samples: int, rate_hz: int, names: Sequence[str], progress: ProgressFn | None = None,
               ramp_s: float = 0.0, skip: int = 0, on_ready: Callable[[dict], object] | None = None
               ) -> dict[str, np.ndarray]:
        """Arm a capture of ``n_samples`` at ``rate_hz`` (Hz) and read channels ``names`` (those the
        buffer holds; ``torque`` and ``iq_ref`` required) while it records (:class:`StreamReader`);
        return when every sample is read.

        The capture starts by itself once the shaft is at speed: ``ramp_s`` (s) is the ramp still
        to go, added to the wait. The first ``skip`` samples are recorded but never read (a
        lead-in). ``on_ready(status)`` is called as soon as the capture is ready, while its last
        samples are still read (the shaft may ramp to the next point meanwhile; nothing may arm
        another capture before this returns). Returns the channels as :meth:`read_buffer`,
        samples ``skip`` on.
        """
        if not 0 <= skip < n_samples:
            raise ValueError(f"skip {skip} of a capture of {n_samples} samples")
        cfg = self.config
        self.arm(n_samples, rate_hz)
        fill = BufferFill(n_samples)
        reader: Stream | None = None
        if self._reader is None:
            self._reader = BufferReader(cfg)

        def recorded(s: dict) -> bool:
            nonlocal reader
            state = s["capture_state"]
            if state == CaptureState.ERROR:
                raise DynoError(f"{self.where}: capture ended in the error state")
            count = int(s["capture_count"]) if state in (CaptureState.RUNNING, CaptureState.READY) else 0
            if reader is None and count > 0:
                assert self._reader is not None  # opened above, before the wait
                reader = self._reader.stream(self.recorded_channels(s, names), fill, rate_hz, progress, skip)
            if state == CaptureState.READY and count != n_samples:
                raise DynoError(f"{self.where}: capture holds {count} samples, {n_samples} requested")
            fill.update(count)
            return state == CaptureState.READY

        def interval(s: dict) -> float:
            # poll faster near the end: the capture's last chunk is read once it is ready
            left = (n_samples - fill.count) / rate_hz if s["capture_state"] == CaptureState.RUNNING else 1.0
            return min(cfg.poll_interval, max(left - cfg.poll_interval / 2, READY_POLL_S))

        try:
            st = self.wait(recorded, ramp_s + cfg.settle_timeout + n_samples / rate_hz + cfg.capture_timeout, "capturing",
                           interval)
            if on_ready is not None:
                on_ready(st)
            # the wait ended on READY with n_samples (>= 1) samples recorded: recorded opened the stream
            assert reader is not None
            return reader.result(cfg.capture_timeout)
        except TransferError as exc:
            raise DynoError(f"{self.where}: reading the capture buffer failed: {exc}") from None
        except BaseException:
            if reader is not None:
                reader.abandon("the capture failed")
            raise

    def recorded_channels(self, st: dict, names: Sequence[str]) -> list[str]:
        """Of channels ``names``, those the buffer holds (status ``capture_channels``); refuses a
        buffer without ``torque`` or ``iq_ref``."""
        known = self.regmap.channels
        available = int(st["capture_channels"])
        want = [c for c in names if available & rm.channel_bit(known[c])]
        for required in ("torque", "iq_ref"):
            if required not in want:
                raise DynoError(f"{self.where}: capture has no {required} channel")
        return want

    def read_buffer(self, names: Sequence[str], n_samples: int, progress: ProgressFn | None = None) -> dict[str, np.ndarray]:
        """Read channels ``names`` (canonical names) plus the digital channel from the buffer.

        Returns the analog channels (float64 from f32) and ``enc_a``, ``enc_b``, ``hall``.
        """
        try:
            result, reconnects = read_capture_buffer(self.config, names, n_samples, progress)
        except TransferError as exc:
            raise DynoError(f"{self.where}: reading the capture buffer failed: {exc}") from None
        self._reconnects += reconnects
        return result

    def safe_state(self) -> str | None:
        """Speed set point 0, capture aborted, drive disabled. Returns None or why it failed.

        Nothing is written to a dyno whose identification did not match the register map: on
        another layout those addresses are other registers.
        """
        self._running_in = None
        try:
            if not self.identified:
                self.connect()
            self.write(speed_setpoint=0.0)
            self.write(capture_start=CaptureCommand.ABORT)
            self.write(enable=Switch.OFF)
        except DynoError as exc:
            return str(exc)
        return None


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

    ``before_capture`` is called (and waited for) right before the first capture is armed, while
    the shaft ramps to the first segment; ``after_capture`` right after the last window was read
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
                before_capture()
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
    from eol_cal.capture import validate, write_capture

    capture = validate(capture)
    if out is not None:
        write_capture(capture, out)
    return capture
