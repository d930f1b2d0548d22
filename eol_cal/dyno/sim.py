"""Dyno simulator: a real pymodbus TCP server speaking the register map of :mod:`.registers`.

The simulated dyno holds a speed set point with a ramp, passes the load command to the motor
under test and, when a capture is started, asks a *capture source* for the recording: by
default the built-in plant, with the motor's compensation taken from the ECU simulator's active
flash bank (``flash_file``), so a flash changes what the next capture shows.

Faults on demand (register ``sim_fault``, :meth:`DynoSim.inject`, or a :class:`FaultPlan`
that fires at the N-th capture or the N-th window read): disconnect (every connection dropped
and requests ignored for a while), over-speed trip and torque-sensor fault (the drive trips,
a running capture ends in the error state).

The pymodbus 3.16 server is fed a :class:`pymodbus.simulator.SimDevice` (the datastore API
3.16 recommends; the ``ModbusDeviceContext`` classes are deprecated shims) whose ``action``
hook sees every request: it validates and applies writes and refreshes what a read returns.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from eol_cal.capture.model import Capture
from eol_cal.dyno import registers as rm
from eol_cal.dyno.registers import (
    BY_NAME,
    CaptureState,
    DriveState,
    DutCmdKind,
    Fault,
    Interlock,
    Mode,
    SimFault,
)

#: speed tolerance for "at speed": max(SPEED_TOL_RPM, SPEED_TOL_REL * |set point|)
SPEED_TOL_RPM = 1.0
SPEED_TOL_REL = 0.005
#: deceleration of a disabled or tripped drive (rpm/s)
COAST_DECEL = 2000.0
MAX_CAPTURE_SAMPLES = 4_000_000
#: firmware mode without a valid parameter bank: the raw encoder angle, no compensation
NO_BLOCK_MODE = "raw"

_FC_READ = (3, 4)


@dataclass(frozen=True)
class SegmentRequest:
    """What the dyno asks its capture source to record.

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
    mode : str
        ``raw``, ``estimated`` or ``compensated``: the ECU's angle source / compensation.
    block : object or None
        The active parameter block (:class:`eol_cal.firmware.block.ParamBlock`) or None.
    """

    speed_rpm: float
    dut_cmd_kind: DutCmdKind
    dut_cmd: float
    n_samples: int
    rate_hz: float
    serial: str
    seed: int | None
    capture_index: int
    mode: str = NO_BLOCK_MODE
    block: object | None = None

    @property
    def seconds(self) -> float:
        """Capture duration (s)."""
        return self.n_samples / self.rate_hz


#: a capture source: segment request -> capture at ``rate_hz`` with ``n_samples`` samples
CaptureSource = Callable[[SegmentRequest], Capture]


@dataclass(frozen=True)
class FaultPlan:
    """A fault that fires by itself.

    Attributes
    ----------
    kind : SimFault
        The fault.
    at : str
        ``capture`` (fires when capture number ``index`` starts running) or ``read`` (fires on
        the ``index``-th read of the capture window since start-up).
    index : int
        1-based count of the event above.
    arg_ms : int
        Disconnect duration (ms) for :attr:`SimFault.DISCONNECT`.
    """

    kind: SimFault
    at: str = "capture"
    index: int = 1
    arg_ms: int = 500


def parse_fault_plan(text: str) -> FaultPlan:
    """``KIND[@capture:N|@read:N][/MS]`` -> :class:`FaultPlan` (e.g. ``disconnect@read:5/300``)."""
    from eol_cal.errors import InputError

    names = {"disconnect": SimFault.DISCONNECT, "over-speed": SimFault.OVER_SPEED, "torque-sensor": SimFault.TORQUE_SENSOR}
    spec, _, ms = text.partition("/")
    kind, _, when = spec.partition("@")
    if kind not in names:
        raise InputError(None, "--fault", f"unknown fault {kind!r}; known: {', '.join(names)}")
    at, index = "capture", 1
    if when:
        at, _, n = when.partition(":")
        if at not in ("capture", "read") or not n.isdigit() or int(n) < 1:
            raise InputError(None, "--fault", f"bad trigger {when!r}; use capture:N or read:N (N >= 1)")
        index = int(n)
    if ms and (not ms.isdigit() or not 0 < int(ms) < 65536):
        raise InputError(None, "--fault", f"bad duration {ms!r}; milliseconds 1..65535")
    return FaultPlan(names[kind], at, index, int(ms) if ms else 500)


def block_mode(block: object | None) -> str:
    """ECU mode the parameter block selects: its flags, or :data:`NO_BLOCK_MODE` without one."""
    if block is None:
        return NO_BLOCK_MODE
    from eol_cal.plant.simulate import mode_of_block

    return mode_of_block(block)


def active_block_from_flash(flash_file: str | Path | None) -> object | None:
    """The active parameter block in the ECU simulator's flash file, or None without a valid bank
    (or before the ECU simulator created the file)."""
    if flash_file is None or not Path(flash_file).exists():
        return None
    from eol_cal.ecu.flash import active_block_from_file
    from eol_cal.firmware.block import unpack

    data = active_block_from_file(flash_file)
    return None if data is None else unpack(data, f"{flash_file} (active bank)")


def i_qo_of(req: SegmentRequest, kt: float) -> float:
    """Nominal q current (A) a segment request asks for."""
    return req.dut_cmd if req.dut_cmd_kind == DutCmdKind.IQ else req.dut_cmd / kt


def synthetic_source(req: SegmentRequest) -> Capture:
    """Capture source without JAX: the analytic model of :mod:`eol_cal.capture.synthetic`.

    It models quantisation ripple and the 6th harmonic but no ECU: ``req.mode`` and the block do
    not change what it shows (use :func:`plant_source` for that).
    """
    from eol_cal.capture.synthetic import synthetic_capture
    from eol_cal.motor import load_motor

    motor = load_motor("paper")
    return synthetic_capture(
        rpm=req.speed_rpm,
        i_qo=i_qo_of(req, motor.kt),
        seconds=req.n_samples / req.rate_hz,
        fs=req.rate_hz,
        seed=(req.seed or 0) * 1000 + req.capture_index,
        theta_r0=0.7 * req.capture_index,
        serial=req.serial,
    )


def plant_source(spec_for: Callable[[SegmentRequest], object] | None = None) -> CaptureSource:
    """Capture source backed by the built-in plant (:func:`eol_cal.plant.simulate.simulate`).

    Parameters
    ----------
    spec_for : callable, optional
        ``request -> PlantSpec``: the motor on the dyno (default: the plant's motor drawn from
        the request's seed and serial). The ECU mode and block come from the request.
    """

    def source(req: SegmentRequest) -> Capture:
        from eol_cal.plant.profile import Profile, Segment
        from eol_cal.plant.simulate import simulate

        spec = (spec_for or default_plant_spec)(req)
        f_tick = spec.motor.f_pwm
        step = f_tick / req.rate_hz
        if abs(step - round(step)) > 1e-9:
            raise ValueError(f"capture rate {req.rate_hz} Hz does not divide the plant's {f_tick} Hz")
        step = int(round(step))
        iq = i_qo_of(req, spec.motor.kt)
        profile = Profile("dyno", (Segment(speed_rpm=req.speed_rpm, seconds=req.n_samples * step / f_tick, iq=iq),))
        seed = (req.seed or 0) * 1000 + req.capture_index
        result = simulate(spec, profile, mode=req.mode, blocks=req.block, seed=seed)[0]
        cap = result.capture
        # the plant runs at the PWM tick; the dyno's DAQ keeps every step-th sample
        channels = {k: v[::step][: req.n_samples] for k, v in cap.channels.items()}
        return Capture(cap.t[::step][: req.n_samples], channels, dict(cap.metadata), dict(cap.truth), source="<plant>")

    return source


def default_plant_spec(req: SegmentRequest, preset: str = "paper"):
    """The motor on the dyno: the plant preset, or with a seed a motor drawn from production
    tolerances around it (:mod:`eol_cal.plant.variation`)."""
    from eol_cal.plant.presets import preset_spec

    spec = preset_spec(preset, serial=req.serial)
    if req.seed is None:
        return spec
    from eol_cal.plant import variation

    return variation.vary(spec, req.seed)


class DynoSim:
    """State and behaviour of the simulated dyno (one motor under test).

    Parameters
    ----------
    source : CaptureSource
        Produces the recording of each capture.
    serial : str
        Serial of the motor on the dyno.
    poles, encoder_ppr : int
        The motor's poles P and encoder pulses per revolution N_enc.
    kt : float
        Torque constant (N*m/A), to show a shaft torque for an i_qo command.
    seed : int or None
        Motor variation seed passed to the source.
    flash_file : path or None
        ECU simulator flash file; its active bank is read at every capture start.
    max_speed : float
        Over-speed trip threshold (rpm).
    tick_hz : int
        Internal sample clock (Hz); capture rates must divide it.
    faults : sequence of FaultPlan
        Faults that fire by themselves.
    """

    def __init__(
        self,
        source: CaptureSource,
        *,
        serial: str = "M-0001",
        poles: int = 6,
        encoder_ppr: int = 64,
        kt: float = 0.04905,
        seed: int | None = None,
        flash_file: str | Path | None = None,
        max_speed: float = 3000.0,
        tick_hz: int = 20000,
        faults: tuple[FaultPlan, ...] | list[FaultPlan] = (),
    ) -> None:
        self.source = source
        self.serial = serial
        self.poles = poles
        self.encoder_ppr = encoder_ppr
        self.kt = kt
        self.seed = seed
        self.flash_file = flash_file
        self.max_speed = max_speed
        self.tick_hz = tick_hz
        self.fault_plans = list(faults)

        self.mode = Mode.OFF
        self.enabled = False
        self.stopping = False
        self.direction = 0
        self.setpoint = 0.0
        self.ramp = 100.0
        self.dut_cmd_kind = DutCmdKind.TORQUE
        self.dut_cmd = 0.0
        self.capture_rate = 10000
        self.capture_length = 10000
        self.watchdog_ms = 0
        self.speed = 0.0
        self.temperature = 25.0
        self.faults = Fault(0)
        self.interlocks = Interlock.ALL
        self.capture_state = CaptureState.IDLE
        self.capture_seq = 0
        self.captures_started = 0
        self.window_reads = 0
        self.buffer: dict[int, np.ndarray] = {}  # channel id -> register words (uint16)
        self.buffer_count = 0
        self.page: list[int] = []
        self.buf_channel = 0
        self.buf_offset = 0
        self.disconnect_until = 0.0
        self.last_capture: Capture | None = None
        #: every write the dyno accepted: (monotonic time, register name, value), for tests
        self.log: list[tuple[float, str, float | int | str]] = []

        self._t0 = time.monotonic()
        #: a value here freezes the heartbeat (a hung dyno controller), for tests
        self.heartbeat_frozen: int | None = None
        self._t_last = self._t0
        self._last_request = self._t0
        self._capture_job: asyncio.Future | None = None
        self._capture_token = 0
        self._server = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # ------------------------------------------------------------------ physics
    def _target(self) -> float:
        if self.enabled and not self.stopping and self.mode == Mode.SPEED and not self._tripped():
            return self.setpoint * (-1.0 if self.direction else 1.0)
        return 0.0

    def _tripped(self) -> bool:
        return bool(self.faults & (Fault.OVER_SPEED | Fault.TORQUE_SENSOR | Fault.COMM_WATCHDOG | Fault.DRIVE))

    def at_speed(self) -> bool:
        target = self._target()
        tol = max(SPEED_TOL_RPM, SPEED_TOL_REL * abs(target))
        return self.enabled and abs(self.speed - target) <= tol

    def drive_state(self) -> DriveState:
        if self._tripped():
            return DriveState.TRIPPED
        if self.stopping:
            return DriveState.STOPPING
        if not self.enabled:
            return DriveState.DISABLED
        return DriveState.AT_SPEED if self.at_speed() else DriveState.RAMPING

    def shaft_torque(self) -> float:
        """Shaft torque (N*m) shown in the status registers."""
        if self.faults & Fault.TORQUE_SENSOR:
            return math.nan
        if not self.enabled or self.mode != Mode.SPEED:
            return 0.0
        return self.dut_cmd if self.dut_cmd_kind == DutCmdKind.TORQUE else self.kt * self.dut_cmd

    def advance(self, now: float | None = None) -> None:
        """Move the simulated time forward to ``now`` (monotonic s)."""
        now = time.monotonic() if now is None else now
        dt = max(0.0, now - self._t_last)
        self._t_last = now
        target = self._target()
        rate = self.ramp if (self.enabled and not self._tripped()) else max(self.ramp, COAST_DECEL)
        step = rate * dt
        self.speed = target if abs(target - self.speed) <= step else self.speed + math.copysign(step, target - self.speed)
        if self.stopping and self.speed == 0.0:
            self.stopping = False
            self.enabled = False
        if abs(self.speed) > self.max_speed:
            self._trip(Fault.OVER_SPEED)
        if self.watchdog_ms and self.enabled and now - self._last_request > self.watchdog_ms / 1000.0:
            self._trip(Fault.COMM_WATCHDOG)
        if self.capture_state == CaptureState.ARMED and self.at_speed():
            self._start_capture()
        elif self.capture_state in (CaptureState.ARMED, CaptureState.RUNNING) and not self.enabled:
            self._capture_failed()

    def _trip(self, fault: Fault) -> None:
        self.faults |= fault
        self.enabled = False
        self.stopping = False
        self.setpoint = 0.0  # a tripped dyno needs a fresh set point before it spins again
        if self.capture_state in (CaptureState.ARMED, CaptureState.RUNNING):
            self._capture_failed()

    def _capture_failed(self) -> None:
        self._capture_token += 1  # a job still running finishes into the void
        self.capture_state = CaptureState.ERROR
        self.faults |= Fault.CAPTURE
        self.buffer, self.buffer_count = {}, 0

    # ------------------------------------------------------------------ faults
    def inject(self, kind: SimFault, arg_ms: int = 500) -> None:
        """Inject a fault now (call on the server's event loop, e.g. ``DynoSimThread.call``)."""
        kind = SimFault(kind)
        if kind == SimFault.DISCONNECT:
            self.disconnect_until = time.monotonic() + arg_ms / 1000.0
            self._drop_connections()
        elif kind == SimFault.OVER_SPEED:
            self.speed = math.copysign(self.max_speed * 1.05, self.speed or 1.0)
            self._trip(Fault.OVER_SPEED)
        elif kind == SimFault.TORQUE_SENSOR:
            self._trip(Fault.TORQUE_SENSOR)
        self.log.append((time.monotonic(), "fault", kind.name))

    def _fire_plans(self, at: str, count: int) -> None:
        for plan in list(self.fault_plans):
            if plan.at == at and plan.index == count:
                self.fault_plans.remove(plan)
                self.inject(plan.kind, plan.arg_ms)

    def _drop_connections(self) -> None:
        server = self._server
        if server is None:
            return
        for conn in list(server.active_connections.values()):
            conn.close()

    def trace_packet(self, sending: bool, data: bytes) -> bytes:
        """pymodbus hook on every frame: while 'disconnected', drop requests and connections."""
        if not sending and time.monotonic() < self.disconnect_until:
            assert self._loop is not None
            self._loop.call_soon(self._drop_connections)
            return b""
        return data

    # ------------------------------------------------------------------ captures
    def _start_capture(self) -> None:
        self.captures_started += 1
        self.capture_state = CaptureState.RUNNING
        block = active_block_from_flash(self.flash_file)
        request = SegmentRequest(
            speed_rpm=self._target(),
            dut_cmd_kind=self.dut_cmd_kind,
            dut_cmd=self.dut_cmd,
            n_samples=self.capture_length,
            rate_hz=float(self.capture_rate),
            serial=self.serial,
            seed=self.seed,
            capture_index=self.captures_started,
            mode=block_mode(block),
            block=block,
        )
        self._capture_token += 1
        token = self._capture_token
        assert self._loop is not None
        job = self._loop.run_in_executor(None, self.source, request)
        job.add_done_callback(lambda f: self._capture_done(f, token, request))
        self._capture_job = job
        self._fire_plans("capture", self.captures_started)

    def _capture_done(self, job: asyncio.Future, token: int, request: SegmentRequest) -> None:
        if token != self._capture_token or self.capture_state != CaptureState.RUNNING:
            return
        exc = job.exception()
        if exc is not None:
            self.log.append((time.monotonic(), "capture_error", repr(exc)))
            self._capture_failed()
            return
        capture: Capture = job.result()
        try:
            self.buffer = capture_to_buffer(capture, request.n_samples)
        except ValueError as err:
            self.log.append((time.monotonic(), "capture_error", str(err)))
            self._capture_failed()
            return
        self.buffer_count = request.n_samples
        self.last_capture = capture
        if "temp" in capture.channels:
            self.temperature = float(np.mean(capture.channels["temp"]))
        self.capture_seq = (self.capture_seq + 1) & 0xFFFF
        self.capture_state = CaptureState.READY

    def _fill_page(self) -> None:
        words = self.buffer.get(self.buf_channel)
        if words is None:
            self.page = []
            return
        per = 1 if self.buf_channel == rm.DIGITAL_CHANNEL_ID else 2
        first = self.buf_offset * per
        self.page = words[first : first + rm.WINDOW_REGS].tolist()

    # ------------------------------------------------------------------ registers
    def status_values(self) -> dict[str, float | int | str]:
        """Current value of every read-only register except the window."""
        mask = 0
        for cid in self.buffer:
            mask |= rm.channel_bit(cid)
        return {
            "map_version": rm.MAP_VERSION,
            "dut_serial": self.serial,
            "dut_poles": self.poles,
            "dut_encoder_ppr": self.encoder_ppr,
            "dut_kt": self.kt,
            "max_speed": self.max_speed,
            "tick_hz": self.tick_hz,
            "speed": self.speed,
            "torque": self.shaft_torque(),
            "temperature": self.temperature,
            "faults": int(self.faults),
            "interlocks": int(self.interlocks),
            "drive_state": int(self.drive_state()),
            "capture_state": int(self.capture_state),
            "capture_count": self.buffer_count if self.capture_state == CaptureState.READY else 0,
            "capture_channels": mask,
            "heartbeat": self.heartbeat_frozen if self.heartbeat_frozen is not None else int((time.monotonic() - self._t0) * 100) & 0xFFFF,
            "capture_seq": self.capture_seq,
        }

    def control_values(self) -> dict[str, float | int]:
        return {
            "mode": int(self.mode),
            "enable": int(self.enabled),
            "stop": 0,
            "direction": self.direction,
            "speed_setpoint": self.setpoint,
            "ramp": self.ramp,
            "dut_cmd_kind": int(self.dut_cmd_kind),
            "dut_cmd": self.dut_cmd,
            "capture_rate": self.capture_rate,
            "capture_length": self.capture_length,
            "capture_start": 0,
            "fault_reset": 0,
            "watchdog_ms": self.watchdog_ms,
            "buf_channel": self.buf_channel,
            "buf_offset": self.buf_offset,
            "sim_fault": 0,
            "sim_fault_arg": 0,
        }

    def simdevice(self):
        """The pymodbus :class:`SimDevice` backing the server (one shared register space)."""
        from pymodbus.simulator import DataType, SimData, SimDevice

        data = []
        values = {**self.status_values(), **self.control_values()}
        for reg in rm.REGISTERS:
            if reg.type == "words":
                data.append(SimData(reg.address, count=reg.count, values=0, datatype=DataType.REGISTERS, readonly=True))
            else:
                data.append(
                    SimData(reg.address, values=rm.encode(reg.name, values[reg.name]), datatype=DataType.REGISTERS, readonly=not reg.writable)
                )
        # id 0: answer every unit id, as a TCP device usually does
        return SimDevice(0, simdata=data, action=self.action)

    async def action(
        self, function_code: int, start_address: int, address: int, count: int, registers: list[int], set_values
    ):
        """pymodbus hook, called for every request before it touches ``registers``."""
        from pymodbus.constants import ExcCodes

        now = time.monotonic()
        self._last_request = now
        self.advance(now)
        end = address + count
        if function_code in _FC_READ:
            if address < rm.WINDOW_ADDR + rm.WINDOW_REGS and end > rm.WINDOW_ADDR:
                self.window_reads += 1
                self._fire_plans("read", self.window_reads)
                if time.monotonic() < self.disconnect_until:
                    return ExcCodes.DEVICE_BUSY  # the connection is being dropped anyway
                lo = max(address, rm.WINDOW_ADDR) - rm.WINDOW_ADDR
                hi = min(end, rm.WINDOW_ADDR + rm.WINDOW_REGS) - rm.WINDOW_ADDR
                chunk = self.page[lo:hi]
                chunk += [0] * (hi - lo - len(chunk))
                base = rm.WINDOW_ADDR - start_address
                registers[base + lo : base + hi] = chunk
            if address < rm.WINDOW_ADDR:
                self._refresh(registers, start_address, address, min(end, rm.WINDOW_ADDR), self.status_values())
            return None
        if set_values is None:
            return None
        return self._write(address, list(set_values), set_values, registers, start_address) or None

    @staticmethod
    def _refresh(registers: list[int], start: int, lo: int, hi: int, values: dict) -> None:
        for name, value in values.items():
            reg = BY_NAME[name]
            if reg.address < hi and reg.address + reg.count > lo:
                i = reg.address - start
                registers[i : i + reg.count] = rm.encode(name, value)

    def _write(self, address: int, words: list[int], set_values, registers: list[int], start: int):
        from pymodbus.constants import ExcCodes

        end = address + len(words)
        # A write must cover whole values: half of an f32 would change it to garbage.
        new: dict[str, float | int | str] = {}
        for reg in rm.REGISTERS:
            if reg.address < end and reg.address + reg.count > address:
                if reg.address < address or reg.address + reg.count > end or not reg.writable:
                    return ExcCodes.ILLEGAL_ADDRESS
                i = reg.address - address
                new[reg.name] = rm.decode(reg.name, words[i : i + reg.count])
        err = self._apply(new)
        if err:
            return err
        # self-clearing command registers read back 0
        for name in ("stop", "capture_start", "fault_reset", "sim_fault"):
            if name in new:
                set_values[BY_NAME[name].address - address] = 0
        return None

    def _apply(self, new: dict[str, float | int | str]):
        """Validate a write as a whole, then apply it; a Modbus exception code on refusal."""
        from pymodbus.constants import ExcCodes

        bad = ExcCodes.ILLEGAL_VALUE
        if "mode" in new and new["mode"] not in (0, 1):
            return bad
        for name in ("speed_setpoint", "ramp", "dut_cmd"):
            if name in new and not math.isfinite(float(new[name])):
                return bad
        if "speed_setpoint" in new and not 0.0 <= float(new["speed_setpoint"]) <= self.max_speed:
            return bad
        if "ramp" in new and float(new["ramp"]) <= 0.0:
            return bad
        if "direction" in new and new["direction"] not in (0, 1):
            return bad
        if "dut_cmd_kind" in new and new["dut_cmd_kind"] not in (0, 1):
            return bad
        if "capture_rate" in new and (int(new["capture_rate"]) <= 0 or self.tick_hz % int(new["capture_rate"])):
            return bad
        if "capture_length" in new and not 1 <= int(new["capture_length"]) <= MAX_CAPTURE_SAMPLES:
            return bad
        if new.get("enable") == 1 and (self.interlocks != Interlock.ALL or self._tripped()):
            return bad
        if new.get("capture_start") not in (None, 0, 1, 2):
            return bad
        if new.get("capture_start") == 1 and not self.enabled:
            return bad
        if "buf_channel" in new and new["buf_channel"] not in (0, rm.DIGITAL_CHANNEL_ID, *rm.ANALOG_CHANNELS):
            return bad
        if "sim_fault" in new and new["sim_fault"] not in tuple(int(k) for k in SimFault):
            return bad
        if "direction" in new and new["direction"] != self.direction and abs(self.speed) > rm.STANDSTILL_RPM and self.enabled:
            return bad  # reversing a spinning shaft goes through zero speed: stop first
        now = time.monotonic()
        for name, value in new.items():
            self.log.append((now, name, value))
        if new.get("fault_reset") == 1:
            self.faults = Fault(0)
            if self.capture_state == CaptureState.ERROR:
                self.capture_state = CaptureState.IDLE
        for name in ("mode", "direction", "dut_cmd_kind"):
            if name in new:
                setattr(self, name, type(getattr(self, name))(int(new[name])))
        if "speed_setpoint" in new:
            self.setpoint = float(new["speed_setpoint"])
        if "ramp" in new:
            self.ramp = float(new["ramp"])
        if "dut_cmd" in new:
            self.dut_cmd = float(new["dut_cmd"])
        for name in ("capture_rate", "capture_length", "watchdog_ms"):
            if name in new:
                setattr(self, name, int(new[name]))
        if "enable" in new:
            self.enabled = bool(new["enable"])
            self.stopping = False
            if not self.enabled and self.capture_state in (CaptureState.ARMED, CaptureState.RUNNING):
                self._capture_failed()
        if new.get("stop") == 1:
            self.setpoint = 0.0
            self.stopping = self.enabled
        if new.get("capture_start") == 1:
            self._capture_token += 1
            self.buffer, self.buffer_count = {}, 0
            self.capture_state = CaptureState.ARMED
            self.advance(now)
        elif new.get("capture_start") == 2 and self.capture_state in (CaptureState.ARMED, CaptureState.RUNNING):
            self._capture_token += 1
            self.capture_state = CaptureState.IDLE
        if "buf_channel" in new or "buf_offset" in new:
            self.buf_channel = int(new.get("buf_channel", self.buf_channel))
            self.buf_offset = int(new.get("buf_offset", self.buf_offset))
            self._fill_page()
        if new.get("sim_fault"):
            self.inject(SimFault(int(new["sim_fault"])), int(new.get("sim_fault_arg", 500)) or 500)
        return None

    # ------------------------------------------------------------------ serving
    async def serve(self, host: str = "127.0.0.1", port: int = 5020, started: Callable[[int], None] | None = None) -> None:
        """Run the Modbus TCP server until cancelled; ``started(port)`` once it listens."""
        from pymodbus.server import ModbusTcpServer

        self._loop = asyncio.get_running_loop()
        server = ModbusTcpServer(self.simdevice(), address=(host, port), trace_packet=self.trace_packet)
        self._server = server
        await server.serve_forever(background=True)
        bound = server.transport.sockets[0].getsockname()[1]
        if started is not None:
            started(bound)
        try:
            while True:
                await asyncio.sleep(0.01)
                self.advance()
        finally:
            await server.shutdown()
            self._server = None


def capture_to_buffer(capture: Capture, n_samples: int) -> dict[int, np.ndarray]:
    """A capture -> register words per channel id (the dyno's capture buffer).

    Raises ValueError when the capture lacks the digital channels or has the wrong length.
    """
    if len(capture.t) != n_samples:
        raise ValueError(f"capture source returned {len(capture.t)} samples, {n_samples} requested")
    ch = capture.channels
    if "enc_a" not in ch or "hall" not in ch:
        raise ValueError("capture source returned no enc_a/hall channels")
    buffer = {rm.DIGITAL_CHANNEL_ID: rm.pack_digital(ch["enc_a"], ch.get("enc_b"), ch["hall"])}
    for cid, name in rm.ANALOG_CHANNELS.items():
        if name in ch:
            buffer[cid] = rm.f32_to_words(ch[name])
    return buffer


class DynoSimThread:
    """A :class:`DynoSim` served from a background thread (tests, demo, benchmarks).

    Use as a context manager; ``port`` is the bound port (pass ``port=0`` for a free one).
    """

    def __init__(self, sim: DynoSim, host: str = "127.0.0.1", port: int = 0) -> None:
        self.sim = sim
        self.host = host
        self.port = port
        self._thread: threading.Thread | None = None
        self._task: asyncio.Task | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None

    def start(self) -> "DynoSimThread":
        def run() -> None:
            async def main() -> None:
                self._task = asyncio.current_task()
                await self.sim.serve(self.host, self.port, self._on_started)

            try:
                asyncio.run(main())
            except asyncio.CancelledError:
                pass
            except BaseException as exc:  # noqa: BLE001 - reported to the starting thread
                self._error = exc
                self._started.set()

        self._thread = threading.Thread(target=run, name="dyno-sim", daemon=True)
        self._thread.start()
        if not self._started.wait(10.0) or self._error is not None:
            raise RuntimeError(f"dyno simulator did not start: {self._error!r}")
        return self

    def _on_started(self, port: int) -> None:
        self.port = port
        self._started.set()

    def call(self, fn: Callable, *args):
        """Run ``fn(*args)`` on the server's event loop and return its result."""
        loop = self.sim._loop
        assert loop is not None
        fut = asyncio.run_coroutine_threadsafe(_acall(fn, *args), loop)
        return fut.result(10.0)

    def stop(self) -> None:
        loop = self.sim._loop
        if loop is not None and self._task is not None and self._thread is not None and self._thread.is_alive():
            loop.call_soon_threadsafe(self._task.cancel)
            self._thread.join(10.0)

    def __enter__(self) -> "DynoSimThread":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


async def _acall(fn: Callable, *args):
    return fn(*args)
