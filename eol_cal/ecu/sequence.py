"""The flash sequence of firmware contract v1 section 3 (revision 1.1), on a :class:`UdsSession`.

Safety rests on the ECU's rules, which this tester never works around (it only erases and
writes the inactive bank; the ECU boots the valid bank with the highest sequence), and on
one rule of its own: **the new block becomes a boot candidate only when the tester has
checked it.** The ECU takes a bank as complete once its last byte is written (revision 1.1),
so the tester writes the block without its CRC, reads that back and compares, and only then
sends the CRC (the last 4 bytes) as the final TransferData. A download that breaks before
leaves a block whose CRC field is still erased (0xFFFFFFFF, and the tester never sends a
block whose CRC is 0xFFFFFFFF): it can never be valid. A failure after the CRC went out
(lost link, Ctrl-C, a refused check) erases the bank again when the ECU still answers, so
an exit other than 0 leaves the previous block active; when it cannot, the message says
that the new, checked block boots at the next reset.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, TypeVar
from collections.abc import Callable

import can

from eol_cal.ecu import protocol as P
from eol_cal.ecu.aftermath import FlashProgress, aftermath, clean_up, mark
from eol_cal.ecu.session import (ClientTiming, EcuError, SeedToKey, UdsSession,
                                 VerifyFailed, shrink)
from eol_cal.errors import EolCalError, InputError, Interrupted
from eol_cal.firmware import block as B
from eol_cal.firmware.block_layout import get_field
from eol_cal.firmware.block_sanity import MotorType, require_safe, type_problems
from eol_cal.domain.motor_params import MotorParams, load_motor

TAIL_BYTES = 4
"""The CRC: the last bytes of a block, written last (the block is valid only with them)."""
ERASED_CRC = int.from_bytes(bytes([P.ERASED_BYTE]) * TAIL_BYTES, "little")
"""The CRC field of an erased bank."""
MAX_RESTARTS = 5
"""Downloads started again from the erase after losses on the bus (smaller blocks each time)."""
_T = TypeVar("_T")


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
        The block without its CRC was read back equal before the CRC was written (False with
        ``verify=False`` or a dry run).
    dry_run : bool
    seconds : float
        Wall time, s.
    transfer_blocks : int
        TransferData requests.
    retries : int
        Requests repeated after a timeout.
    restarts : int
        Downloads started again from the erase after losses.
    steps : list of str
        Steps completed, in order.
    image : bytes
        The block as written (its sequence and CRC set): what the ECU's bank holds (empty on a
        dry run). Not in :meth:`to_dict`.
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
    restarts: int = 0
    steps: list[str] = field(default_factory=list)
    image: bytes = field(default=b"", repr=False)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        del d["image"]
        d["crc32"] = f"{self.crc32:08x}"
        for key in ("previous", "active_after"):
            if d[key] is not None:
                d[key]["crc32"] = f"{d[key]['crc32']:08x}"
        return d


def refuse_block(data: bytes, source: str, motor: MotorParams) -> B.ParamBlock:
    """The block, when it is valid and physically sane for ``motor`` (checked before any session
    opens); else an :class:`~eol_cal.errors.InputError`."""
    chk = B.check(data)
    if not chk.valid:
        raise InputError(source, "block", "invalid parameter block: " + "; ".join(chk.reasons))
    blk = B.unpack(data, source)
    require_safe(blk, motor, source, check_type=False)  # the type is checked against the ECU's own
    return blk


def _ecu_motor_type(s: UdsSession, previous: P.ActiveBlock, motor: MotorParams) -> tuple[MotorType, str]:
    """The ECU's motor type: the header of its active block (ReadMemoryByAddress, before any
    erase), else, on an ECU without one, the station's motor. (The contract has no DID for it.)"""
    if previous.has_bank:
        head = s.read_memory(B.BANK_WORD_ADDR[previous.bank], B.HEADER_BYTES, "read the active block's header (23)")
        return MotorType.of_header(head), f"the active block in bank {previous.bank}"
    return MotorType.of_motor(motor), f"no active block: the station's motor {motor.name!r}"


def _image(blk: B.ParamBlock, sequence: int) -> bytes:
    """The block with its new sequence; a CRC of 0xFFFFFFFF (the erased CRC field, which would
    make the block valid before its CRC is written) moves ``calibrated_at`` on by a second."""
    blk = dataclasses.replace(blk, sequence=sequence)
    image = B.pack(blk)
    while B.check(image).crc_stored == ERASED_CRC:
        blk = dataclasses.replace(blk, calibrated_at=blk.calibrated_at + 1)
        image = B.pack(blk)
    return image


def _send(s: UdsSession, data: bytes, start: int, limit: int, bsc: int) -> tuple[int, int]:
    """TransferData of ``data`` (the image from byte ``start``) in pieces of ``limit`` bytes.

    Returns the next block sequence counter and the number of requests.
    """
    blocks = 0
    for offset in range(0, len(data), limit):
        s.transfer(f"transfer data (36) at byte {start + offset}", bsc, data[offset:offset + limit])
        bsc = P.next_block_counter(bsc)
        blocks += 1
    return bsc, blocks


def _download_body(s: UdsSession, prog: FlashProgress, base: int, image: bytes, report: FlashReport,
                   erased: bool = False) -> int:
    """Erase (unless the bank was ``erased`` just before, :meth:`Programming.erase_ahead`),
    RequestDownload and every byte but the CRC; returns the next block counter.

    After losses on the bus the download starts again from the erase (revision 1.1: never
    resumed mid-bank) with a quarter the block size.
    """
    body = image[:-TAIL_BYTES]
    limit: int | None = None
    for restart in range(MAX_RESTARTS + 1):
        if restart or not erased:
            s.routine(prog.step("erase"), P.RID_ERASE, base, B.BANK_BYTES)
        prog.step("download")
        try:
            max_payload = s.request_download(base, len(image))
            limit = max_payload if limit is None else min(limit, max_payload)
            bsc, blocks = _send(s, body, 0, limit, 1)
        except EcuError as exc:
            if exc.cause != "timeout" or restart == MAX_RESTARTS or s.ecu_gone:
                raise
            report.restarts += 1
            limit = shrink(limit) if limit is not None else None
            continue
        report.transfer_blocks += blocks
        return bsc
    raise AssertionError("the loop returns or raises")


def flash_block(bus: can.BusABC, data: bytes, *, seed_to_key: SeedToKey | None, verify: bool = True,
                dry_run: bool = False, force: bool = False, source: str = "<block>",
                timing: ClientTiming = ClientTiming(),
                progress: Callable[[str], None] | None = None, motor: MotorParams | None = None,
                before_commit: Callable[[], None] | None = None) -> FlashReport:
    """Write a parameter block into the ECU's inactive bank (contract section 3).

    Parameters
    ----------
    bus : can.BusABC
        The tester's own bus object.
    data : bytes
        A valid block image; its ``sequence`` is replaced by the ECU's active sequence + 1.
    seed_to_key : SeedToKey
        Security algorithm (:func:`eol_cal.ecu.client.hmac_seed_to_key` for the contract's ECUs).
    verify : bool
        Read the block back (all but its CRC) and compare before the CRC makes it valid.
    dry_run : bool
        Stop before the erase: sessions, unlock and identification only; nothing is written.
    force : bool
        Flash even when the block's serial differs from the ECU's (F18C).
    motor : MotorParams, optional
        The station's motor (default the paper preset): its current rating bounds the block's
        currents (checked before any session), and its type (poles, PPR, tick) is the ECU's when
        the ECU has no active block to read it from.
    source : str
        File name for error messages.
    progress : callable or None
        Called with each step's name as it starts.
    before_commit : callable or None
        Called once the block is written and read back, before its CRC makes it a boot candidate:
        what must be done before the block may count (the station's calibration capture on disk)
        runs beside the download. An :class:`~eol_cal.errors.EolCalError` from it aborts the flash
        before the CRC (the block never counts: the previous block stays active) and is raised
        with that said.

    Raises
    ------
    InputError
        The block is invalid or physically unsafe (nothing was sent).
    EcuError
        Refused (layout, serial), an NRC, a timeout, a lost link; the message ends with what
        the ECU boots now (the previous block unless the new one was complete and checked).
    VerifyFailed
        Written, but the read-back, the check routine or FD01 after the reset disagrees.
    Interrupted
        SIGINT/SIGTERM (raised by the caller's handler); same cleanup and message as EcuError.

    Each of these raised after the session opened carries ``ecu_boots``: ``{"boots":
    "previous" | "new" | "maybe new", "bank", "sequence"}`` (the new block boots when the link
    died after its CRC was written).
    """
    t0 = time.perf_counter()
    blk = refuse_block(data, source, motor or load_motor())
    with UdsSession(bus, seed_to_key=seed_to_key, timing=timing) as s:
        flash = Programming(s, motor, progress)
        flash.identify()
        report = flash.write(blk, verify=verify, dry_run=dry_run, force=force, before_commit=before_commit)
    report.seconds = time.perf_counter() - t0
    return report


@dataclass(frozen=True)
class Identification:
    """What steps 1-3 of the sequence read (the programming session open and unlocked).

    Attributes
    ----------
    serial : str
        F18C.
    layouts : tuple of int
        FD00: the layout versions the ECU supports.
    previous : protocol.ActiveBlock
        FD01: the active block before the flash.
    ecu_type : MotorType
        The motor type of the ECU (its active block's header, else the station's motor).
    known_from : str
        Where ``ecu_type`` comes from, for a message.
    """

    serial: str
    layouts: tuple[int, ...]
    previous: P.ActiveBlock
    ecu_type: MotorType
    known_from: str

    @property
    def bank(self) -> int:
        """The inactive bank, the one written (bank 0 when none is active)."""
        return 0 if not self.previous.has_bank else 1 - self.previous.bank


class Programming:
    """The flash sequence on an open :class:`UdsSession`, in the halves :func:`flash_block` runs
    back to back: :meth:`identify` (sessions, security access, identification: nothing of the
    block needed), optionally :meth:`erase_ahead` (the inactive bank's erase), and :meth:`write`
    (the block's checks against the identification, then erase, download, read-back, CRC, check
    routine, reset, confirm). The station identifies and erases while its fit computes the block.

    A failure in any half is cleaned up as one sequence's (:func:`~eol_cal.ecu.aftermath.clean_up`: what the ECU
    boots is added to the message; a bank written past its CRC is erased again), and an
    interruption likewise (raised as :class:`~eol_cal.errors.Interrupted`).
    """

    def __init__(self, s: UdsSession, motor: MotorParams | None = None,
                 progress: Callable[[str], None] | None = None) -> None:
        self.s = s
        self.motor = motor or load_motor()
        self.prog = FlashProgress([], progress)
        self.base = 0
        self.ident: Identification | None = None
        self.erased = False

    def identify(self) -> Identification:
        """Steps 1-3: extended then programming session, security access, F18C, FD00, FD01 and
        the ECU's motor type."""
        return self._guarded(self._identify)

    def erase_ahead(self) -> bool:
        """Step 4 before the block is known, where nothing is lost by it: erase the inactive bank
        unless its header is a block's (an earlier calibration, which ``eol-cal ecu restore``
        brings back, stays until a block is written over it). The active bank is never touched:
        the ECU boots what it booted. Returns whether it erased; :meth:`write` then downloads
        without erasing again."""
        return self._guarded(self._erase_ahead)

    def write(self, blk: B.ParamBlock, *, verify: bool = True, dry_run: bool = False, force: bool = False,
              before_commit: Callable[[], None] | None = None) -> FlashReport:
        """The block's checks against the identification, then steps 4-10 (:func:`flash_block`)."""
        report = self._guarded(lambda: self._write(blk, verify, dry_run, force, before_commit))
        report.retries = self.s.retries_used
        return report

    def _identify(self) -> Identification:
        s, prog = self.s, self.prog
        prog.step("sessions")
        s.session(P.SESSION_EXTENDED)
        s.session(P.SESSION_PROGRAMMING)
        prog.step("security access")
        s.unlock()
        prog.step("identification")
        serial = s.read_did(P.DID_SERIAL)
        layouts = tuple(s.read_did(P.DID_LAYOUTS))
        previous = s.read_did(P.DID_ACTIVE_BLOCK)
        ecu_type, known_from = _ecu_motor_type(s, previous, self.motor)
        self.ident = Identification(serial, layouts, previous, ecu_type, known_from)
        self.base = B.BANK_WORD_ADDR[self.ident.bank]
        return self.ident

    def _erase_ahead(self) -> bool:
        if self.ident is None:
            raise AssertionError("identify() comes first")
        head = self.s.read_memory(self.base, B.HEADER_BYTES, "read the inactive bank's header (23)")
        if get_field(head, "magic", 0) == B.MAGIC:
            return False
        self.s.routine(self.prog.step("erase"), P.RID_ERASE, self.base, B.BANK_BYTES)
        self.erased = True
        return True

    def _write(self, blk: B.ParamBlock, verify: bool, dry_run: bool, force: bool,
               before_commit: Callable[[], None] | None) -> FlashReport:
        s, prog, ident = self.s, self.prog, self.ident
        if ident is None:
            raise AssertionError("identify() comes first")
        if blk.layout_version not in ident.layouts:
            raise EcuError("identification", f"the ECU supports layout versions {list(ident.layouts)}, "
                                             f"the block is layout {blk.layout_version}")
        if blk.serial != ident.serial and not force:
            raise EcuError("identification", f"block serial {blk.serial!r} differs from the ECU's "
                                             f"{ident.serial!r} (F18C); flash it anyway only on purpose (force)")
        mismatch = type_problems(blk, ident.ecu_type)
        if mismatch:
            raise EcuError("identification", f"the block is for another motor type than the ECU's ({ident.ecu_type}, "
                                             f"from {ident.known_from}): " + "; ".join(r for _, r in mismatch))
        previous, bank, base = ident.previous, ident.bank, self.base
        sequence = previous.sequence + 1 if previous.has_bank else 1
        if sequence >= B.SEQUENCE_INVALID[1]:
            raise EcuError("identification", f"active sequence {previous.sequence} cannot be incremented")
        image = _image(blk, sequence)
        crc = B.check(image).crc_stored or 0
        report = FlashReport(serial=ident.serial, bank=bank, sequence=sequence, crc32=crc,
                             block_bytes=len(image), previous=previous, dry_run=dry_run, steps=prog.steps,
                             image=b"" if dry_run else image)
        if dry_run:
            s.leave()
            return report
        prog.bank, prog.sequence, prog.image = bank, sequence, image
        bsc = _download_body(s, prog, base, image, report, erased=self.erased)
        if verify:
            body = image[:-TAIL_BYTES]
            back = s.read_memory(base, len(body), prog.step("read-back before the CRC (23)"))
            if back != body:
                first = next(i for i, (a, b) in enumerate(zip(back, body, strict=False)) if a != b)
                raise VerifyFailed("read-back", f"bank {bank} differs from the block at byte {first}; "
                                                "its CRC was not written")
            report.verified = True
        if before_commit is not None:
            prog.step("before the CRC")
            try:
                before_commit()
            except (EcuError, VerifyFailed):
                raise  # cleaned up by _guarded, once
            except EolCalError as exc:
                clean_up(s, prog, base, exc)
                raise
        prog.step("CRC (36)")
        prog.tail = "sent"
        _send(s, image[-TAIL_BYTES:], len(image) - TAIL_BYTES, TAIL_BYTES, bsc)
        prog.tail = "written"
        report.transfer_blocks += 1
        prog.step("transfer exit (37)")
        s.transfer_exit()
        status = s.routine(prog.step("check routine (31 0202)"), P.RID_CHECK, base, len(image))
        if not status or status[0] != P.STATUS_VALID:
            code = status[0] if status else None
            raise VerifyFailed("check routine", f"ECU reports bank {bank} "
                               + (P.CHECK_STATUS_TEXT.get(code, f"status {code}") if code is not None
                                  else "no status (an empty routine answer)"))
        prog.step("reset")
        prog.reset_sent = True  # from here the ECU may have reset (no answer, an interruption)
        expected = P.ActiveBlock(bank, sequence, blk.layout_version, crc)
        unanswered: EcuError | None = None
        try:
            s.reset()
        except EcuError as exc:
            prog.reset_sent = exc.nrc is None  # refused with an NRC: it did not reset
            if exc.cause != "timeout":
                raise
            # No answer: the ECU may have reset before its answer got out, or the answer was lost (a
            # busy bus, an ECU late to answer). FD01 tells: the new block active means it reset and
            # booted it; anything else, or no answer again, is the reset's failure as it was.
            unanswered = exc
        prog.step("confirm (22 FD01)")
        try:
            after = s.read_did(P.DID_ACTIVE_BLOCK)
        except EcuError:
            if unanswered is None:
                raise
            raise unanswered from None
        if unanswered is not None and after != expected:
            raise unanswered from None
        s.in_session = s.programming = False  # the ECU reset: its answer says so, or FD01 after a lost one
        report.active_after = after
        if after != expected:
            raise VerifyFailed("confirm", f"after the reset FD01 reports {after}, expected {expected}")
        return report

    def _guarded(self, step: Callable[[], _T]) -> _T:
        s, prog = self.s, self.prog
        try:
            return step()
        except (EcuError, VerifyFailed) as exc:
            clean_up(s, prog, self.base, exc)
            raise
        except KeyboardInterrupt as exc:  # Interrupted (SIGINT/SIGTERM) or a bare Ctrl-C
            name = exc.signal_name if isinstance(exc, Interrupted) else "SIGINT"
            try:
                outcome, word = aftermath(s, prog, self.base, rollback=True)
            except KeyboardInterrupt:  # a second signal: stop cleaning up
                outcome, word = aftermath(s, prog, self.base, rollback=False)
            interrupted = Interrupted(name, f"flash ({prog.current})", outcome)
            mark(interrupted, prog, word)
            raise interrupted from None
