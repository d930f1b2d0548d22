"""Raw register words <-> raw numbers, in a dyno's byte and word order (vectorised).

A register is 16 bits. ``byte_order`` is the order of its two bytes on the wire: ``big`` (the
Modbus standard, high byte first) or ``little``. A 32-bit value (``u32``, ``i32``, ``f32``)
takes two registers; ``word_order`` says which comes first: ``big`` = the high word at the lower
address ("ABCD", pymodbus ``word_order="big"``), ``little`` = the low word first ("CDAB").
``f32`` is IEEE-754 binary32; ``str`` is ASCII, two characters per register, NUL-padded.

:func:`to_words` and :func:`from_words` code arrays (a capture's samples); :func:`value_words` and
:func:`words_value` code one value (a register a status poll reads, a write), the same words
and values bit for bit without numpy's per-call cost (a dyno client polls its status ~100
times a second).
"""

from __future__ import annotations

import struct
from types import MappingProxyType
from collections.abc import Mapping, Sequence

import numpy as np

#: registers each numeric type occupies
TYPE_REGS: Mapping[str, int] = MappingProxyType({"u16": 1, "i16": 1, "u32": 2, "i32": 2, "f32": 2})
#: every value type a map may give a register (``str`` takes the entry's ``count`` registers)
TYPES: tuple[str, ...] = (*TYPE_REGS, "str")
INTEGER_TYPES: tuple[str, ...] = ("u16", "i16", "u32", "i32")
ORDERS: tuple[str, ...] = ("big", "little")

#: (lowest, highest) raw value of each integer type
RANGES: Mapping[str, tuple[int, int]] = MappingProxyType({
    "u16": (0, 0xFFFF), "i16": (-0x8000, 0x7FFF), "u32": (0, 0xFFFFFFFF), "i32": (-0x80000000, 0x7FFFFFFF),
})
_DTYPES = {"u16": (np.uint16, np.uint16), "i16": (np.int16, np.uint16), "u32": (np.uint32, np.uint32),
           "i32": (np.int32, np.uint32), "f32": (np.float32, np.uint32)}


def _swap_bytes(words: np.ndarray) -> np.ndarray:
    w = words.astype(np.uint16)
    return ((w >> 8) | (w << 8)).astype(np.uint16)


def to_words(raw: np.ndarray, type_: str, byte_order: str, word_order: str) -> np.ndarray:
    """Raw numbers of ``type_`` -> register words (uint16, ``TYPE_REGS[type_]`` per value).

    Integers must already be in the type's range (:data:`RANGES`).
    """
    value_dtype, bits_dtype = _DTYPES[type_]
    bits = np.ascontiguousarray(np.asarray(raw).astype(value_dtype)).view(bits_dtype)
    if TYPE_REGS[type_] == 2:
        hi = (bits >> 16).astype(np.uint16)
        lo = (bits & 0xFFFF).astype(np.uint16)
        words = np.stack([hi, lo] if word_order == "big" else [lo, hi], axis=-1).reshape(-1)
    else:
        words = bits.astype(np.uint16).reshape(-1)
    return _swap_bytes(words) if byte_order == "little" else words


def from_words(words: np.ndarray, type_: str, byte_order: str, word_order: str) -> np.ndarray:
    """Register words -> raw numbers of ``type_`` (the inverse of :func:`to_words`)."""
    w = np.asarray(words, dtype=np.uint16)
    if byte_order == "little":
        w = _swap_bytes(w)
    value_dtype, bits_dtype = _DTYPES[type_]
    if TYPE_REGS[type_] == 2:
        pairs = w.reshape(-1, 2).astype(np.uint32)
        hi, lo = (pairs[:, 0], pairs[:, 1]) if word_order == "big" else (pairs[:, 1], pairs[:, 0])
        bits = ((hi << 16) | lo).astype(np.uint32)
    else:
        bits = w.astype(np.uint16)
    return np.ascontiguousarray(bits.astype(bits_dtype)).view(value_dtype)


_F32 = struct.Struct(">f")
_U32 = struct.Struct(">I")


def _swap16(w: int) -> int:
    return ((w >> 8) | (w << 8)) & 0xFFFF


def value_words(raw: float | int, type_: str, byte_order: str, word_order: str) -> list[int]:
    """One raw number of ``type_`` -> its register words: :func:`to_words` of that one value."""
    try:
        # binary32 rounding to nearest as numpy's cast; a finite value beyond its range raises
        bits = _U32.unpack(_F32.pack(raw))[0] if type_ == "f32" else int(raw) & (0xFFFFFFFF if TYPE_REGS[type_] == 2 else 0xFFFF)
    except OverflowError:  # numpy's cast makes it infinite
        return [int(w) for w in to_words(np.asarray([raw]), type_, byte_order, word_order)]
    if TYPE_REGS[type_] == 2:
        words = [bits >> 16, bits & 0xFFFF] if word_order == "big" else [bits & 0xFFFF, bits >> 16]
    else:
        words = [bits]
    return [_swap16(w) for w in words] if byte_order == "little" else words


def words_value(words: Sequence[int], type_: str, byte_order: str, word_order: str) -> float | int:
    """The raw number of ``type_`` in ``words`` (its :data:`TYPE_REGS` registers): :func:`from_words`'
    one value, as a Python number."""
    ws = [_swap16(int(w)) for w in words] if byte_order == "little" else [int(w) for w in words]
    if TYPE_REGS[type_] == 2:
        hi, lo = (ws[0], ws[1]) if word_order == "big" else (ws[1], ws[0])
        bits = hi << 16 | lo
    else:
        bits = ws[0]
    if type_ == "f32":
        return float(_F32.unpack(_U32.pack(bits))[0])
    if type_ == "i16":
        return bits - 0x10000 if bits & 0x8000 else bits
    if type_ == "i32":
        return bits - 0x100000000 if bits & 0x80000000 else bits
    return bits


def text_to_words(text: str, count: int, byte_order: str) -> list[int]:
    """ASCII text -> ``count`` registers, two characters each (the first in the first byte on the wire)."""
    raw = text.encode("ascii")[: 2 * count].ljust(2 * count, b"\0")
    dtype = ">u2" if byte_order == "big" else "<u2"
    return [int(x) for x in np.frombuffer(raw, dtype=dtype)]


def words_to_text(words: list[int], byte_order: str) -> str:
    """Registers -> ASCII text up to the first NUL (bytes outside ASCII become U+FFFD)."""
    dtype = ">u2" if byte_order == "big" else "<u2"
    raw = np.asarray(words, dtype=np.uint16).astype(dtype).tobytes()
    return raw.split(b"\0", 1)[0].decode("ascii", "replace")
