"""Dyno client: one Modbus TCP connection to a dyno and the requests of a test profile's sequence.

The sequence per segment: set the load command, direction and speed set point, enable, wait
until the dyno reports "at speed", start a capture, poll until the buffer is ready, read every
channel through the paged window and check it. Which registers those are, and how their values
are encoded, is the dyno's register map (:mod:`.regmap`, from a map file: ``DynoConfig.register_map``).
The profile as set points is :mod:`eol_cal.dyno.setpoints`; the whole profile run and the
segments joined into one capture, :mod:`eol_cal.dyno.profile_run`.

Safety: whatever goes wrong (timeout, lost connection, fault bit, bad data, Ctrl-C) the profile
run sets the speed to zero and disables the drive (:meth:`DynoClient.safe_state`) and raises
:class:`DynoError`; the capture file is written (atomically) only after every segment was read
and validated.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from eol_cal.infra.address import parse_modbus_address
from eol_cal.dyno import registers as rm
from eol_cal.dyno.regmap import READ_FC
from eol_cal.dyno.registers import (CaptureCommand, CaptureState, Direction, DriveState, Mode, Switch,
                                    fault_names)
from eol_cal.dyno.setpoints import DynoSetpoint
from eol_cal.dyno.transfer import BufferFill, BufferReader, DynoConfig, ProgressFn, Stream, TransferError, read_capture_buffer
from eol_cal.errors import EolCalError
from eol_cal.infra.exchange_log import log_modbus
from eol_cal.infra.retry import RetriesExhausted, retry_call

if TYPE_CHECKING:
    from pymodbus.pdu import ModbusPDU

#: a heartbeat that does not change for this long means the dyno's controller stopped (s)
HEARTBEAT_STALL_S = 1.0
#: status poll period (s) when a capture is about to be ready
READY_POLL_S = 0.002


class DynoError(EolCalError):
    """The dyno run failed; the drive was sent to the safe state (exit code 2)."""


def parse_address(text: str) -> tuple[str, int]:
    """The dyno's ``HOST`` or ``HOST:PORT`` -> (host, port), Modbus TCP's port 502 when none is
    given; a bad address is an :class:`InputError`."""
    return parse_modbus_address(text, "address")



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

        from eol_cal.dyno.pdu import fast_reads

        self.config = config
        self.regmap = config.regmap
        self._client = ModbusTcpClient(config.host, port=config.port, timeout=config.timeout, retries=0, reconnect_delay=0)
        fast_reads(self._client)
        self._reconnects = 0
        self._reader: BufferReader | None = None  # the streamed buffer reads, opened at the first capture
        self._heartbeat = (-1, time.monotonic())
        #: the dyno's identification matched the register map: only then is anything written
        self.identified = False
        #: the direction this client last enabled the drive in (speed mode), while it ran since
        self._running_in: Direction | None = None
        # the block reads of each set of registers read (the status poll's, ~100 a second, the same each time)
        self._runs: dict[tuple[str, ...], list[tuple[str, int, int, tuple[str, ...]]]] = {}
        self._status = self.regmap.group("status")

    # ------------------------------------------------------------ transport
    @property
    def where(self) -> str:
        return f"dyno {self.config.host}:{self.config.port}"

    def _call(self, what: str, fn: Callable[[], ModbusPDU], request: tuple[int, int, int, list[int] | None]
              ) -> ModbusPDU:
        """Run one request with :func:`eol_cal.infra.retry.retry_call`: reconnect on lost connections
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
        key = tuple(names)
        runs = self._runs.get(key)
        if runs is None:
            runs = self._runs[key] = self.regmap.read_runs(key)
        for table, address, count, run in runs:
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
        st = self.read(self._status)
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
        buffer holds; ``torque`` and ``iq_ref`` required) while it records (:class:`~eol_cal.dyno.transfer.BufferReader`);
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
