"""Make an earlier calibration active again: read a bank's block, check it, re-flash it.

The ECU boots the valid bank with the highest sequence (contract section 2), so an older block
becomes active only by being written again with a sequence above the active one. That is an
ordinary flash (:func:`eol_cal.ecu.sequence.flash_block`: the inactive bank, read-back before
the CRC, check routine, reset, FD01 confirm), of a block read from the ECU and checked here
first: valid by the contract's rules and physically sane for the station's motor
(:mod:`eol_cal.firmware.block_sanity`).

The previous calibration lives in the inactive bank, which is the bank the flash erases and
writes: the block is held in memory (and, when the caller saves it, in a file) from the read
to the end of the flash. A flash that fails leaves the active block active and that bank erased.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import can

from eol_cal.ecu import protocol as P
from eol_cal.ecu.client import read_bank
from eol_cal.ecu.sequence import FlashReport, flash_block
from eol_cal.ecu.session import ClientTiming, UdsSession
from eol_cal.errors import InputError
from eol_cal.firmware import block as B
from eol_cal.firmware.block_sanity import require_safe
from eol_cal.domain.motor_params import MotorParams

#: ``which`` of :func:`read_bank_block` that means the bank that is not active
PREVIOUS = "previous"


@dataclass(frozen=True)
class BankBlock:
    """A block read from one of the ECU's banks.

    Attributes
    ----------
    bank : int
        The bank it was read from.
    data : bytes
        The block, ``block_bytes`` long.
    active : protocol.ActiveBlock
        FD01 when it was read (which bank the ECU runs).
    """

    bank: int
    data: bytes
    active: P.ActiveBlock

    @property
    def is_active(self) -> bool:
        return self.active.has_bank and self.active.bank == self.bank

    @property
    def source(self) -> str:
        """The block's name in messages."""
        return f"ECU bank {self.bank}"


def _bank_of(which: int | str, active: P.ActiveBlock) -> int:
    if which == PREVIOUS:
        if not active.has_bank:
            raise InputError("ECU", "bank", "no bank is active (FD01 bank 0xFF), so there is no previous block")
        return 1 - active.bank
    if which not in range(len(B.BANK_WORD_ADDR)):
        raise InputError(None, "bank", f"{which!r} is not a bank (0, 1 or {PREVIOUS})")
    return int(which)


def _read(s: UdsSession, bank: int) -> bytes:
    """The block in ``bank``; refused when its header says nothing sane (an erased or damaged bank)."""
    data = read_bank(s, bank, f"read bank {bank} (23)")
    if len(data) == B.HEADER_BYTES:  # the rest of a block that was read is checked before the flash
        raise InputError(f"ECU bank {bank}", "block", "no block to restore: " + "; ".join(B.check(data).reasons))
    return data


def read_bank_block(bus: can.BusABC, which: int | str, *, timing: ClientTiming = ClientTiming()) -> BankBlock:
    """Read the block in bank ``which`` (0, 1 or :data:`PREVIOUS`, the bank not active). No security access.

    Raises
    ------
    InputError
        No such bank, no active bank to take the previous of, or a bank without a block.
    EcuError
        The ECU did not answer or refused.
    """
    with UdsSession(bus, timing=timing) as s:
        s.session(P.SESSION_EXTENDED)
        try:
            active = s.read_did(P.DID_ACTIVE_BLOCK)
            bank = _bank_of(which, active)
            data = _read(s, bank)
        finally:
            s.leave()
    return BankBlock(bank, data, active)


def check_restorable(data: bytes, source: str, motor: MotorParams) -> B.ParamBlock:
    """The block, when it is valid (every rule, the CRC included) and sane for ``motor``.

    Raises
    ------
    InputError
        Naming ``source``: which rule the block breaks.
    """
    chk = B.check(data)
    if not chk.valid:
        raise InputError(source, "block", "not a valid block, not restored: " + "; ".join(chk.reasons))
    blk = B.unpack(data, source)
    require_safe(blk, motor, source, check_type=False)  # the flash checks the type against the ECU's own
    return blk


def restore_block(bus: can.BusABC, data: bytes, source: str, *, seed_to_key: Callable[[bytes], bytes],
                  motor: MotorParams, timing: ClientTiming = ClientTiming(),
                  progress: Callable[[str], None] | None = None) -> FlashReport:
    """Flash a checked earlier block again, with the ECU's active sequence + 1 (it becomes active).

    Returns
    -------
    FlashReport
        As :func:`eol_cal.ecu.sequence.flash_block` (read-back verified).
    """
    check_restorable(data, source, motor)
    return flash_block(bus, data, seed_to_key=seed_to_key, verify=True, source=source, timing=timing,
                       progress=progress, motor=motor)
