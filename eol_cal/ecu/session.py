"""The tester's UDS session: udsoncan on ISO-TP with step names, bounded waits and retries.

Every request goes through :meth:`UdsSession.call`, which names the step, retries what is
safe to repeat after a timeout (the ECU acknowledges a repeated TransferData or
RequestTransferExit without acting twice, contract revision 1.1), and turns every NRC,
timeout and transport failure into one :class:`EcuError` whose message says which step
failed and why.

Every wait is bounded (docs/flashing.md, "Dead link"): an attempt waits P2, or P2* after a
0x78; a retry is made only while the ECU was heard less than S3 ago (past S3 a living ECU
has dropped the programming session anyway); a dead bus (python-can-remote closed, adapter
gone) is reported at once by :class:`~eol_cal.ecu.transport.TesterConnection`.

Real ECUs answer late: the answer to a request the tester gave up on arrives while it waits
for the next one (a RoutineControl answer 0x71 while it waited for ECUReset's 0x51 turned a
good flash into an ERROR). :func:`eol_cal.ecu.matching.answers` is the one rule of which received
message answers the request sent; :class:`~eol_cal.ecu.matching.MatchingConnection` discards any
other and goes on waiting within the same P2/P2* (udsoncan would raise on the first message of
another service).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any
from collections.abc import Callable

import can
import isotp
import udsoncan
from udsoncan.client import Client
from udsoncan.common.DidCodec import DidCodec
from udsoncan.exceptions import (InvalidResponseException, NegativeResponseException,
                                 TimeoutException, UnexpectedResponseException)

from eol_cal.ecu import protocol as P
from eol_cal.ecu.matching import MatchingConnection
from eol_cal.ecu.transport import GuardedBus, IsoTpTiming, LinkLost, make_stack
from eol_cal.errors import CheckFailed, EolCalError, InputError
from eol_cal.infra.retry import RetriesExhausted, retry_call

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
    cause : str
        ``nrc``, ``timeout`` (no answer), ``link`` (the bus itself is gone), ``invalid``
        (a malformed answer) or ``refused`` (the tester's own decision).
    ecu_boots : dict or None
        Set by the flash sequence: which block the ECU boots after this failure.
    """

    ecu_boots: dict[str, Any] | None = None

    def __init__(self, step: str, reason: str, nrc: int | None = None, cause: str = "refused") -> None:
        super().__init__(f"{step}: {reason}")
        self.step = step
        self.nrc = nrc
        self.cause = "nrc" if nrc is not None else cause


class VerifyFailed(CheckFailed):
    """The block was written but the ECU's check, the read-back or FD01 disagrees (exit code 1)."""

    ecu_boots: dict[str, Any] | None = None

    def __init__(self, step: str, reason: str) -> None:
        super().__init__(f"{step}: {reason}")
        self.step = step


@dataclass(frozen=True)
class ClientTiming:
    """Tester-side timing.

    Attributes
    ----------
    p2_s : float
        Wait for a response, s: the ECU's P2 (50 ms) plus the transport's delay.
    p2_star_s : float
        Wait after NRC 0x78, s: the ECU's P2* (5 s) plus margin.
    s3_s : float
        The ECU's S3, s: no retry once the ECU has been silent this long.
    retries : int
        Extra attempts for a request that timed out (only where repeating is safe).
    retry_delay_s : float
        Wait before the first retry, s; doubles for each further one (``eol_cal.infra.retry``).
    tester_present_s : float
        Send TesterPresent when no request went out for this long, s (S3 is 5 s).
    request_s : float
        Longest one request may take however many 0x78 the ECU sends, s (a sector erase).
    send_s : float
        Longest a request may take to leave the tester (all its frames), s.
    isotp : IsoTpTiming
    """

    p2_s: float = 0.5
    p2_star_s: float = 5.5
    s3_s: float = P.S3_S
    retries: int = 3
    retry_delay_s: float = 0.02
    tester_present_s: float = 2.0
    request_s: float = 30.0
    send_s: float = 10.0
    isotp: IsoTpTiming = IsoTpTiming()

    @property
    def dead_link_bound_s(self) -> float:
        """Longest a command goes on after the ECU's last frame, s.

        The failing request ends at most max(P2*, S3 + back-off + P2) after it: a 0x78 followed
        by silence, or retries while the silence is shorter than S3. Clean-up requests (back to
        the default session, erasing a written bank) go out only while it is shorter than S3,
        so they end within the same time. Stopping ISO-TP and closing the bus: under 1 s.
        """
        backoff = self.retry_delay_s * 2 ** max(self.retries - 1, 0)
        return max(self.p2_star_s, self.s3_s + backoff + self.p2_s) + 1.0


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


class _SilentPastS3(Exception):
    """No retry: the ECU has been silent for S3 (a living one has left the session anyway)."""

    def __init__(self, last: BaseException) -> None:
        super().__init__(str(last))
        self.last = last
SESSION_NAMES = {P.SESSION_DEFAULT: "default", P.SESSION_EXTENDED: "extended", P.SESSION_PROGRAMMING: "programming"}
SESSION_LOST_NRCS = (P.NRC.ServiceNotSupportedInActiveSession, P.NRC.SecurityAccessDenied,
                     P.NRC.SubFunctionNotSupportedInActiveSession)
"""Answers that mean the ECU is no longer in this tester's unlocked programming session."""


class UdsSession:
    """A udsoncan client on ISO-TP over ``bus``, with step names, retries and TesterPresent.

    Parameters
    ----------
    bus : can.BusABC
        The tester's bus object (its own; the ISO-TP stack reads it). Not closed here.
    seed_to_key : SeedToKey or None
        Needed only for security access.
    timing : ClientTiming
    """

    def __init__(self, bus: can.BusABC, *, seed_to_key: SeedToKey | None = None,
                 timing: ClientTiming = ClientTiming()) -> None:
        self.timing = timing
        self.seed_to_key = seed_to_key
        self.link = bus if isinstance(bus, GuardedBus) else GuardedBus(bus, owns=False)
        self.link.watch_id = P.TESTER_ID
        self.link.foreign_frames = 0
        # Blocking send: udsoncan's P2 timer must start after the last consecutive frame.
        stack = make_stack(self.link, tx_id=P.TESTER_ID, rx_id=P.ECU_ID, blocking_send=True, timing=timing.isotp)
        config = dict(udsoncan.configs.default_client_config)
        config.update({
            "request_timeout": timing.request_s,
            "p2_timeout": timing.p2_s,
            "p2_star_timeout": timing.p2_star_s,
            "use_server_timing": False,
            "data_identifiers": DID_CODECS,
            "server_address_format": P.ADDRESS_BITS,
            "server_memorysize_format": P.SIZE_BITS,
            "security_algo": self._security_algo,
            "nrc78_callback": self._heard,
        })
        self.conn = MatchingConnection(stack, self.link, timing.send_s)
        self.client = Client(self.conn, config=config)
        self._lock = threading.RLock()
        self._last_request = time.monotonic()
        self.last_heard = time.monotonic()
        self._stop = threading.Event()
        self._keepalive: threading.Thread | None = None
        self.in_session = False
        self.programming = False
        self.unlocked = False
        self.retries_used = 0
        self.last_attempts = 0
        """Attempts the last :meth:`call` made (more than 1: an answer was lost)."""

    def _security_algo(self, level: int, seed: bytes, params: Any = None) -> bytes:
        if self.seed_to_key is None:
            raise InputError(None, "secret", "security access needs the ECU's seed-to-key (its secret)")
        return self.seed_to_key(bytes(seed))

    def _heard(self) -> None:
        self.last_heard = time.monotonic()

    @property
    def silent_s(self) -> float:
        """Seconds since the ECU's last frame (answer or 0x78)."""
        return time.monotonic() - self.last_heard

    @property
    def ecu_gone(self) -> bool:
        """The link is dead, or the ECU has been silent for S3 (a living one has dropped the session)."""
        return self.link.lost is not None or self.silent_s >= self.timing.s3_s

    def __enter__(self) -> UdsSession:
        self.client.open()
        self._keepalive = threading.Thread(target=self._keep_alive, name="tester-present", daemon=True)
        self._keepalive.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._keepalive is not None:
            self._keepalive.join(1.0)
        self.client.close()
        self.link.shutdown()

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

        Transient failures (no answer, ISO-TP send failure, a stale answer) are repeated with
        the same arguments ``timing.retries`` times when ``retry``, and only while the ECU was
        heard less than S3 ago; negative responses never are, a dead link never is.
        """
        if self.link.foreign_frames and not self.unlocked:
            # CAN gives the ECU no tester identity: two testers would share one session and
            # take each other's answers. The one that has not unlocked yet steps back.
            raise EcuError(step, "another tester is talking to this ECU (requests on 0x7E0 this tester did not "
                                 "send); nothing was written", cause="refused")

        def attempt(n: int) -> Any:
            self.last_attempts = n + 1
            with self._lock:
                try:
                    result = func(*args)
                    self._heard()
                    return result
                except NegativeResponseException as exc:
                    self._heard()
                    code = exc.response.code
                    raise EcuError(step, f"ECU answered {P.nrc_text(code)}", nrc=code) from None
                except InvalidResponseException as exc:
                    raise EcuError(step, f"invalid response from the ECU: {exc}", cause="invalid") from None
                except LinkLost as exc:
                    raise EcuError(step, f"CAN link lost ({exc})", cause="link") from None
                finally:
                    self._last_request = time.monotonic()

        def before_retry(n: int, exc: BaseException) -> None:
            if self.silent_s >= self.timing.s3_s:
                raise _SilentPastS3(exc)
            self.retries_used += 1
            log.info("%s: %s; retrying (%d/%d)", step, exc, n, self.timing.retries)

        try:
            return retry_call(attempt, retries=self.timing.retries if retry else 0, delay_s=self.timing.retry_delay_s,
                              retry_on=_TRANSIENT, before_retry=before_retry)
        except RetriesExhausted as exc:
            last = exc.last
        except _SilentPastS3 as exc:
            last = exc.last
        attempts = self.last_attempts
        if isinstance(last, TimeoutException):
            reason = (f"no response from the ECU (P2 {self.timing.p2_s:g} s) after {attempts} attempt(s), "
                      f"silent for {self.silent_s:.1f} s: is it powered and on this bus at 0x7E0/0x7E8?")
        elif isinstance(last, isotp.errors.BlockingSendFailure):
            reason = (f"ISO-TP send failed after {attempts} attempt(s) (no flow control from the ECU "
                      f"within N_Bs {self.timing.isotp.n_bs_ms} ms)")
        else:
            reason = f"unexpected response after {attempts} attempt(s): {last}"
        raise EcuError(step, reason, cause="timeout")

    # --- the services, one line each ------------------------------------------------------------
    def session(self, session: int) -> None:
        step = f"{SESSION_NAMES[session]} session (10 {session:02X})"
        try:
            self.call(step, self.client.change_session, session)
        except EcuError as exc:
            if (exc.nrc == P.NRC.ConditionsNotCorrect and session == P.SESSION_PROGRAMMING
                    and self.last_attempts > 1 and not self.link.foreign_frames):
                # The answer to our own 10 02 was lost and the repeat found the session held: with
                # no other tester on the bus, it is ours.
                log.info("%s: the repeat found the programming session held by this tester", step)
            elif exc.nrc == P.NRC.ConditionsNotCorrect:
                raise EcuError(step, "ECU answered NRC 0x22 ConditionsNotCorrect: another tester holds the "
                                     f"programming session (or one ended less than S3 = {self.timing.s3_s:g} s ago "
                                     "without leaving it); wait and retry", nrc=exc.nrc) from None
            else:
                raise
        self.in_session = session != P.SESSION_DEFAULT
        self.programming = session == P.SESSION_PROGRAMMING

    def unlock(self) -> None:
        if self.seed_to_key is None:
            raise EcuError("security access (27)", "no seed-to-key algorithm: give the ECU's key")
        self.call("security access (27 01/02)", self.client.unlock_security_access, P.SECURITY_LEVEL)
        self.unlocked = True

    def enter_programming(self) -> None:
        """``10 03``, ``10 02``, ``27 01``/``27 02``: the start of every write (contract section 3)."""
        self.session(P.SESSION_EXTENDED)
        self.session(P.SESSION_PROGRAMMING)
        self.unlock()

    def read_did(self, did: int) -> Any:
        resp = self.call(f"read DID {did:04X} (22)", self.client.read_data_by_identifier, did)
        return resp.service_data.values[did]

    def routine(self, step: str, rid: int, word_address: int, size: int, *, retry: bool = True) -> bytes:
        resp = self.call(step, self.client.start_routine, rid, P.location_bytes(word_address, size), retry=retry)
        return bytes(resp.service_data.routine_status_record)

    def request_download(self, word_address: int, size: int) -> int:
        """RequestDownload; returns the data bytes one TransferData may carry (whole words).

        Not repeated: once the ECU took it, the bank is no longer erased and a repeat gets 0x24
        (revision 1.1); after a lost answer the caller starts again from the erase.
        """
        resp = self.call("request download (34)", self.client.request_download,
                         P.memory_location(word_address, size), retry=False)
        max_payload = ((resp.service_data.max_length - 2) // P.WORD_BYTES) * P.WORD_BYTES
        if max_payload <= 0:
            raise EcuError("request download (34)", f"maxNumberOfBlockLength {resp.service_data.max_length}")
        return max_payload

    def transfer(self, step: str, bsc: int, data: bytes) -> None:
        """TransferData; a lost answer is repeated with the same counter and data (revision 1.1)."""
        self.call(step, self.client.transfer_data, bsc, data)

    def transfer_exit(self) -> None:
        """RequestTransferExit; a lost answer is repeated (the ECU answers a repeat positively)."""
        self.call("transfer exit (37)", self.client.request_transfer_exit)

    def reset(self) -> None:
        self.call("ECU reset (11 01)", self.client.ecu_reset, P.RESET_HARD, retry=False)
        self.in_session = self.programming = False

    def read_memory(self, word_address: int, size: int, step: str = "read memory (23)") -> bytes:
        """Read ``size`` bytes from ``word_address`` in requests of at most 1024 bytes.

        After a lost answer the request size shrinks (see :func:`shrink`): a long ISO-TP
        message on a lossy bus rarely arrives whole. Reading twice changes nothing.
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
                if exc.cause != "timeout" or failures > self.timing.retries or self.silent_s >= self.timing.s3_s:
                    raise
                self.retries_used += 1
                limit = shrink(limit)
                continue
            chunk = bytes(resp.service_data.memory_block)
            if len(chunk) != n:
                raise EcuError(step, f"asked for {n} bytes, got {len(chunk)}", cause="invalid")
            out += chunk
            failures = 0
        return bytes(out)

    def leave(self) -> None:
        """Best effort back to the default session, one attempt (after an error the ECU may be gone).

        Only a tester that entered the programming session itself (and unlocked it, if another
        tester showed up) sends it: a tester that was refused must not end another's session.
        """
        mine = self.unlocked or not self.link.foreign_frames
        if self.in_session and self.programming and mine and not self.ecu_gone:
            try:
                self.call("default session (10 01)", self.client.change_session, P.SESSION_DEFAULT, retry=False)
            except EcuError as exc:
                log.debug("leaving the session: %s", exc)
        self.in_session = self.programming = self.unlocked = False


MIN_BLOCK_BYTES = 64


def shrink(limit: int) -> int:
    """Request size after a loss: a quarter, whole words, at least 64 bytes.

    With a frame-loss rate p an n-frame message arrives whole with probability (1-p)^n, so a
    2 KiB message (about 310 frames) almost never survives 1 % loss; a 64-byte one (10 frames)
    does 90 % of the time.
    """
    return max(MIN_BLOCK_BYTES, (limit // 4) // P.WORD_BYTES * P.WORD_BYTES)
