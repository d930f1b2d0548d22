"""Raw register words <-> raw numbers, in a dyno's byte and word order (vectorised).

A register is 16 bits. ``byte_order`` is the order of its two bytes on the wire: ``big`` (the
Modbus standard, high byte first) or ``little``. A 32-bit value (``u32``, ``i32``, ``f32``)
takes two registers; ``word_order`` says which comes first: ``big`` = the high word at the lower
address ("ABCD", pymodbus ``word_order="big"``), ``little`` = the low word first ("CDAB").
``f32`` is IEEE-754 binary32; ``str`` is ASCII, two characters per register, NUL-padded.
"""

from __future__ import annotations

from types import MappingProxyType
from collections.abc import Mapping

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
