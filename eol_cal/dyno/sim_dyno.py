"""Dyno simulator: a real pymodbus TCP server speaking a dyno register map (:mod:`.regmap`: the
reference layout by default, or any map file the client can drive).

The simulated dyno holds a speed set point with a ramp, passes the load command to the motor
under test and, when a capture is started, asks a *capture source* for the recording
(:data:`CaptureSource`): the analytic model here (:func:`synthetic_source`), or what the rig
wires in (:mod:`eol_cal.sim.rig`: the built-in plant running the ECU simulator's active
flash bank, so a flash changes what the next capture shows). The dyno knows no ECU and no
parameter block; the motor's data (poles, encoder, torque constant, PWM clock) come from its
:class:`~eol_cal.domain.motor_params.MotorParams`.

In real-time mode (``realtime=True``, ``eol-cal dyno-sim --realtime``) a capture takes its
physical time, as on a real dyno: the buffer fills at the capture rate from the moment the
capture starts, ``capture_count`` counts the samples recorded so far, a window read of samples
not recorded yet waits until they are, and the capture is ready at its physical end. The capture
source may compute the recording ahead (the plant usually does), but nothing of it is answered
earlier than the shaft would have turned it out; a source slower than real time holds the
samples back until it is done (:attr:`DynoSim.captures` says by how much).

Faults on demand (register ``sim_fault``, :meth:`DynoSim.inject`, or a :class:`FaultPlan`
that fires at the N-th capture or the N-th window read): disconnect (every connection dropped
and requests ignored for a while), over-speed trip and torque-sensor fault (the drive trips,
a running capture ends in the error state).

The register side (values, the pymodbus request hook, the server thread) is in
:mod:`eol_cal.dyno.sim_modbus`.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from dataclasses import dataclass
from typing import TypeVar
from collections.abc import Callable

import numpy as np

from eol_cal.capture.data import Capture
from eol_cal.dyno.registers import (
    CaptureState,
    DriveState,
    DutCmdKind,
    Fault,
    Interlock,
    Mode,
    SimFault,
    SPEED_TOL_REL,
    SPEED_TOL_RPM,
)
from eol_cal.dyno.mapfile import default_register_map
from eol_cal.dyno.regmap import RegisterMap
from eol_cal.dyno.sim_capture import CaptureRequest, CaptureSource, CaptureTiming, capture_to_buffer
from eol_cal.dyno.sim_modbus import ModbusFace
from eol_cal.domain.motor_params import MotorParams, load_motor

T = TypeVar("T")
#: the faults that stop the drive (the mask built once: an enum flag's ``|`` costs microseconds, and
#: every request to the simulator asks)
_TRIPPING = Fault.OVER_SPEED | Fault.TORQUE_SENSOR | Fault.COMM_WATCHDOG | Fault.DRIVE

#: deceleration of a disabled or tripped drive (rpm/s)
COAST_DECEL = 2000.0
#: the longest step between two of the simulator's own updates that counts whole as the client's
#: silence (s): it updates every 10 ms while it serves; a longer step is a stall of its own
LIVE_STEP_S = 0.25


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


class DynoSim(ModbusFace):
    """State and behaviour of the simulated dyno (one motor under test).

    Parameters
    ----------
    source : CaptureSource
        Produces the recording of each capture.
    serial : str
        Serial of the motor on the dyno.
    motor : MotorParams, optional
        The motor on the dyno (default the ``paper`` preset): its poles P, encoder pulses N_enc
        and torque constant kt (N*m/A, to show a shaft torque for an i_qo command) go into the
        identification registers; its PWM frequency (Hz) is the dyno's sample clock, which
        capture rates must divide.
    seed : int or None
        Motor variation seed passed to the source.
    max_speed : float
        Over-speed trip threshold (rpm).
    faults : sequence of FaultPlan
        Faults that fire by themselves.
    register_map : RegisterMap, optional
        The layout the dyno serves (default: the eol-cal reference map, ``maps/default.toml``).
    realtime : bool
        A capture takes its physical time (``capture_length / capture_rate``) and its buffer
        fills as the shaft turns (module doc); False: ready as soon as the source has computed it.
    """

    def __init__(
        self,
        source: CaptureSource,
        *,
        serial: str = "M-0001",
        motor: MotorParams | None = None,
        seed: int | None = None,
        max_speed: float = 3000.0,
        faults: tuple[FaultPlan, ...] | list[FaultPlan] = (),
        register_map: RegisterMap | None = None,
        realtime: bool = False,
    ) -> None:
        self.regmap = default_register_map() if register_map is None else register_map
        self.realtime = realtime
        self.source = source
        self.serial = serial
        self.motor = load_motor("paper") if motor is None else motor
        self.seed = seed
        self.max_speed = max_speed
        self.tick_hz = int(self.motor.f_pwm)
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
        #: every capture started since start-up, with its timing (:class:`CaptureTiming`)
        self.captures: list[CaptureTiming] = []
        self._recording: CaptureRequest | None = None  # the capture running now
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
        self._silent_s = 0.0  # the client's silence while this simulator ran (advance)
        self._capture_job: asyncio.Future | None = None
        self._turning_on = False  # the drive stayed enabled since the last capture was ready
        self._capture_token = 0
        self._server = None
        self._loop: asyncio.AbstractEventLoop | None = None

    # ------------------------------------------------------------------ physics
    def _target(self) -> float:
        if self.enabled and not self.stopping and self.mode == Mode.SPEED and not self._tripped():
            return self.setpoint * (-1.0 if self.direction else 1.0)
        return 0.0

    def _tripped(self) -> bool:
        return bool(self.faults & _TRIPPING)

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
        return self.dut_cmd if self.dut_cmd_kind == DutCmdKind.TORQUE else self.motor.kt * self.dut_cmd

    def advance(self, now: float | None = None) -> None:
        """Move the simulated time forward to ``now`` (monotonic s)."""
        now = time.monotonic() if now is None else now
        dt = max(0.0, now - self._t_last)
        # The watchdog counts the client's silence while this simulator ran. Over a stall of its own
        # (its thread starved of the CPU or the GIL on a loaded machine) the client's requests wait in
        # its socket unseen: counted whole, the stall tripped the watchdog of a client that kept
        # asking (bench_station.py beside a busy loop, the first motor). A real dyno's controller
        # does not stall.
        if self._last_request > self._t_last:  # a request came since the last step
            self._silent_s = now - self._last_request
        else:
            self._silent_s += min(dt, LIVE_STEP_S)
        self._t_last = now
        target = self._target()
        rate = self.ramp if (self.enabled and not self._tripped()) else max(self.ramp, COAST_DECEL)
        step = rate * dt
        self.speed = target if abs(target - self.speed) <= step else self.speed + math.copysign(step, target - self.speed)
        if self.stopping and self.speed == 0.0:
            self.stopping = False
            self.enabled = False
        if not self.enabled:
            self._turning_on = False
        if abs(self.speed) > self.max_speed:
            self._trip(Fault.OVER_SPEED)
        if self.watchdog_ms and self.enabled and self._silent_s > self.watchdog_ms / 1000.0:
            self._trip(Fault.COMM_WATCHDOG)
        if self.capture_state == CaptureState.RUNNING and self._recording_due(now):
            self._capture_ready()
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
        self._recording = None
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
            self._serving_loop().call_soon(self._drop_connections)
            return b""
        return data

    # ------------------------------------------------------------------ captures
    def _start_capture(self) -> None:
        self.captures_started += 1
        self.capture_state = CaptureState.RUNNING
        self._capture_token += 1
        token = self._capture_token
        loop = self._serving_loop()

        def partial(piece: Capture) -> None:  # from the source's thread
            loop.call_soon_threadsafe(self._capture_partial, token, piece)

        now = time.monotonic()
        previous = self.captures[-1] if self.captures else None
        gap = (now - previous.physical_end if self.realtime and self._turning_on and previous is not None
               and previous.ready is not None else None)
        self._turning_on = False
        request = CaptureRequest(
            speed_rpm=self._target(),
            dut_cmd_kind=self.dut_cmd_kind,
            dut_cmd=self.dut_cmd,
            n_samples=self.capture_length,
            rate_hz=float(self.capture_rate),
            serial=self.serial,
            seed=self.seed,
            capture_index=self.captures_started,
            partial=partial if self.realtime else None,
            gap_s=None if gap is None else max(0.0, gap),
        )
        self.captures.append(CaptureTiming(request.capture_index, now, now + request.seconds))
        self._recording = request
        job = loop.run_in_executor(None, self.source, request)
        job.add_done_callback(lambda f: self._capture_done(f, token, request))
        self._capture_job = job
        self._fire_plans("capture", self.captures_started)

    def _capture_done(self, job: asyncio.Future, token: int, request: CaptureRequest) -> None:
        if token != self._capture_token or self.capture_state != CaptureState.RUNNING:
            return
        exc = job.exception()
        if exc is not None:
            self.log.append((time.monotonic(), "capture_error", repr(exc)))
            self._capture_failed()
            return
        capture: Capture = job.result()
        try:
            self.buffer = capture_to_buffer(capture, request.n_samples, self.regmap)
        except ValueError as err:
            self.log.append((time.monotonic(), "capture_error", str(err)))
            self._capture_failed()
            return
        self.last_capture = capture
        self.captures[-1].source_done = time.monotonic()
        if not self.realtime or self._recording_due(time.monotonic()):
            self._capture_ready()

    def _capture_partial(self, token: int, piece: Capture) -> None:
        """The first samples of the running capture, from a source still computing the rest: into
        the buffer (the rest of it zeros until they come), counted in ``computed``."""
        request, timing = self._recording, (self.captures[-1] if self.captures else None)
        if (token != self._capture_token or self.capture_state != CaptureState.RUNNING or request is None
                or timing is None or timing.source_done is not None):
            return
        k0, k = timing.computed, min(len(piece.t), request.n_samples)
        if k <= k0:
            return
        new = Capture(piece.t[k0:k], {name: v[k0:k] for name, v in piece.channels.items()}, piece.metadata)
        try:
            words = capture_to_buffer(new, k - k0, self.regmap)
        except ValueError as err:  # the whole capture will say it again, and fail the capture then
            self.log.append((time.monotonic(), "capture_partial_error", str(err)))
            return
        for cid, w in words.items():
            if cid not in self.buffer:
                self.buffer[cid] = np.zeros(request.n_samples * self.regmap.regs_per_sample(cid), w.dtype)
            first = k0 * self.regmap.regs_per_sample(cid)
            self.buffer[cid][first:first + len(w)] = w
        timing.computed = k

    def _recording_due(self, now: float) -> bool:
        """Real time: the running capture's source is done and its physical time has passed."""
        timing = self.captures[-1] if self.captures else None
        return (self.realtime and self._recording is not None and timing is not None
                and timing.source_done is not None and now >= timing.physical_end)

    def _capture_ready(self) -> None:
        request, self._recording = self._recording, None
        assert request is not None  # called while a capture runs (RUNNING): _recording is set with that state
        self.buffer_count = request.n_samples
        self.captures[-1].ready = time.monotonic()
        capture = self.last_capture
        if capture is not None and "temp" in capture.channels:
            self.temperature = float(np.mean(capture.channels["temp"]))
        self.capture_seq = (self.capture_seq + 1) & 0xFFFF
        self.capture_state = CaptureState.READY
        self._turning_on = self.enabled

    def captured(self, now: float | None = None) -> int:
        """Samples in the capture buffer now: all of a ready capture; in real time, those of a
        running capture the shaft has turned out and the source has computed; else 0."""
        if self.capture_state == CaptureState.READY:
            return self.buffer_count
        request, timing = self._recording, (self.captures[-1] if self.captures else None)
        if not self.realtime or self.capture_state != CaptureState.RUNNING or request is None or timing is None:
            return 0
        computed = request.n_samples if timing.source_done is not None else timing.computed
        now = time.monotonic() if now is None else now
        return min(computed, max(0, int((now - timing.started) * request.rate_hz)))

    async def wait_recorded(self, samples: int) -> bool:
        """Real time: wait until the running capture holds ``samples`` samples (a window read of
        samples not recorded yet). False when the capture failed or was aborted meanwhile."""
        token = self._capture_token
        while self.capture_state == CaptureState.RUNNING and token == self._capture_token:
            now = time.monotonic()
            self.advance(now)
            if self.captured(now) >= samples or self.capture_state != CaptureState.RUNNING:
                break
            timing, request = self.captures[-1], self._recording
            assert request is not None  # still RUNNING (checked above): _recording is set with that state
            due = (timing.started + samples / request.rate_hz - now) if timing.source_done is not None else 0.005
            await asyncio.sleep(min(max(due, 0.0005), 0.05))
        return token == self._capture_token and self.capture_state in (CaptureState.READY, CaptureState.RUNNING)

    def window_words(self, channel: int, offset: int, lo: int, hi: int) -> list[int]:
        """Registers ``lo:hi`` of the window page of ``channel`` from sample ``offset`` (zeros
        past the buffer or for a channel it does not hold)."""
        words = self.buffer.get(channel)
        chunk: list[int] = []
        if words is not None:
            first = offset * self.regmap.regs_per_sample(channel)
            chunk = words[first + lo: first + hi].tolist()
        return chunk + [0] * (hi - lo - len(chunk))


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

    def start(self) -> DynoSimThread:
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

    def call(self, fn: Callable[..., T], *args: object) -> T:
        """Run ``fn(*args)`` on the server's event loop and return its result (10 s at most)."""
        loop = self.sim._serving_loop()
        fut = asyncio.run_coroutine_threadsafe(_acall(fn, *args), loop)
        return fut.result(10.0)

    def stop(self) -> None:
        loop = self.sim._loop
        if loop is not None and self._task is not None and self._thread is not None and self._thread.is_alive():
            loop.call_soon_threadsafe(self._task.cancel)
            self._thread.join(10.0)

    def __enter__(self) -> DynoSimThread:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


async def _acall(fn: Callable[..., T], *args: object) -> T:
    return fn(*args)
