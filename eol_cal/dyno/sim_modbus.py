"""The dyno simulator's Modbus face: register values, the request hook, the TCP server.

:class:`ModbusFace` is mixed into :class:`eol_cal.dyno.sim_dyno.DynoSim`; it turns the simulated
state into the registers of the dyno's :class:`~eol_cal.dyno.regmap.RegisterMap` (any map the
client can drive: the reference layout, or a vendor's) and every accepted write back into state.
The pymodbus 3.16 server is fed a :class:`pymodbus.simulator.SimDevice` (the datastore API 3.16
recommends; the ``ModbusDeviceContext`` classes are deprecated shims), one shared register space
or separate holding and input tables as the map says, whose ``action`` hook sees every request:
it validates and applies writes and refreshes what a read returns.
"""

from __future__ import annotations

import asyncio
import math
import time
from typing import TYPE_CHECKING
from collections.abc import Callable

from eol_cal.domain.bench_mechanics import SIMULATED_BENCH_KEY
from eol_cal.dyno import registers as rm
from eol_cal.dyno.regmap import RegisterMap
from eol_cal.dyno.registers import CaptureState, Fault, Interlock, SimFault
from eol_cal.dyno.sim_capture import CaptureRequest

if TYPE_CHECKING:
    import numpy as np
    from pymodbus.constants import ExcCodes
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import SimDevice


_FC_READ = (3, 4)
#: longest capture the buffer holds (samples)
MAX_CAPTURE_SAMPLES = 4_000_000
#: command registers: act on the write, read back idle (0)
_SELF_CLEARING = ("stop", "capture_start", "fault_reset", "sim_fault")


class ModbusFace:
    """Registers of the simulated dyno (a mixin: the state lives in :class:`DynoSim`)."""

    _loop: asyncio.AbstractEventLoop | None
    _server: ModbusTcpServer | None
    _recording: CaptureRequest | None  # the capture running now
    buffer: dict[int, np.ndarray]  # channel id -> register words (uint16)
    regmap: RegisterMap
    realtime: bool
    captures: list
    _turning_on: bool  # the drive stayed enabled since the last capture was ready

    def _serving_loop(self) -> asyncio.AbstractEventLoop:
        """The server's event loop; a :class:`RuntimeError` before :meth:`serve` started."""
        if self._loop is None:
            raise RuntimeError("the dyno simulator is not serving (call serve() or use DynoSimThread)")
        return self._loop

    def status_values(self) -> dict[str, float | int | str]:
        """Current value of every read-only register (physical or semantic values)."""
        return {
            "map_version": self.regmap.map_version or 0,
            "dut_serial": self.serial,
            "dut_poles": self.motor.poles,
            "dut_encoder_ppr": self.motor.N_enc,
            "dut_kt": self.motor.kt,
            "max_speed": self.max_speed,
            "tick_hz": self.tick_hz,
            "speed": self.speed,
            "torque": self.shaft_torque(),
            "temperature": self.temperature,
            "faults": int(self.faults),
            "interlocks": int(self.interlocks),
            "drive_state": int(self.drive_state()),
            "capture_state": int(self.capture_state),
            "capture_count": self.captured(),
            "capture_channels": self.regmap.channel_mask(list(self.buffer)),
            "heartbeat": (self.heartbeat_frozen if self.heartbeat_frozen is not None
                          else int((time.monotonic() - self._t0) * 100) & 0xFFFF),
            "capture_seq": self.capture_seq,
            # the plant's own claim (its capture's metadata): a fit on the same bench file knows the path
            "sim_bench": str((self.last_capture.metadata if self.last_capture is not None else {}).get(
                SIMULATED_BENCH_KEY, "")),
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

    def simdevice(self) -> SimDevice:
        """The pymodbus :class:`SimDevice` backing the server: the map's registers and window."""
        from pymodbus.simulator import DataType, SimData, SimDevice

        m = self.regmap
        values = {**self.status_values(), **self.control_values()}
        tables: dict[str, list] = {"holding": [], "input": []}
        for e in m.entries.values():
            tables[e.table].append(SimData(e.address, values=m.encode(e.name, values[e.name]), datatype=DataType.REGISTERS,
                                           readonly=not e.role.writable))
        w = m.window
        tables[w.table].append(SimData(w.address, count=w.registers, values=0, datatype=DataType.REGISTERS, readonly=True))
        # id 0: answer every unit id, as a TCP device usually does
        if m.shared_tables:
            return SimDevice(0, simdata=tables["holding"] + tables["input"], action=self.action)
        for name in ("holding", "input"):
            if not tables[name]:  # pymodbus needs an entry in each table
                tables[name].append(SimData(0, values=0, datatype=DataType.REGISTERS, readonly=True))
        bit = [SimData(0, datatype=DataType.BITS, readonly=True)]
        return SimDevice(0, simdata=(bit, list(bit), tables["holding"], tables["input"]), action=self.action)

    def _table_of(self, function_code: int) -> str | None:
        """The table a request addresses (None: the one shared space)."""
        if self.regmap.shared_tables:
            return None
        return "input" if function_code == 4 else "holding"

    async def action(
        self, function_code: int, start_address: int, address: int, count: int, registers: list[int],
        set_values: list[int] | None,
    ) -> ExcCodes | None:
        """pymodbus hook, called for every request before it touches ``registers``."""
        self._request_seen()
        end = address + count
        table = self._table_of(function_code)
        w = self.regmap.window
        if function_code in _FC_READ:
            if table in (None, w.table) and address < w.end and end > w.address:
                lo = max(address, w.address) - w.address
                hi = min(end, w.end) - w.address
                words = await self._window_page(lo, hi)
                if not isinstance(words, list):
                    return words
                base = w.address - start_address
                registers[base + lo: base + hi] = words
            if address < w.address or end > w.end or table not in (None, w.table):  # not a window-only read
                self._refresh(registers, start_address, address, end, table, self.status_values())
            return None
        if set_values is None:
            return None
        return self._write(address, list(set_values), set_values) or None

    def _request_seen(self) -> None:
        """A request came: the watchdog's clock restarts and the simulated time moves to now."""
        now = time.monotonic()
        self._last_request = now
        self.advance(now)

    async def _window_page(self, lo: int, hi: int) -> list[int] | ExcCodes:
        """Registers ``lo:hi`` of the capture window (a read of them), or the exception to answer."""
        from pymodbus.constants import ExcCodes

        w = self.regmap.window
        self.window_reads += 1
        self._fire_plans("read", self.window_reads)
        if time.monotonic() < self.disconnect_until:
            return ExcCodes.DEVICE_BUSY  # the connection is being dropped anyway
        channel, offset = self.buf_channel, self.buf_offset  # the page this read addresses
        recorded = channel == w.digital_id or channel in self.regmap.channels.values()
        if self.realtime and self.capture_state == CaptureState.RUNNING and recorded:
            per = self.regmap.regs_per_sample(channel)
            # as a real dyno: samples the shaft has not turned out yet are waited for
            if not await self.wait_recorded(offset + -(-hi // per)):
                return ExcCodes.DEVICE_FAILURE  # the capture failed or was aborted meanwhile
            self.captures[-1].early_reads += 1
        return self.window_words(channel, offset, lo, hi)

    async def direct_read(self, function_code: int, address: int, count: int) -> list[int] | ExcCodes | None:
        """A read that lies in the capture window, answered from the buffer without the datastore
        (:func:`eol_cal.dyno.pdu.server_pdus`): what :meth:`action` makes of it, the same registers
        or exception; None for any other read (the datastore's checks and :meth:`action`)."""
        w = self.regmap.window
        if (function_code not in _FC_READ or self._table_of(function_code) not in (None, w.table)
                or count <= 0 or address < w.address or address + count > w.end):
            return None
        self._request_seen()
        return await self._window_page(address - w.address, address + count - w.address)

    def _refresh(self, registers: list[int], start: int, lo: int, hi: int, table: str | None, values: dict) -> None:
        for name, value in values.items():
            e = self.regmap.entries.get(name)
            if e is not None and table in (None, e.table) and e.address < hi and e.end > lo:
                i = e.address - start
                registers[i: i + e.count] = self.regmap.encode(name, value)

    def _write(self, address: int, words: list[int], set_values: list[int]) -> ExcCodes | None:
        from pymodbus.constants import ExcCodes

        end = address + len(words)
        m = self.regmap
        # A write must cover whole values: half of an f32 would change it to garbage.
        new: dict[str, float | int | str] = {}
        for e in m.entries.values():
            if (m.shared_tables or e.table == "holding") and e.address < end and e.end > address:
                if e.address < address or e.end > end or not e.role.writable:
                    return ExcCodes.ILLEGAL_ADDRESS
                i = e.address - address
                try:
                    new[e.name] = m.decode(e.name, words[i: i + e.count])
                except ValueError:
                    return ExcCodes.ILLEGAL_VALUE  # a raw code the map does not list
        err = self._apply(new)
        if err:
            return err
        for name in _SELF_CLEARING:
            if name in new:
                i = m[name].address - address
                set_values[i: i + m[name].count] = m.encode(name, 0)
        return None

    def _apply(self, new: dict[str, float | int | str]) -> ExcCodes | None:
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
        if "buf_channel" in new and new["buf_channel"] not in (0, self.regmap.window.digital_id, *self.regmap.analog_channels):
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
            self._turning_on = self._turning_on and self.enabled
            if not self.enabled and self.capture_state in (CaptureState.ARMED, CaptureState.RUNNING):
                self._capture_failed()
        if new.get("stop") == 1:
            self.setpoint = 0.0
            self.stopping = self.enabled
        if new.get("capture_start") == 1:
            self._capture_token += 1
            self._recording = None
            self.buffer, self.buffer_count = {}, 0
            self.capture_state = CaptureState.ARMED
            self.advance(now)
        elif new.get("capture_start") == 2 and self.capture_state in (CaptureState.ARMED, CaptureState.RUNNING):
            self._capture_token += 1
            self._recording = None
            self.capture_state = CaptureState.IDLE
        if "buf_channel" in new or "buf_offset" in new:
            self.buf_channel = int(new.get("buf_channel", self.buf_channel))
            self.buf_offset = int(new.get("buf_offset", self.buf_offset))
        if new.get("sim_fault"):
            self.inject(SimFault(int(new["sim_fault"])), int(new.get("sim_fault_arg", 500)) or 500)
        return None

    # ------------------------------------------------------------------ serving
    async def serve(self, host: str = "127.0.0.1", port: int = 5020, started: Callable[[int], None] | None = None) -> None:
        """Run the Modbus TCP server until cancelled; ``started(port)`` once it listens."""
        from pymodbus.server import ModbusTcpServer

        from eol_cal.dyno.pdu import server_pdus

        self._loop = asyncio.get_running_loop()
        server = ModbusTcpServer(self.simdevice(), address=(host, port), trace_packet=self.trace_packet,
                                 custom_pdu=server_pdus(self.direct_read))
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
