"""The simulated ECU's two parameter banks: NOR-flash semantics, persisted in a file.

The file is the raw image of both sectors (bank 0 then bank 1, 65536 bytes each, words
little-endian). Every erase and program writes the whole image through atomically
(:func:`eol_cal.infra.atomic.atomic_path`), so a simulator started later on the same file
(a "restart") sees exactly what the flash held, including the damage a power loss left behind.
"""

from __future__ import annotations

import json
import os
import random
from pathlib import Path

import numpy as np

from eol_cal.infra.atomic import atomic_write
from eol_cal.ecu import protocol as P
from eol_cal.errors import InputError
from eol_cal.firmware import block as B
from eol_cal.infra.inputs import read_bytes

N_BANKS = len(B.BANK_WORD_ADDR)
ERASED = P.ERASED_BYTE


class ProgramError(Exception):
    """A program operation needed a bit to go from 0 to 1 (NOR flash cannot; erase first)."""


def bank_at(word_address: int, size_bytes: int) -> tuple[int, int]:
    """Locate ``[word_address, +size_bytes)`` inside one bank.

    Returns
    -------
    bank, byte_offset
        Bank index and the byte offset of ``word_address`` from that bank's start.

    Raises
    ------
    ValueError
        The range is not wholly inside one bank.
    """
    for bank, base in enumerate(B.BANK_WORD_ADDR):
        offset = (word_address - base) * P.WORD_BYTES
        if 0 <= offset < B.BANK_BYTES:
            if size_bytes < 0 or offset + size_bytes > B.BANK_BYTES:
                raise ValueError(f"{size_bytes} bytes from word 0x{word_address:06X} run past bank {bank}")
            return bank, offset
    raise ValueError(f"word address 0x{word_address:06X} is not in a parameter bank")


class NorFlash:
    """Two flash sectors with NOR semantics, optionally backed by a file.

    Parameters
    ----------
    path : path or None
        Image file; created erased when missing. None keeps the flash in memory only.
    seed : int
        Seed of the RNG that makes the "arbitrary" words of an interrupted erase or program.
    """

    def __init__(self, path: str | os.PathLike[str] | None = None, *, seed: int = 0) -> None:
        self.path = Path(path) if path is not None else None
        self._rng = random.Random(seed)
        size = N_BANKS * B.BANK_BYTES
        if self.path is not None and self.path.exists():
            raw = read_bytes(self.path, "flash image", max_bytes=size, register=False)
            if len(raw) != size:
                raise InputError(str(self.path), "size",
                                 f"{len(raw)} bytes; a flash image of {N_BANKS} banks has {size}")
            self._mem = np.frombuffer(raw, dtype=np.uint8).copy()
        else:
            self._mem = np.full(size, ERASED, dtype=np.uint8)
            self.persist()

    def persist(self) -> None:
        """Write the image through to the file (no-op without a file)."""
        if self.path is not None:
            atomic_write(self.path, self._mem.tobytes())

    def bank(self, bank: int) -> bytes:
        """The whole sector of ``bank`` (65536 bytes)."""
        start = bank * B.BANK_BYTES
        return self._mem[start:start + B.BANK_BYTES].tobytes()

    def read(self, bank: int, offset: int, size: int) -> bytes:
        """``size`` bytes from byte ``offset`` of ``bank``."""
        start = bank * B.BANK_BYTES + offset
        return self._mem[start:start + size].tobytes()

    def erase(self, bank: int, *, interrupted: bool = False) -> None:
        """Erase a sector to 0xFF; ``interrupted`` leaves arbitrary words (power lost mid-erase)."""
        start = bank * B.BANK_BYTES
        if interrupted:
            garbage = self._rng.randbytes(B.BANK_BYTES)
            self._mem[start:start + B.BANK_BYTES] = np.frombuffer(garbage, dtype=np.uint8)
        else:
            self._mem[start:start + B.BANK_BYTES] = ERASED
        self.persist()

    def program(self, bank: int, offset: int, data: bytes, *, cut_at: int | None = None) -> None:
        """Program ``data`` (whole words) at byte ``offset`` of ``bank``: stored = old AND new.

        Parameters
        ----------
        cut_at : int or None
            Power fails while programming byte ``cut_at`` of ``data``: the words before it are
            programmed, the word in flight gets an arbitrary value (bits can only clear), the
            words after it stay as they were.

        Raises
        ------
        ProgramError
            A bit of ``data`` is 1 where the flash holds 0; nothing is written.
        """
        if len(data) % P.WORD_BYTES or offset % P.WORD_BYTES:
            raise ValueError("flash is programmed in whole 16-bit words")
        start = bank * B.BANK_BYTES + offset
        new = np.frombuffer(bytes(data), dtype=np.uint8)
        old = self._mem[start:start + new.size]
        if cut_at is None:
            if np.any(new & ~old):
                raise ProgramError(f"bank {bank} byte 0x{offset + int(np.argmax(new & ~old)):04X}: "
                                   "a bit must go from 0 to 1")
            self._mem[start:start + new.size] = old & new
        else:
            word = (cut_at // P.WORD_BYTES) * P.WORD_BYTES
            self._mem[start:start + word] = old[:word] & new[:word]
            flight = np.frombuffer(self._rng.randbytes(P.WORD_BYTES), dtype=np.uint8)
            end = min(word + P.WORD_BYTES, new.size)
            self._mem[start + word:start + end] &= flight[:end - word]
        self.persist()


def select_active(flash: NorFlash) -> tuple[P.ActiveBlock, bytes | None]:
    """The boot loader's choice: the valid bank with the highest sequence (contract section 2).

    Returns
    -------
    active, data
        The FD01 record and the active block's bytes (None when no bank is valid).
    """
    best: tuple[P.ActiveBlock, bytes] | None = None
    for bank in range(N_BANKS):
        image = flash.bank(bank)
        chk = B.check(image)
        if not chk.valid:
            continue
        blk = B.unpack(image, f"bank {bank}")
        assert blk.layout_version is not None  # a ParamBlock's layout is never None once made (__post_init__)
        data = image[:blk.block_bytes]
        if best is None or blk.sequence > best[0].sequence:
            best = (P.ActiveBlock(bank, blk.sequence, blk.layout_version, chk.crc_stored or 0), data)
    if best is None:
        return P.ActiveBlock(P.NO_BANK, 0, 0, 0), None
    return best


def active_block_from_file(path: str | os.PathLike[str]) -> bytes | None:
    """The bytes of the block a simulated ECU with flash image ``path`` would boot, or None.

    For other simulators (the dyno's plant) that must run the compensation the ECU runs.
    Raises :class:`InputError` when the file is missing or has the wrong size.
    """
    if not Path(path).exists():
        raise InputError(str(path), None, "flash image not found")
    return select_active(NorFlash(path))[1]


class SecurityMemory:
    """Security-access state the ECU keeps in non-volatile memory (revision 1.1).

    Wrong keys in a row and whether a lock-out delay is running survive a reset and a power
    cycle, so neither buys more attempts: at boot a pending lock-out starts its delay again
    (ISO 14229-1's delay at power-up). Kept beside the flash image as ``<image>.sec`` (JSON),
    in memory when the flash has no file.

    Parameters
    ----------
    flash : NorFlash
    """

    def __init__(self, flash: NorFlash) -> None:
        self.path = flash.path.with_name(flash.path.name + ".sec") if flash.path is not None else None
        self.failed = 0
        self.lockout_pending = False
        if self.path is not None and self.path.exists():
            try:
                state = json.loads(read_bytes(self.path, max_bytes=4096, register=False))
                self.failed = int(state["failed"])
                self.lockout_pending = bool(state["lockout_pending"])
            except (InputError, ValueError, KeyError, TypeError, RecursionError):
                # A torn record reads as locked out: failing safe costs one delay, never attempts.
                self.failed, self.lockout_pending = 0, True

    def save(self) -> None:
        if self.path is not None:
            atomic_write(self.path, json.dumps({"failed": self.failed,
                                                "lockout_pending": self.lockout_pending}).encode("ascii"))
