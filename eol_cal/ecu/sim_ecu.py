"""ECU simulator: a UDS server over ISO-TP on a python-can bus implementing firmware contract v1
(``docs/firmware-contract.md``).

udsoncan is a client library, so the server side is written here: requests are parsed once
(``udsoncan.Request.from_payload`` plus :mod:`eol_cal.ecu.protocol`), each service has one
handler, and negative answers are raised as :class:`Nrc`. Programming state and the banks
are :class:`eol_cal.ecu.programming.BankProgrammer` on :class:`eol_cal.ecu.flash.NorFlash`;
:class:`Faults` injects power loss, NRCs, lost answers, a wrong block counter and (through
:class:`eol_cal.ecu.transport.FaultyBus`) dropped and delayed frames.

One tester at a time: while the programming session is held, every session change other
than back to the default session is refused with NRC 0x22, so a second tester cannot take
over (or restart) a download. CAN gives the ECU no tester identity; the rest is the tester's
part (docs/flashing.md, "One tester at a time").

A power loss makes the simulator stop answering for good; a new :class:`EcuSimulator` on the
same flash file is the restart.
"""

from __future__ import annotations

import hmac
import logging
import random
import struct
import threading
import time
from collections.abc import Callable

import can
from udsoncan import Request, Response, services

from eol_cal.ecu import protocol as P
from eol_cal.ecu.flash import NorFlash, SecurityMemory, select_active
from eol_cal.ecu.programming import BankProgrammer, Nrc, PowerLoss, parse_location
from eol_cal.ecu.simconfig import STEPS, Faults, SimConfig
from eol_cal.ecu.transport import FaultyBus, make_stack
from eol_cal.ecu.wire import PacedBus

__all__ = ["EcuSimulator", "Faults", "Nrc", "STEPS", "SimConfig"]

log = logging.getLogger(__name__)

_STEP_OF_SERVICE = {
    services.DiagnosticSessionControl: "session",
    services.SecurityAccess: "security",
    services.ReadDataByIdentifier: "read_did",
    services.RequestDownload: "download",
    services.TransferData: "transfer",
    services.RequestTransferExit: "transfer_exit",
    services.ReadMemoryByAddress: "read_memory",
    services.ECUReset: "reset",
    services.TesterPresent: "tester_present",
}


class _Pending:
    """Answers NRC 0x78 while a request takes longer than P2 (and again every P2*/2).

    ISO 14229-2: a server that cannot answer within P2 sends responsePending; the final
    answer goes out under the same lock, so it can never overtake a 0x78.
    """

    def __init__(self, sim: EcuSimulator, service: type) -> None:
        self._sim = sim
        self._payload = Response(service=service, code=P.NRC.RequestCorrectlyReceived_ResponsePending).get_payload()
        self._lock = threading.Lock()
        self._done = False
        self._arm(0.8 * sim.config.p2_s)

    def _arm(self, delay: float) -> None:
        self._timer = threading.Timer(delay, self._fire)
        self._timer.daemon = True
        self._timer.start()

    def _fire(self) -> None:
        with self._lock:
            if self._done:
                return
            self._sim._send(self._payload)
            self._arm(0.5 * self._sim.config.p2_star_s)

    def finish(self, final: bytes | None) -> None:
        with self._lock:
            self._done = True
            self._timer.cancel()
            if final is not None:
                self._sim._send(final)


class EcuSimulator:
    """The simulated ECU, serving UDS on ``bus`` (IDs 0x7E0 -> 0x7E8) from a thread.

    Parameters
    ----------
    bus : can.BusABC
        Its own bus object (the ISO-TP stack reads it); other parties open their own.
    flash : NorFlash
        The two banks (a file-backed one survives restarts).
    config : SimConfig
    faults : Faults
    """

    def __init__(self, bus: can.BusABC, flash: NorFlash, config: SimConfig | None = None,
                 faults: Faults | None = None) -> None:
        self.flash = flash
        self.config = config or SimConfig()
        self.faults = faults or Faults()
        f = self.faults
        if self.config.bitrate:
            bus = PacedBus(bus, self.config.bitrate)
        self.bus: can.BusABC = (FaultyBus(bus, drop_rate=f.drop_rate, delay_rate=f.delay_rate,
                                          delay_s=f.delay_s, seed=f.seed)
                                if (f.drop_rate or f.delay_rate) else bus)
        self._stack = make_stack(self.bus, tx_id=P.ECU_ID, rx_id=P.TESTER_ID, blocking_send=False,
                                 timing=self.config.isotp_timing)
        self._rng = random.Random(f.seed)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.powered_off = threading.Event()
        self.on_power_loss: Callable[[], None] | None = None
        """Called when the injected power loss happens (``ecu-sim`` kills its own process there)."""
        self.steps_seen: list[str] = []
        self._previous: tuple[bytes, bytes] | None = None  # the last (request, answer), for stale_answers
        self.stale_sent = 0
        self.security = SecurityMemory(flash)
        self._lockout_until = 0.0
        self._step_counts: dict[str, int] = {}
        self.banks = BankProgrammer(flash, self.faults, self._power_fails)
        self._handlers = {
            services.DiagnosticSessionControl: self._session,
            services.SecurityAccess: self._security,
            services.TesterPresent: self._tester_present,
            services.ReadDataByIdentifier: self._read_did,
            services.RoutineControl: self._routine,
            services.RequestDownload: self._request_download,
            services.TransferData: self._transfer_data,
            services.RequestTransferExit: self._transfer_exit,
            services.ReadMemoryByAddress: self._read_memory,
            services.ECUReset: self._reset,
        }
        self._boot()

    @property
    def faults(self) -> Faults:
        """The faults injected; may be replaced between flashes."""
        return self._faults

    @faults.setter
    def faults(self, faults: Faults) -> None:
        self._faults = faults
        if hasattr(self, "banks"):
            self.banks.faults = faults

    # --- life cycle -------------------------------------------------------------------------
    def _boot(self) -> None:
        """Power-on / reset: default session, locked, bank re-selected; a pending lock-out starts again."""
        self.active, _ = select_active(self.flash)
        if self.security.lockout_pending:
            self._lockout_until = time.monotonic() + self.config.lockout_s
        self._to_default()

    def _to_default(self) -> None:
        self.session = P.SESSION_DEFAULT
        self.unlocked = False
        self._seed: bytes | None = None
        self.banks.forget()
        self._last_activity = time.monotonic()

    def start(self) -> EcuSimulator:
        """Start serving in a background thread."""
        self._stack.start()
        self._thread = threading.Thread(target=self._run, name="ecu-sim", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving (not a power loss: nothing happens to the flash)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(2.0)
        if self._stack.started:
            self._stack.stop()

    def __enter__(self) -> EcuSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def alive(self) -> bool:
        return not self.powered_off.is_set()

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.security.lockout_pending and time.monotonic() >= self._lockout_until:
                self.security.lockout_pending = False  # the delay ran out while powered
                self.security.save()
            if (self.session != P.SESSION_DEFAULT
                    and time.monotonic() - self._last_activity > self.config.s3_s):
                log.info("S3 expired: back to the default session, locked")
                self._to_default()
            payload = self._stack.recv(block=True, timeout=0.02)
            if payload is None:
                continue
            try:
                self._serve(bytes(payload))
            except PowerLoss:
                log.info("power loss")
                self.powered_off.set()
                if self.on_power_loss is not None:
                    self.on_power_loss()
                self._stack.stop()
                return
            self._last_activity = time.monotonic()

    # --- dispatch ------------------------------------------------------------------------------
    def _send(self, payload: bytes) -> None:
        self._stack.send(payload)

    def _stale_answer(self, payload: bytes) -> None:
        """Faults.stale_answers: the previous answer again, before this request's own; not after
        the very same request (the answer would be the same) nor between two reads of memory
        (their answers carry no echo: UDS gives a tester nothing to tell them apart by)."""
        previous, self._previous = self._previous, None
        if previous is None or previous[0] == payload:
            return
        if previous[0][:1] == payload[:1] == bytes((services.ReadMemoryByAddress.request_id(),)):
            return
        self.stale_sent += 1
        self._send(previous[1])

    def _serve(self, payload: bytes) -> None:
        if self.faults.stale_answers:
            self._stale_answer(payload)
        req = Request.from_payload(payload)
        if req.service is None or req.service not in self._handlers:
            # No udsoncan service object exists for an unknown ID, so build 7F SID 11 here.
            self._send(bytes((0x7F, payload[0], P.NRC.ServiceNotSupported)))
            return
        step = self._step_of(req)
        self.steps_seen.append(step)
        self._step_counts[step] = self._step_counts.get(step, 0) + 1
        if step not in ("erase", "transfer") and self._power_fails(step):
            raise PowerLoss
        drop = self.faults.drop_response.get(step, ())
        lost = self._step_counts[step] in (drop if isinstance(drop, tuple) else (drop,))
        pending = _Pending(self, req.service)
        try:
            time.sleep(self.faults.slow_step.get(step, 0.0))
            if req.service.request_id() in self.faults.nrc:
                raise Nrc(self.faults.nrc[req.service.request_id()])
            data = self._handlers[req.service](req)
        except Nrc as exc:
            final = None if lost else Response(service=req.service, code=exc.code).get_payload()
            pending.finish(final)
            self._previous = None if final is None else (payload, final)
            return
        except BaseException:
            pending.finish(None)
            raise
        final = None
        if data is not None and not req.suppress_positive_response and not lost:
            final = Response(service=req.service, code=Response.Code.PositiveResponse, data=data).get_payload()
        pending.finish(final)
        self._previous = None if final is None else (payload, final)

    def _power_fails(self, step: str) -> bool:
        return (self.faults.power_loss_step == step
                and self._step_counts.get(step, 0) == self.faults.power_loss_occurrence)

    @staticmethod
    def _step_of(req: Request) -> str:
        assert req.service is not None  # the caller answered a request of no known service before asking
        if req.service is services.RoutineControl:
            rid = int.from_bytes((req.data or b"")[:2], "big")
            return "erase" if rid == P.RID_ERASE else "check"
        return _STEP_OF_SERVICE[req.service]

    def _require(self, *, session: tuple[int, ...] | None = None, unlocked: bool = False) -> None:
        if session is not None and self.session not in session:
            raise Nrc(P.NRC.ServiceNotSupportedInActiveSession)
        if unlocked and not self.unlocked:
            raise Nrc(P.NRC.SecurityAccessDenied)

    # --- services ----------------------------------------------------------------------------------
    def _session(self, req: Request) -> bytes:
        sub = req.subfunction
        if sub not in (P.SESSION_DEFAULT, P.SESSION_EXTENDED, P.SESSION_PROGRAMMING):
            raise Nrc(P.NRC.SubFunctionNotSupported)
        if req.data:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        if sub == P.SESSION_PROGRAMMING and self.session == P.SESSION_DEFAULT:
            raise Nrc(P.NRC.SubFunctionNotSupportedInActiveSession)
        if self.session == P.SESSION_PROGRAMMING and sub != P.SESSION_DEFAULT:
            # One tester at a time: the programming session is not taken over or restarted.
            raise Nrc(P.NRC.ConditionsNotCorrect)
        if sub != self.session:
            self._to_default()
            self.session = sub
        return bytes((sub,)) + P.session_timing_record(self.config.p2_s, self.config.p2_star_s)

    def _security(self, req: Request) -> bytes:
        self._require(session=(P.SESSION_EXTENDED, P.SESSION_PROGRAMMING))
        sub = req.subfunction
        if sub == P.SECURITY_LEVEL:
            if req.data:
                raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
            if time.monotonic() < self._lockout_until:
                raise Nrc(P.NRC.RequiredTimeDelayNotExpired)
            if self.unlocked:
                return bytes((sub,)) + bytes(P.SEED_BYTES)
            if self._seed is None:
                seed = bytes(P.SEED_BYTES)
                while seed == bytes(P.SEED_BYTES):
                    seed = self._rng.randbytes(P.SEED_BYTES)
                self._seed = seed
            return bytes((sub,)) + self._seed
        if sub == P.SECURITY_LEVEL + 1:
            key = req.data or b""
            if len(key) != P.KEY_BYTES:
                raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
            if self._seed is None:
                raise Nrc(P.NRC.RequestSequenceError)
            expected = P.security_key(self.config.secret, self._seed)
            self._seed = None
            sec = self.security
            if hmac.compare_digest(key, expected):
                self.unlocked = True
                if sec.failed:
                    sec.failed = 0
                    sec.save()
                return bytes((sub,))
            sec.failed += 1
            if sec.failed >= P.LOCKOUT_ATTEMPTS:
                sec.failed, sec.lockout_pending = 0, True
                self._lockout_until = time.monotonic() + self.config.lockout_s
            sec.save()  # before the answer: a power cut right after it must not forget the attempt
            raise Nrc(P.NRC.ExceedNumberOfAttempts if sec.lockout_pending else P.NRC.InvalidKey)
        raise Nrc(P.NRC.SubFunctionNotSupported)

    def _tester_present(self, req: Request) -> bytes:
        if req.subfunction != 0:
            raise Nrc(P.NRC.SubFunctionNotSupported)
        if req.data:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        return bytes((0,))

    def did_value(self, did: int) -> bytes:
        """The bytes of a data identifier; raises :class:`Nrc` 0x31 for an unknown one."""
        if did == P.DID_SERIAL:
            return self.config.serial.encode("ascii")
        if did == P.DID_SW_VERSION:
            return self.config.sw_version.encode("ascii")
        if did == P.DID_LAYOUTS:
            return P.pack_layouts(self.config.layouts)
        if did == P.DID_ACTIVE_BLOCK:
            return self.active.pack()
        raise Nrc(P.NRC.RequestOutOfRange)

    def _read_did(self, req: Request) -> bytes:
        data = req.data or b""
        if not data or len(data) % 2:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        out = b""
        for (did,) in struct.iter_unpack(">H", data):
            out += struct.pack(">H", did) + self.did_value(did)
        return out

    def _routine(self, req: Request) -> bytes:
        self._require(session=(P.SESSION_PROGRAMMING,))
        if req.subfunction != P.ROUTINE_START:
            raise Nrc(P.NRC.SubFunctionNotSupported)
        data = req.data or b""
        if len(data) < 2:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        rid = int.from_bytes(data[:2], "big")
        if rid not in (P.RID_ERASE, P.RID_CHECK):
            raise Nrc(P.NRC.RequestOutOfRange)
        self._require(unlocked=True)
        bank, offset, size = parse_location(data[2:])
        echo = bytes((req.subfunction,)) + data[:2]
        if rid == P.RID_CHECK:
            return echo + bytes((self.banks.check(bank, offset, size),))
        if offset != 0 or size == 0:
            raise Nrc(P.NRC.RequestOutOfRange)
        self.banks.erase(bank, self.active.bank, self._erase_starts)
        return echo

    def _erase_starts(self) -> None:
        # Like a real boot loader, announce the erase at once; _Pending repeats 0x78 if it lasts.
        self._send(Response(service=services.RoutineControl,
                            code=P.NRC.RequestCorrectlyReceived_ResponsePending).get_payload())
        if not self._power_fails("erase"):
            time.sleep(self.config.erase_s)

    def _request_download(self, req: Request) -> bytes:
        self._require(session=(P.SESSION_PROGRAMMING,), unlocked=True)
        data = req.data or b""
        if len(data) < 2:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        if data[0] != P.DOWNLOAD_DFI:
            raise Nrc(P.NRC.RequestOutOfRange)
        bank, offset, size = parse_location(data[1:])
        self.banks.request_download(bank, offset, size, self.active.bank)
        # lengthFormatIdentifier 0x20: maxNumberOfBlockLength follows in 2 bytes.
        return bytes((0x20,)) + struct.pack(">H", self.config.max_block_length)

    def _transfer_data(self, req: Request) -> bytes:
        data = req.data or b""
        if not data or 1 + len(data) > self.config.max_block_length:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        self.banks.transfer(data[0], data[1:])
        return data[:1]

    def _transfer_exit(self, req: Request) -> bytes:
        if req.data:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        self.banks.transfer_exit()
        return b""

    def _read_memory(self, req: Request) -> bytes:
        self._require(session=(P.SESSION_EXTENDED, P.SESSION_PROGRAMMING))
        return self.banks.read(*parse_location(req.data or b""))

    def _reset(self, req: Request) -> bytes:
        if req.subfunction != P.RESET_HARD:
            raise Nrc(P.NRC.SubFunctionNotSupported)
        if req.data:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        # A real ECU answers, then restarts; answering after the re-boot looks the same on the bus.
        self._boot()
        return bytes((P.RESET_HARD,))
