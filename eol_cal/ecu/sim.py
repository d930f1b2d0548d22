"""ECU simulator: a UDS server over ISO-TP on a python-can bus implementing firmware contract v1.

udsoncan is a client library, so the server side is written here: requests are parsed once
(``udsoncan.Request.from_payload`` plus :mod:`eol_cal.ecu.protocol`), each service has one
handler, and negative answers are raised as :class:`Nrc`. The flash lives in
:class:`eol_cal.ecu.flash.NorFlash`; :class:`Faults` injects power loss, NRCs, a wrong
block counter and (through :class:`eol_cal.ecu.transport.FaultyBus`) dropped and delayed frames.

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
from dataclasses import dataclass, field

import can
from udsoncan import Request, Response, services

from eol_cal.ecu import protocol as P
from eol_cal.ecu.flash import NorFlash, ProgramError, bank_at, select_active
from eol_cal.ecu.transport import FaultyBus, IsoTpTiming, make_stack
from eol_cal.firmware import block as B

log = logging.getLogger(__name__)

STEPS = ("session", "security", "read_did", "erase", "download", "transfer", "transfer_exit",
         "check", "read_memory", "reset", "tester_present")
"""Names of the steps a power loss can be placed at (contract section 3 order)."""

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


@dataclass
class Faults:
    """Faults the simulator injects.

    Attributes
    ----------
    power_loss_step : str or None
        Power fails when a request of this step (one of :data:`STEPS`) arrives. For
        ``erase`` the sector is left with arbitrary words; for ``transfer`` programming is cut
        in the middle of the first TransferData block; other steps change no flash.
    power_loss_occurrence : int
        Which request of ``power_loss_step`` fails (1 = the first; the flash reads DIDs
        before the erase and again after the reset).
    power_loss_byte : int or None
        Power fails while programming this byte offset of the download.
    corrupt_byte : int or None
        A worn flash cell: this byte offset of the download is stored with bit 0 cleared, so
        the check routine reports a CRC mismatch.
    drop_rate : float
        Probability that a frame the ECU sends or receives is lost.
    delay_rate, delay_s : float
        Probability that a frame the ECU sends is held ``delay_s`` seconds first.
    nrc : dict of int to int
        Request service ID -> NRC the ECU answers instead of serving it.
    wrong_block_counter : int or None
        The n-th TransferData request (1-based) is answered NRC 0x73.
    seed : int
        Seed of every random choice (dropped frames, arbitrary words, seeds).
    """

    power_loss_step: str | None = None
    power_loss_occurrence: int = 1
    power_loss_byte: int | None = None
    corrupt_byte: int | None = None
    drop_rate: float = 0.0
    delay_rate: float = 0.0
    delay_s: float = 0.0
    nrc: dict[int, int] = field(default_factory=dict)
    wrong_block_counter: int | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if self.power_loss_step is not None and self.power_loss_step not in STEPS:
            raise ValueError(f"power_loss_step {self.power_loss_step!r} not one of {STEPS}")


@dataclass
class SimConfig:
    """What the simulated ECU is and how fast it runs.

    Attributes
    ----------
    serial : str
        Motor serial answered on DID F18C.
    sw_version : str
        DID F195.
    layouts : tuple of int
        Supported layout versions (DID FD00).
    secret : bytes
        16-byte security secret (the contract's development secret by default).
    s3_s, lockout_s, p2_s, p2_star_s : float
        Session timeout, security lock-out delay, announced P2 and P2*, s.
    erase_s : float
        Sector erase time, s (answered with NRC 0x78 first).
    max_block_length : int
        maxNumberOfBlockLength of the RequestDownload response: bytes of one TransferData
        request, service ID and counter included.
    isotp_timing : IsoTpTiming
    """

    serial: str = "SIM-0001"
    sw_version: str = "eol-cal-sim 1"
    layouts: tuple[int, ...] = B.SUPPORTED_LAYOUTS
    secret: bytes = P.DEV_SECRET
    s3_s: float = P.S3_S
    lockout_s: float = P.LOCKOUT_S
    p2_s: float = P.P2_S
    p2_star_s: float = P.P2_STAR_S
    erase_s: float = 0.05
    max_block_length: int = 4094
    isotp_timing: IsoTpTiming = IsoTpTiming()


class Nrc(Exception):
    """Raised by a handler: answer this negative response code."""

    def __init__(self, code: int) -> None:
        super().__init__(P.nrc_text(code))
        self.code = code


class _PowerLoss(Exception):
    pass


class _Pending:
    """Answers NRC 0x78 while a request takes longer than P2 (and again every P2*/2).

    ISO 14229-2: a server that cannot answer within P2 sends responsePending; the final
    answer goes out under the same lock, so it can never overtake a 0x78.
    """

    def __init__(self, sim: "EcuSimulator", service: type) -> None:
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


@dataclass
class _Download:
    bank: int
    size: int
    offset: int = 0
    next_bsc: int = 1
    last_bsc: int | None = None
    last_len: int = 0


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
        self.bus: can.BusABC = (FaultyBus(bus, drop_rate=f.drop_rate, delay_rate=f.delay_rate,
                                          delay_s=f.delay_s, seed=f.seed)
                                if (f.drop_rate or f.delay_rate) else bus)
        self._stack = make_stack(self.bus, tx_id=P.ECU_ID, rx_id=P.TESTER_ID, blocking_send=False,
                                 timing=self.config.isotp_timing)
        self._rng = random.Random(f.seed)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.powered_off = threading.Event()
        self.steps_seen: list[str] = []
        self._failures = 0
        self._lockout_until = 0.0
        self._transfers = 0
        self._step_counts: dict[str, int] = {}
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

    # --- life cycle -------------------------------------------------------------------------
    def _boot(self) -> None:
        """Power-on / reset: default session, locked, bank re-selected. The lock-out survives."""
        self.active, _ = select_active(self.flash)
        self._to_default()

    def _to_default(self) -> None:
        self.session = P.SESSION_DEFAULT
        self.unlocked = False
        self._seed: bytes | None = None
        self._erased: set[int] = set()
        self._download: _Download | None = None
        self._exited = False
        self._last_activity = time.monotonic()

    def start(self) -> "EcuSimulator":
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

    def __enter__(self) -> "EcuSimulator":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def alive(self) -> bool:
        return not self.powered_off.is_set()

    def _run(self) -> None:
        while not self._stop.is_set():
            if (self.session != P.SESSION_DEFAULT
                    and time.monotonic() - self._last_activity > self.config.s3_s):
                log.info("S3 expired: back to the default session, locked")
                self._to_default()
            payload = self._stack.recv(block=True, timeout=0.02)
            if payload is None:
                continue
            try:
                self._serve(bytes(payload))
            except _PowerLoss:
                log.info("power loss")
                self.powered_off.set()
                self._stack.stop()
                return
            self._last_activity = time.monotonic()

    # --- dispatch ------------------------------------------------------------------------------
    def _send(self, payload: bytes) -> None:
        self._stack.send(payload)

    def _serve(self, payload: bytes) -> None:
        req = Request.from_payload(payload)
        if req.service is None or req.service not in self._handlers:
            # No udsoncan service object exists for an unknown ID, so build 7F SID 11 here.
            self._send(bytes((0x7F, payload[0], P.NRC.ServiceNotSupported)))
            return
        step = self._step_of(req)
        self.steps_seen.append(step)
        self._step_counts[step] = self._step_counts.get(step, 0) + 1
        if step not in ("erase", "transfer") and self._power_fails(step):
            raise _PowerLoss
        pending = _Pending(self, req.service)
        try:
            if req.service.request_id() in self.faults.nrc:
                raise Nrc(self.faults.nrc[req.service.request_id()])
            data = self._handlers[req.service](req)
        except Nrc as exc:
            pending.finish(Response(service=req.service, code=exc.code).get_payload())
            return
        except BaseException:
            pending.finish(None)
            raise
        final = None
        if data is not None and not req.suppress_positive_response:
            final = Response(service=req.service, code=Response.Code.PositiveResponse, data=data).get_payload()
        pending.finish(final)

    def _power_fails(self, step: str) -> bool:
        return (self.faults.power_loss_step == step
                and self._step_counts.get(step, 0) == self.faults.power_loss_occurrence)

    @staticmethod
    def _step_of(req: Request) -> str:
        if req.service is services.RoutineControl:
            rid = int.from_bytes((req.data or b"")[:2], "big")
            return "erase" if rid == P.RID_ERASE else "check"
        return _STEP_OF_SERVICE[req.service]

    def _require(self, *, session: tuple[int, ...] | None = None, unlocked: bool = False) -> None:
        if session is not None and self.session not in session:
            raise Nrc(P.NRC.ServiceNotSupportedInActiveSession)
        if unlocked and not self.unlocked:
            raise Nrc(P.NRC.SecurityAccessDenied)

    @staticmethod
    def _location(data: bytes) -> tuple[int, int, int]:
        """Parse ``44 addr size`` (nothing after it) into (bank, byte offset, size)."""
        if not data or data[0] != P.ALFID:
            raise Nrc(P.NRC.RequestOutOfRange)
        try:
            word_address, size, rest = P.parse_location(data)
        except ValueError:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat) from None
        if rest:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        try:
            bank, offset = bank_at(word_address, size)
        except ValueError:
            raise Nrc(P.NRC.RequestOutOfRange) from None
        return bank, offset, size

    # --- services ----------------------------------------------------------------------------------
    def _session(self, req: Request) -> bytes:
        sub = req.subfunction
        if sub not in (P.SESSION_DEFAULT, P.SESSION_EXTENDED, P.SESSION_PROGRAMMING):
            raise Nrc(P.NRC.SubFunctionNotSupported)
        if req.data:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        if sub == P.SESSION_PROGRAMMING and self.session == P.SESSION_DEFAULT:
            raise Nrc(P.NRC.SubFunctionNotSupportedInActiveSession)
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
            if hmac.compare_digest(key, expected):
                self.unlocked = True
                self._failures = 0
                return bytes((sub,))
            self._failures += 1
            if self._failures >= P.LOCKOUT_ATTEMPTS:
                self._failures = 0
                self._lockout_until = time.monotonic() + self.config.lockout_s
                raise Nrc(P.NRC.ExceedNumberOfAttempts)
            raise Nrc(P.NRC.InvalidKey)
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
        bank, offset, size = self._location(data[2:])
        echo = bytes((req.subfunction,)) + data[:2]
        if rid == P.RID_ERASE:
            if offset != 0 or size == 0:
                raise Nrc(P.NRC.RequestOutOfRange)
            if bank == self.active.bank:
                raise Nrc(P.NRC.ConditionsNotCorrect)
            self._erase(bank)
            return echo
        if size == 0:
            raise Nrc(P.NRC.RequestOutOfRange)
        status = B.check(self.flash.read(bank, offset, size)).status
        return echo + bytes((status,))

    def _erase(self, bank: int) -> None:
        # Like a real boot loader, announce the erase at once; _Pending repeats 0x78 if it lasts.
        self._send(Response(service=services.RoutineControl,
                            code=P.NRC.RequestCorrectlyReceived_ResponsePending).get_payload())
        self._download = None
        self._exited = False
        self._erased.discard(bank)
        if self._power_fails("erase"):
            self.flash.erase(bank, interrupted=True)
            raise _PowerLoss
        time.sleep(self.config.erase_s)
        self.flash.erase(bank)
        self._erased.add(bank)

    def _request_download(self, req: Request) -> bytes:
        self._require(session=(P.SESSION_PROGRAMMING,), unlocked=True)
        data = req.data or b""
        if len(data) < 2:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        if data[0] != P.DOWNLOAD_DFI:
            raise Nrc(P.NRC.RequestOutOfRange)
        bank, offset, size = self._location(data[1:])
        if size == 0 or size % P.WORD_BYTES:
            raise Nrc(P.NRC.RequestOutOfRange)
        if bank == self.active.bank:
            raise Nrc(P.NRC.UploadDownloadNotAccepted)
        if bank not in self._erased:
            raise Nrc(P.NRC.RequestSequenceError)
        # A download may start anywhere in the erased bank: the tester resumes after losses.
        self._download = _Download(bank=bank, size=offset + size, offset=offset)
        self._exited = False
        self._transfers = 0
        # lengthFormatIdentifier 0x20: maxNumberOfBlockLength follows in 2 bytes.
        return bytes((0x20,)) + struct.pack(">H", self.config.max_block_length)

    def _transfer_data(self, req: Request) -> bytes:
        d = self._download
        if d is None:
            raise Nrc(P.NRC.RequestSequenceError)
        data = req.data or b""
        if not data:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        if 1 + len(data) > self.config.max_block_length:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        bsc, chunk = data[0], data[1:]
        self._transfers += 1
        if self._transfers == self.faults.wrong_block_counter:
            raise Nrc(P.NRC.WrongBlockSequenceCounter)
        if bsc == d.last_bsc and len(chunk) == d.last_len:
            # ISO 14229-1: a repeated block (its response was lost) is acknowledged, not rewritten.
            return bytes((bsc,))
        if bsc != d.next_bsc:
            raise Nrc(P.NRC.WrongBlockSequenceCounter)
        if not chunk or len(chunk) % P.WORD_BYTES:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        if d.offset + len(chunk) > d.size:
            raise Nrc(P.NRC.RequestOutOfRange)
        cut = None
        plb = self.faults.power_loss_byte
        if plb is not None and d.offset <= plb < d.offset + len(chunk):
            cut = plb - d.offset
        elif self._power_fails("transfer"):
            cut = len(chunk) // 2
        if cut is not None:
            self.flash.program(d.bank, d.offset, chunk, cut_at=cut)
            raise _PowerLoss
        cb = self.faults.corrupt_byte
        if cb is not None and d.offset <= cb < d.offset + len(chunk):
            worn = bytearray(chunk)
            worn[cb - d.offset] &= 0xFE
            chunk = bytes(worn)
        try:
            self.flash.program(d.bank, d.offset, chunk)
        except ProgramError:
            self._download = None
            raise Nrc(P.NRC.GeneralProgrammingFailure) from None
        d.offset += len(chunk)
        d.last_bsc, d.last_len = bsc, len(chunk)
        d.next_bsc = (bsc + 1) & 0xFF
        return bytes((bsc,))

    def _transfer_exit(self, req: Request) -> bytes:
        if req.data:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        d = self._download
        if d is None:
            if self._exited:
                return b""  # the repeat of an exit whose answer was lost
            raise Nrc(P.NRC.RequestSequenceError)
        if d.offset != d.size:
            raise Nrc(P.NRC.RequestSequenceError)
        self._download = None
        self._exited = True
        return b""

    def _read_memory(self, req: Request) -> bytes:
        self._require(session=(P.SESSION_EXTENDED, P.SESSION_PROGRAMMING))
        bank, offset, size = self._location(req.data or b"")
        if not 0 < size <= P.MAX_READ_BYTES:
            raise Nrc(P.NRC.RequestOutOfRange)
        return self.flash.read(bank, offset, size)

    def _reset(self, req: Request) -> bytes:
        if req.subfunction != P.RESET_HARD:
            raise Nrc(P.NRC.SubFunctionNotSupported)
        if req.data:
            raise Nrc(P.NRC.IncorrectMessageLengthOrInvalidFormat)
        # A real ECU answers, then restarts; answering after the re-boot looks the same on the bus.
        self._boot()
        return bytes((P.RESET_HARD,))
