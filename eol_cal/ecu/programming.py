"""The simulated ECU's boot-loader side: erase, download, transfer, exit and check on the banks.

The UDS services of :mod:`eol_cal.ecu.sim_ecu` parse requests and enforce sessions and security;
this module keeps the programming state (which bank is erased, the open download, the last
accepted block counter) and applies the contract's rules (revision 1.1) to the flash:

- RequestDownload only at the start of a bank (no resume mid-bank), never into the active
  bank (NRC 0x70), only into a bank erased since its last download (NRC 0x24);
- a repeat of the last accepted TransferData (same counter and length: its answer was lost)
  is answered positively and not programmed twice; a repeated RequestTransferExit is answered
  positively while no new RequestDownload came;
- the check routine reads and reports; the active bank changes only at boot.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol
from collections.abc import Callable

from eol_cal.ecu import protocol as P
from eol_cal.ecu.flash import NorFlash, ProgramError, bank_at
from eol_cal.firmware import block as B


class Nrc(Exception):
    """Raised by a handler: answer this negative response code."""

    def __init__(self, code: int) -> None:
        super().__init__(P.nrc_text(code))
        self.code = code


class PowerLoss(Exception):
    """The ECU dies here: it answers nothing more (a new simulator on the flash file is the restart)."""


def parse_location(data: bytes) -> tuple[int, int, int]:
    """Parse ``44 addr size`` (nothing after it) into (bank, byte offset, size); NRCs as the ECU answers."""
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


@dataclass
class _Download:
    bank: int
    size: int
    offset: int = 0
    next_bsc: int = 1
    last_bsc: int | None = None
    last_len: int = 0


class ProgramFaults(Protocol):
    """The programming faults of :class:`eol_cal.ecu.sim_ecu.Faults` (byte offsets of the download)."""

    power_loss_byte: int | None
    corrupt_byte: int | None
    wrong_block_counter: int | None


class BankProgrammer:
    """Programming state of the two banks between a session's erase and its transfer exit.

    Parameters
    ----------
    flash : NorFlash
    faults : ProgramFaults
    power_fails : callable
        ``power_fails(step)`` says whether power fails at this request of ``step``.
    """

    def __init__(self, flash: NorFlash, faults: ProgramFaults, power_fails: Callable[[str], bool]) -> None:
        self.flash = flash
        self.faults = faults
        self._power_fails = power_fails
        self.programmed_blocks = 0
        """TransferData blocks written into flash (a repeat is not counted)."""
        self._transfers = 0
        self.forget()

    def forget(self) -> None:
        """A session change or reset: no bank counts as erased, no download is open."""
        self.erased: set[int] = set()
        self.download: _Download | None = None
        self.exited = False

    def erase(self, bank: int, active_bank: int, before: Callable[[], None]) -> None:
        """Erase ``bank`` (NRC 0x22 for the active one); ``before`` announces it (0x78) first."""
        if bank == active_bank:
            raise Nrc(P.NRC.ConditionsNotCorrect)
        before()
        self.download = None
        self.exited = False
        self.erased.discard(bank)
        if self._power_fails("erase"):
            self.flash.erase(bank, interrupted=True)
            raise PowerLoss
        self.flash.erase(bank)
        self.erased.add(bank)

    def request_download(self, bank: int, offset: int, size: int, active_bank: int) -> None:
        if size == 0 or size % P.WORD_BYTES or offset != 0:
            raise Nrc(P.NRC.RequestOutOfRange)  # a download starts at a bank's start: no resume mid-bank
        if bank == active_bank:
            raise Nrc(P.NRC.UploadDownloadNotAccepted)
        if bank not in self.erased:
            raise Nrc(P.NRC.RequestSequenceError)
        self.erased.discard(bank)  # one download per erase
        self.download = _Download(bank=bank, size=size)
        self.exited = False
        self._transfers = 0

    def transfer(self, bsc: int, chunk: bytes) -> None:
        d = self.download
        if d is None:
            raise Nrc(P.NRC.RequestSequenceError)
        self._transfers += 1
        if self._transfers == self.faults.wrong_block_counter:
            raise Nrc(P.NRC.WrongBlockSequenceCounter)
        if bsc == d.last_bsc and len(chunk) == d.last_len:
            return  # ISO 14229-1: a repeated block (its answer was lost) is acknowledged, not rewritten
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
            raise PowerLoss
        cb = self.faults.corrupt_byte
        if cb is not None and d.offset <= cb < d.offset + len(chunk):
            worn = bytearray(chunk)
            worn[cb - d.offset] &= 0xFE
            chunk = bytes(worn)
        try:
            self.flash.program(d.bank, d.offset, chunk)
        except ProgramError:
            self.download = None
            raise Nrc(P.NRC.GeneralProgrammingFailure) from None
        self.programmed_blocks += 1
        d.offset += len(chunk)
        d.last_bsc, d.last_len = bsc, len(chunk)
        d.next_bsc = P.next_block_counter(bsc)

    def transfer_exit(self) -> None:
        d = self.download
        if d is None:
            if self.exited:
                return  # the repeat of an exit whose answer was lost
            raise Nrc(P.NRC.RequestSequenceError)
        if d.offset != d.size:
            raise Nrc(P.NRC.RequestSequenceError)
        self.download = None
        self.exited = True

    def check(self, bank: int, offset: int, size: int) -> int:
        """The check routine's status byte; it changes nothing (the active bank is chosen at boot)."""
        if size == 0:
            raise Nrc(P.NRC.RequestOutOfRange)
        return B.check(self.flash.read(bank, offset, size)).status

    def read(self, bank: int, offset: int, size: int) -> bytes:
        if not 0 < size <= P.MAX_READ_BYTES:
            raise Nrc(P.NRC.RequestOutOfRange)
        return self.flash.read(bank, offset, size)
