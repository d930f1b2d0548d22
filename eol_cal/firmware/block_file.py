"""Block files: Intel HEX at a bank's flash address, and the one rule every command reads a
block file with (:func:`read_block_file`)."""

from __future__ import annotations

import io
import os
from pathlib import Path

from intelhex import IntelHex, IntelHexError

from eol_cal.errors import InputError
from eol_cal.firmware.block_layout import BANK_BYTE_ADDR, BANK_BYTES
from eol_cal.infra.inputs import read_bytes


def to_intel_hex(data: bytes, bank: int) -> str:
    """Intel HEX text of a bank image placed at its F28335 flash address.

    The contract gives word addresses; HEX records count bytes, so the image starts at byte
    address ``2 * BANK_WORD_ADDR[bank]`` (0x650000 for bank 0, 0x660000 for bank 1) with the
    low byte of each word first. This is eol-cal's choice, documented in firmware_params/README.md.
    """
    if bank not in (0, 1):
        raise InputError(None, "bank", f"{bank!r}: must be 0 or 1")
    if len(data) > BANK_BYTES:
        raise InputError(None, "block_bytes", f"{len(data)} bytes exceed a bank ({BANK_BYTES})")
    if len(data) % 2:
        raise InputError(None, "block_bytes", f"{len(data)} bytes: the flash takes whole 16-bit words")
    ih = IntelHex()
    ih.frombytes(bytes(data), offset=BANK_BYTE_ADDR[bank])
    out = io.StringIO()
    ih.write_hex_file(out)
    return out.getvalue()


def from_intel_hex(text: str, bank: int, source: str = "<hex>") -> bytes:
    """Inverse of :func:`to_intel_hex`: the bytes stored from ``bank``'s start (gaps read 0xFF).

    Raises :class:`InputError` when the data does not lie inside that bank.
    """
    return _from_intel_hex(text, (bank,), source)[1]


def intel_hex_bank(text: str, source: str = "<hex>") -> tuple[int, bytes]:
    """(bank, bytes) of an Intel HEX image, the bank being the one whose address range holds it."""
    return _from_intel_hex(text, (0, 1), source)


def _from_intel_hex(text: str, banks: tuple[int, ...], source: str) -> tuple[int, bytes]:
    ih = IntelHex()
    try:
        ih.loadhex(io.StringIO(text))
    except (IntelHexError, ValueError) as exc:
        raise InputError(source, "hex", str(exc)) from exc
    addrs = ih.addresses()
    if not addrs:
        raise InputError(source, "hex", "no data records")
    for b in banks:
        if b not in (0, 1):
            raise InputError(source, "bank", f"{b!r}: must be 0 or 1")
        start = BANK_BYTE_ADDR[b]
        if start <= addrs[0] and addrs[-1] < start + BANK_BYTES:
            return b, ih.tobinstr(start=start, end=addrs[-1])
    ranges = ", ".join(f"bank {b}: bytes 0x{BANK_BYTE_ADDR[b]:x}..0x{BANK_BYTE_ADDR[b] + BANK_BYTES - 1:x}"
                       for b in banks)
    raise InputError(source, "address", f"data at 0x{addrs[0]:x}..0x{addrs[-1]:x} is not inside one bank ({ranges})")


#: file name endings that mark an Intel HEX block file
HEX_SUFFIXES = (".hex", ".ihex")


def read_block_file(path: str | os.PathLike, source: str | None = None) -> bytes:
    """The image of a parameter block file: the one rule every command reads blocks with.

    A file is Intel HEX when its name ends in ``.hex``/``.ihex`` or its first byte is ``:``
    (a binary block cannot start with it: its first bytes are the magic 0xEC6A, low byte
    first); the image is then the bytes stored from the start of the bank whose address range
    holds the data (:func:`intel_hex_bank`). Anything else is the raw bank image.

    Parameters
    ----------
    path : path
        The block file.
    source : str, optional
        Name used in error messages (default ``path``).

    Raises
    ------
    InputError
        The file cannot be read, or its Intel HEX is malformed or lies outside both banks.
    """
    source = source or str(path)
    data = read_bytes(path, "file", max_bytes=4 * BANK_BYTES)  # no FIFO, no device, no gigabytes
    if data[:1] == b":" or Path(path).suffix.lower() in HEX_SUFFIXES:
        try:
            text = data.decode("ascii")
        except UnicodeDecodeError as exc:
            raise InputError(source, "hex", "not ASCII text") from exc
        return intel_hex_bank(text, source)[1]
    return data
