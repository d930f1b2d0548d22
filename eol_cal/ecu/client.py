"""Flashing client: the programming sequence of firmware contract v1 section 3 with udsoncan.

Safety rests on the ECU's rules, which this client never works around: it only erases and
writes the inactive bank, and the ECU boots the valid bank with the highest sequence. A
failure at any step therefore leaves the previous block active.

Every request goes through :meth:`UdsSession.call`, which names the step, retries what is
safe to repeat after a timeout (the ECU acknowledges a repeated TransferData without
rewriting it), and turns every NRC, timeout and transport failure into an :class:`EcuError`
whose message says which step failed and why.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import can
import isotp
import udsoncan
from udsoncan.client import Client
from udsoncan.common.DidCodec import DidCodec
from udsoncan.connections import PythonIsoTpConnection
from udsoncan.exceptions import (InvalidResponseException, NegativeResponseException,
                                 TimeoutException, UnexpectedResponseException)

from eol_cal.ecu import protocol as P
from eol_cal.ecu.transport import IsoTpTiming, make_stack
from eol_cal.errors import CheckFailed, EolCalError, InputError
from eol_cal.firmware import block as B

log = logging.getLogger(__name__)

SeedToKey = Callable[[bytes], bytes]
"""A seed-to-key algorithm: seed bytes in, key bytes out."""


class EcuError(EolCalError):
    """The ECU refused a request, did not answer, or the flash was refused (exit code 2).

    Attributes
    ----------
    step : str
        The step of the sequence that failed.
    nrc : int or None
        The negative response code, when the ECU gave one.
    """

    def __init__(self, step: str, reason: str, nrc: int | None = None) -> None:
        super().__init__(f"{step}: {reason}")
        self.step = step
        self.nrc = nrc


class VerifyFailed(CheckFailed):
    """The block was written but the ECU's check, the read-back or FD01 disagrees (exit code 1)."""

    def __init__(self, step: str, reason: str) -> None:
        super().__init__(f"{step}: {reason}")
        self.step = step


def hmac_seed_to_key(secret: bytes) -> SeedToKey:
    """The contract's algorithm: ``key = HMAC-SHA256(secret, seed)[:4]``."""
    if len(secret) != P.SECRET_BYTES:
        raise InputError(None, "secret", f"{len(secret)} bytes, the contract's secret has {P.SECRET_BYTES}")
    return lambda seed: P.security_key(secret, seed)


def load_key_file(path: str | Path) -> bytes:
    """Read a 16-byte security secret written as hex (whitespace and a ``0x`` prefix allowed)."""
    try:
        text = Path(path).read_text("ascii")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(str(path), "key", f"cannot read: {exc}") from exc
    cleaned = "".join(text.split())
    cleaned = cleaned[2:] if cleaned.lower().startswith("0x") else cleaned
    try:
        secret = bytes.fromhex(cleaned)
    except ValueError as exc:
        raise InputError(str(path), "key", "not hex") from exc
    if len(secret) != P.SECRET_BYTES:
        raise InputError(str(path), "key", f"{len(secret)} bytes, expected {P.SECRET_BYTES}")
    return secret


def read_block_file(path: str | Path) -> bytes:
    """The bytes of a parameter block file: raw binary, or Intel HEX (``.hex``) at either bank."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputError(str(path), None, f"cannot read: {exc}") from exc
    if path.suffix.lower() not in (".hex", ".ihex"):
        return raw
    text = raw.decode("ascii", errors="replace")
    errors = []
    for bank in range(len(B.BANK_WORD_ADDR)):
        try:
            return B.from_intel_hex(text, bank, str(path))
        except InputError as exc:
            errors.append(str(exc))
    raise InputError(str(path), "address", "; ".join(errors))


@dataclass(frozen=True)
class ClientTiming:
    """Tester-side timing.

    Attributes
    ----------
    p2_s : float
        Wait for a response, s: the ECU's P2 (50 ms) plus the transport's delay.
    p2_star_s : float
        Wait after NRC 0x78, s: the ECU's P2* (5 s) plus margin.
    retries : int
        Extra attempts for a request that timed out (only where repeating is safe).
    tester_present_s : float
        Send TesterPresent when no request went out for this long, s (S3 is 5 s).
    isotp : IsoTpTiming
    """

    p2_s: float = 0.5
    p2_star_s: float = 5.5
    retries: int = 3
    tester_present_s: float = 2.0
    isotp: IsoTpTiming = IsoTpTiming()


class _Codec(DidCodec):
    """A DID codec that reads the whole remaining payload (single-DID reads)."""

    def __init__(self, decode: Callable[[bytes], Any]) -> None:
        super().__init__()
        self._decode = decode

    def decode(self, did_payload: bytes) -> Any:
        return self._decode(bytes(did_payload))

    def __len__(self) -> int:
        raise DidCodec.ReadAllRemainingData


def _ascii(data: bytes) -> str:
    return data.decode("ascii", errors="replace").rstrip("\0")


DID_CODECS = {
    P.DID_SERIAL: _Codec(_ascii),
    P.DID_SW_VERSION: _Codec(_ascii),
    P.DID_LAYOUTS: _Codec(P.unpack_layouts),
    P.DID_ACTIVE_BLOCK: _Codec(P.ActiveBlock.unpack),
}

_TRANSIENT = (TimeoutException, isotp.errors.BlockingSendFailure, UnexpectedResponseException)


class UdsSession:
    """A udsoncan client on ISO-TP over ``bus``, with step names, retries and TesterPresent.

    Parameters
    ----------
    bus : can.BusABC
        The tester's bus object (its own; the ISO-TP stack reads it).
    seed_to_key : SeedToKey or None
        Needed only for security access.
    timing : ClientTiming
    """

    def __init__(self, bus: can.BusABC, *, seed_to_key: SeedToKey | None = None,
                 timing: ClientTiming = ClientTiming()) -> None:
        self.timing = timing
        self.seed_to_key = seed_to_key
        # Blocking send: udsoncan's P2 timer must start after the last consecutive frame.
        stack = make_stack(bus, tx_id=P.TESTER_ID, rx_id=P.ECU_ID, blocking_send=True, timing=timing.isotp)
        config = dict(udsoncan.configs.default_client_config)
        config.update({
            "request_timeout": None,
            "p2_timeout": timing.p2_s,
            "p2_star_timeout": timing.p2_star_s,
            "use_server_timing": False,
            "data_identifiers": DID_CODECS,
            "server_address_format": P.ADDRESS_BITS,
            "server_memorysize_format": P.SIZE_BITS,
            "security_algo": self._security_algo,
        })
        self.client = Client(PythonIsoTpConnection(stack), config=config)
        self._lock = threading.RLock()
        self._last_request = time.monotonic()
        self._stop = threading.Event()
        self._keepalive: threading.Thread | None = None
        self.in_session = False
        self.retries_used = 0

    def _security_algo(self, level: int, seed: bytes, params: Any = None) -> bytes:
        assert self.seed_to_key is not None
        return self.seed_to_key(bytes(seed))

    def __enter__(self) -> "UdsSession":
        self.client.open()
        self._keepalive = threading.Thread(target=self._keep_alive, name="tester-present", daemon=True)
        self._keepalive.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._keepalive is not None:
            self._keepalive.join(1.0)
        self.client.close()

    def _keep_alive(self) -> None:
        # S3 must not expire during a long step of the caller (a slow read-back, a pause).
        while not self._stop.wait(0.05):
            if not self.in_session or time.monotonic() - self._last_request < self.timing.tester_present_s:
                continue
            with self._lock:
                try:
                    with self.client.suppress_positive_response:
                        self.client.tester_present()
                except Exception as exc:  # noqa: BLE001 - best effort; the next real request reports
                    log.debug("TesterPresent failed: %s", exc)
                self._last_request = time.monotonic()

    def call(self, step: str, func: Callable[..., Any], *args: Any, retry: bool = True) -> Any:
        """Run one udsoncan request, naming ``step`` in any error.

        Transient failures (no answer, ISO-TP send failure, a stale answer) are retried
        ``timing.retries`` times when ``retry``; negative responses never are.
        """
        attempts = 1 + (self.timing.retries if retry else 0)
        last: Exception | None = None
        for attempt in range(attempts):
            with self._lock:
                try:
                    return func(*args)
                except NegativeResponseException as exc:
                    code = exc.response.code
                    raise EcuError(step, f"ECU answered {P.nrc_text(code)}", nrc=code) from None
                except InvalidResponseException as exc:
                    raise EcuError(step, f"invalid response from the ECU: {exc}") from None
                except _TRANSIENT as exc:
                    last = exc
                    if attempt + 1 < attempts:
                        self.retries_used += 1
                        log.info("%s: %s; retrying (%d/%d)", step, exc, attempt + 1, attempts - 1)
                finally:
                    self._last_request = time.monotonic()
        if isinstance(last, TimeoutException):
            reason = (f"no response from the ECU (P2 {self.timing.p2_s:g} s) after {attempts} attempt(s): "
                      "is it powered and on this bus at 0x7E0/0x7E8?")
        elif isinstance(last, isotp.errors.BlockingSendFailure):
            reason = (f"ISO-TP send failed after {attempts} attempt(s) (no flow control from the ECU "
                      f"within N_Bs {self.timing.isotp.n_bs_ms} ms)")
        else:
            reason = f"unexpected response after {attempts} attempt(s): {last}"
        raise EcuError(step, reason)

    # --- the services, one line each ------------------------------------------------------------
    def session(self, session: int) -> None:
        names = {P.SESSION_DEFAULT: "default", P.SESSION_EXTENDED: "extended", P.SESSION_PROGRAMMING: "programming"}
        self.call(f"{names[session]} session (10 {session:02X})", self.client.change_session, session)
        self.in_session = session != P.SESSION_DEFAULT

    def unlock(self) -> None:
        if self.seed_to_key is None:
            raise EcuError("security access (27)", "no seed-to-key algorithm: give --key-file")
        self.call("security access (27 01/02)", self.client.unlock_security_access, P.SECURITY_LEVEL)

    def read_did(self, did: int) -> Any:
        resp = self.call(f"read DID {did:04X} (22)", self.client.read_data_by_identifier, did)
        return resp.service_data.values[did]

    def _after_loss(self, exc: EcuError, failures: int) -> None:
        """Book a lost request of a chunked transfer (the caller shrinks its requests and goes on).

        A negative response is the ECU's answer, never retried; more than ``timing.retries`` losses
        in a row end the transfer.
        """
        if exc.nrc is not None or failures > self.timing.retries:
            raise exc
        self.retries_used += 1

    def read_memory(self, word_address: int, size: int, step: str = "read memory (23)") -> bytes:
        """Read ``size`` bytes from ``word_address`` in requests of at most 1024 bytes.

        After a lost answer the request size shrinks (see :func:`_shrink`): a long ISO-TP
        message on a lossy bus rarely arrives whole.
        """
        out = bytearray()
        limit = P.MAX_READ_BYTES
        failures = 0
        while len(out) < size:
            n = min(limit, size - len(out))
            loc = P.memory_location(word_address + len(out) // P.WORD_BYTES, n)
            try:
                resp = self.call(step, self.client.read_memory_by_address, loc, retry=False)
            except EcuError as exc:
                failures += 1
                self._after_loss(exc, failures)
                limit = _shrink(limit)
                continue
            chunk = bytes(resp.service_data.memory_block)
            if len(chunk) != n:
                raise EcuError(step, f"asked for {n} bytes, got {len(chunk)}")
            out += chunk
            failures = 0
        return bytes(out)

    def download(self, word_address: int, image: bytes) -> int:
        """RequestDownload + TransferData of ``image`` at ``word_address``; returns the block count.

        On a lost block the tester does not guess whether the ECU programmed it: it requests a
        new download from the first unacknowledged word, with smaller blocks. Rewriting words
        with the same data is harmless on NOR flash (old AND new == new).
        """
        offset, blocks, failures, limit = 0, 0, 0, None
        while offset < len(image):
            resp = self.call("request download (34)", self.client.request_download,
                             P.memory_location(word_address + offset // P.WORD_BYTES, len(image) - offset))
            max_payload = ((resp.service_data.max_length - 2) // P.WORD_BYTES) * P.WORD_BYTES
            if max_payload <= 0:
                raise EcuError("request download (34)", f"maxNumberOfBlockLength {resp.service_data.max_length}")
            limit = max_payload if limit is None else min(limit, max_payload)
            bsc = 1
            while offset < len(image):
                piece = image[offset:offset + limit]
                try:
                    self.call(f"transfer data (36) at byte {offset}", self.client.transfer_data, bsc, piece,
                              retry=False)
                except EcuError as exc:
                    failures += 1
                    self._after_loss(exc, failures)
                    limit = _shrink(limit)
                    break
                offset += len(piece)
                blocks += 1
                failures = 0
                bsc = (bsc + 1) & 0xFF
        return blocks

    def routine(self, step: str, rid: int, word_address: int, size: int) -> bytes:
        resp = self.call(step, self.client.start_routine, rid, P.location_bytes(word_address, size))
        return bytes(resp.service_data.routine_status_record)

    def reset(self) -> None:
        self.call("ECU reset (11 01)", self.client.ecu_reset, P.RESET_HARD)
        self.in_session = False


MIN_BLOCK_BYTES = 64


def _shrink(limit: int) -> int:
    """Block size after a loss: a quarter, whole words, at least 64 bytes.

    With a frame-loss rate p an n-frame message arrives whole with probability (1-p)^n, so a
    2 KiB message (about 310 frames) almost never survives 1 % loss; a 64-byte one (10 frames)
    does 90 % of the time.
    """
    return max(MIN_BLOCK_BYTES, (limit // 4) // P.WORD_BYTES * P.WORD_BYTES)


@dataclass
class EcuInfo:
    """What ``eol-cal ecu info`` reports.

    Attributes
    ----------
    serial, sw_version : str
    layouts : tuple of int
    active : protocol.ActiveBlock
    block : bytes or None
        The active block read back (None with no active bank).
    """

    serial: str
    sw_version: str
    layouts: tuple[int, ...]
    active: P.ActiveBlock
    block: bytes | None = None

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "serial": self.serial, "sw_version": self.sw_version, "layouts": list(self.layouts),
            "active": {"bank": None if not self.active.has_bank else self.active.bank,
                       "sequence": self.active.sequence, "layout_version": self.active.layout_version,
                       "crc32": f"{self.active.crc32:08x}"},
            "block": None,
        }
        if self.block is not None:
            chk = B.check(self.block)
            d["block"] = {"valid": chk.valid, "reasons": list(chk.reasons)}
            if chk.valid:
                blk = B.unpack(self.block, "ECU").to_dict()
                for name in ("table_const", "table_per_amp"):
                    blk.pop(name)
                d["block"].update(blk)
        return d


def _read_active_block(s: UdsSession, active: P.ActiveBlock) -> bytes:
    base = B.BANK_WORD_ADDR[active.bank]
    head = s.read_memory(base, B.HEADER_BYTES, "read active block (23)")
    table_len = int.from_bytes(head[B.field_offset("table_len"):B.field_offset("table_len") + 2], "little")
    if not B.table_len_ok(table_len):
        raise EcuError("read active block (23)", f"bank {active.bank} header has table_len {table_len}")
    size = B.block_bytes(table_len)
    rest = s.read_memory(base + B.HEADER_BYTES // P.WORD_BYTES, size - B.HEADER_BYTES, "read active block (23)")
    return head + rest


def ecu_info(bus: can.BusABC, *, read_block: bool = True, timing: ClientTiming = ClientTiming()) -> EcuInfo:
    """Identify the ECU and (optionally) read back its active block. Needs no security access."""
    with UdsSession(bus, timing=timing) as s:
        s.session(P.SESSION_EXTENDED)
        try:
            info = EcuInfo(serial=s.read_did(P.DID_SERIAL), sw_version=s.read_did(P.DID_SW_VERSION),
                           layouts=tuple(s.read_did(P.DID_LAYOUTS)), active=s.read_did(P.DID_ACTIVE_BLOCK))
            if read_block and info.active.has_bank:
                info.block = _read_active_block(s, info.active)
        finally:
            _leave_quietly(s)
    return info


def _leave_quietly(s: UdsSession) -> None:
    """Best effort back to the default session (after an error the ECU may be gone)."""
    try:
        s.call("default session (10 01)", s.client.change_session, P.SESSION_DEFAULT, retry=False)
    except EcuError as exc:
        log.debug("leaving the session: %s", exc)
    s.in_session = False


@dataclass
class FlashReport:
    """Outcome of :func:`flash_block`.

    Attributes
    ----------
    serial : str
        ECU serial (F18C).
    bank : int
        Bank written.
    sequence : int
        Sequence of the new block (previous active + 1).
    crc32 : int
        CRC of the block as written.
    block_bytes : int
    previous : protocol.ActiveBlock
        FD01 before the flash.
    active_after : protocol.ActiveBlock or None
        FD01 after the reset (None on a dry run).
    verified : bool
        Read-back compared equal (False when ``--no-verify`` or dry run).
    dry_run : bool
    seconds : float
        Wall time, s.
    transfer_blocks : int
        TransferData requests.
    retries : int
        Requests repeated after a timeout.
    steps : list of str
        Steps completed, in order.
    """

    serial: str
    bank: int
    sequence: int
    crc32: int
    block_bytes: int
    previous: P.ActiveBlock
    active_after: P.ActiveBlock | None = None
    verified: bool = False
    dry_run: bool = False
    seconds: float = 0.0
    transfer_blocks: int = 0
    retries: int = 0
    steps: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["crc32"] = f"{self.crc32:08x}"
        for key in ("previous", "active_after"):
            if d[key] is not None:
                d[key]["crc32"] = f"{d[key]['crc32']:08x}"
        return d


def _refuse(data: bytes, source: str) -> B.ParamBlock:
    chk = B.check(data)
    if not chk.valid:
        raise InputError(source, "block", "invalid parameter block: " + "; ".join(chk.reasons))
    return B.unpack(data, source)


def flash_block(bus: can.BusABC, data: bytes, *, seed_to_key: SeedToKey | None, verify: bool = True,
                dry_run: bool = False, force: bool = False, source: str = "<block>",
                timing: ClientTiming = ClientTiming(),
                progress: Callable[[str], None] | None = None) -> FlashReport:
    """Write a parameter block into the ECU's inactive bank (contract section 3).

    Parameters
    ----------
    bus : can.BusABC
        The tester's own bus object.
    data : bytes
        A valid block image; its ``sequence`` is replaced by the ECU's active sequence + 1.
    seed_to_key : SeedToKey
        Security algorithm (:func:`hmac_seed_to_key` for the contract's ECUs).
    verify : bool
        Read the block back and compare before the reset.
    dry_run : bool
        Stop before the erase: sessions, unlock and identification only; nothing is written.
    force : bool
        Flash even when the block's serial differs from the ECU's (F18C).
    source : str
        File name for error messages.
    progress : callable or None
        Called with each step's name as it starts.

    Raises
    ------
    InputError
        The block is invalid (nothing was sent).
    EcuError
        Refused (layout, serial), an NRC, a timeout: the previous block stays active.
    VerifyFailed
        Written, but the check routine, the read-back or FD01 after the reset disagrees.
    """
    t0 = time.perf_counter()
    blk = _refuse(data, source)
    steps: list[str] = []

    def step(name: str) -> str:
        steps.append(name)
        if progress is not None:
            progress(name)
        return name

    with UdsSession(bus, seed_to_key=seed_to_key, timing=timing) as s:
        finished = False
        try:
            step("sessions")
            s.session(P.SESSION_EXTENDED)
            s.session(P.SESSION_PROGRAMMING)
            step("security access")
            s.unlock()
            step("identification")
            serial = s.read_did(P.DID_SERIAL)
            layouts = tuple(s.read_did(P.DID_LAYOUTS))
            previous = s.read_did(P.DID_ACTIVE_BLOCK)
            if blk.layout_version not in layouts:
                raise EcuError("identification", f"the ECU supports layout versions {list(layouts)}, "
                                                 f"the block is layout {blk.layout_version}")
            if blk.serial != serial and not force:
                raise EcuError("identification", f"block serial {blk.serial!r} differs from the ECU's "
                                                 f"{serial!r} (F18C); use --force to flash it anyway")
            bank = 0 if not previous.has_bank else 1 - previous.bank
            sequence = previous.sequence + 1 if previous.has_bank else 1
            if sequence >= B.SEQUENCE_INVALID[1]:
                raise EcuError("identification", f"active sequence {previous.sequence} cannot be incremented")
            image = B.pack(dataclasses.replace(blk, sequence=sequence))
            crc = B.check(image).crc_stored or 0
            report = FlashReport(serial=serial, bank=bank, sequence=sequence, crc32=crc,
                                 block_bytes=len(image), previous=previous, dry_run=dry_run, steps=steps)
            base = B.BANK_WORD_ADDR[bank]
            if dry_run:
                report.seconds = time.perf_counter() - t0
                return report

            s.routine(step("erase"), P.RID_ERASE, base, B.BANK_BYTES)
            step("download")
            report.transfer_blocks = s.download(base, image)
            s.call(step("transfer exit (37)"), s.client.request_transfer_exit)
            status = s.routine(step("check routine (31 0202)"), P.RID_CHECK, base, len(image))
            if not status or status[0] != P.CHECK_VALID:
                code = status[0] if status else None
                raise VerifyFailed("check routine", f"ECU reports bank {bank} "
                                   f"{P.CHECK_STATUS_TEXT.get(code, f'status {code}')}; the previous block stays active")
            if verify:
                back = s.read_memory(base, len(image), step("read-back verify (23)"))
                if back != image:
                    first = next(i for i, (a, b) in enumerate(zip(back, image)) if a != b)
                    raise VerifyFailed("read-back verify", f"bank {bank} differs from the block at byte {first}")
                report.verified = True
            step("reset")
            s.reset()
            step("confirm (22 FD01)")
            after = s.read_did(P.DID_ACTIVE_BLOCK)
            report.active_after = after
            expected = P.ActiveBlock(bank, sequence, blk.layout_version, crc)
            if after != expected:
                raise VerifyFailed("confirm", f"after the reset FD01 reports {after}, expected {expected}")
            finished = True
        finally:
            if not finished:
                _leave_quietly(s)
    report.seconds = time.perf_counter() - t0
    report.retries = s.retries_used
    return report


def read_active_block(bus: can.BusABC, *, timing: ClientTiming = ClientTiming()) -> bytes:
    """The active block's bytes read back from the ECU; :class:`EcuError` when no bank is active."""
    info = ecu_info(bus, read_block=True, timing=timing)
    if info.block is None:
        raise EcuError("read active block", "the ECU has no valid block (FD01 bank 0xFF)")
    return info.block
