"""The parameter block's byte layout (``docs/firmware-contract.md`` section 2), read from
``layout_v1.toml`` next to this module, the one place it is defined: field offsets, counts and
types, the table length rule, the CRC, and raw field access on a byte image.

The C header ``firmware_params/eol_param_block.h`` is generated from the same file
(:mod:`eol_cal.firmware.gen_header`); :mod:`eol_cal.firmware.block` packs and unpacks with it.
"""

from __future__ import annotations

import struct
import tomllib
import zlib
from importlib import resources
from typing import Any

import numpy as np

from eol_cal.firmware.contract import FLAGS, MAGIC


def _load_layout() -> dict[str, Any]:
    text = resources.files("eol_cal.firmware").joinpath("layout_v1.toml").read_text("utf-8")
    layout = tomllib.loads(text)
    for f in layout["field"]:
        if f["name"] == "magic":
            f["value"] = MAGIC  # the layout says where the marker is, the contract what it is
    return layout


LAYOUT: dict[str, Any] = _load_layout()
"""The parsed layout file (keys as in ``layout_v1.toml``)."""

FIELDS: dict[str, dict[str, Any]] = {f["name"]: f for f in LAYOUT["field"]}

LAYOUT_VERSION: int = LAYOUT["layout_version"]
SUPPORTED_LAYOUTS: tuple[int, ...] = (LAYOUT_VERSION,)
BANK_WORD_ADDR: tuple[int, int] = tuple(LAYOUT["bank_word_addr"])  # type: ignore[assignment]
#: each bank's start as a byte address, 2 x its word address (the contract's Intel HEX and A2L rule)
BANK_BYTE_ADDR: tuple[int, int] = tuple(2 * a for a in BANK_WORD_ADDR)  # type: ignore[assignment]
BANK_WORDS: int = LAYOUT["bank_words"]
BANK_BYTES: int = LAYOUT["bank_bytes"]
HEADER_BYTES: int = LAYOUT["header_bytes"]
TABLE_LEN_MIN: int = LAYOUT["table_len_min"]
TABLE_LEN_MAX: int = LAYOUT["table_len_max"]


def flag_names(flags: int) -> str:
    """The block's flags by name, ``COMP_ENABLE|INTERP_ENABLE|EST_...`` (``none`` when no bit is
    set); bits the contract does not define follow as one hex number."""
    names = [name for name, f in FLAGS.items() if flags & (1 << f.bit)]
    unknown = flags & ~sum(1 << f.bit for f in FLAGS.values())  # FLAGS itself, so a bit added to it is named
    if unknown:
        names.append(f"0x{unknown:x}")
    return "|".join(names) or "none"


SEQUENCE_INVALID = (0, 0xFFFFFFFF)

STRUCT = {"u16": "<H", "u32": "<I", "f32": "<f"}
SIZE = {"u8": 1, "u16": 2, "u32": 4, "f32": 4}

if LAYOUT_VERSION != 1 or BANK_BYTES != 2 * BANK_WORDS:
    # the layout file is package data: a wrong one is a broken installation, not bad input
    raise ImportError(f"layout_v1.toml is not layout version 1 (version {LAYOUT_VERSION}, "
                      f"bank {BANK_BYTES} bytes for {BANK_WORDS} words)")


def block_bytes(table_len: int) -> int:
    """Total size of a block with ``table_len`` table entries, CRC included (bytes): 104 + 8*N."""
    return HEADER_BYTES + LAYOUT["bytes_per_n"] * table_len + LAYOUT["trailer_bytes"]


def field_offset(name: str, table_len: int = 0) -> int:
    """Byte offset of field ``name`` from the bank start for a block of ``table_len`` entries."""
    f = FIELDS[name]
    return f["offset"] + f.get("offset_per_n", 0) * table_len


def field_count(name: str, table_len: int = 0) -> int:
    """Number of elements of field ``name`` (``table_len`` for the tables)."""
    count = FIELDS[name].get("count", 1)
    return table_len if count == "N" else count


def table_len_ok(n: int) -> bool:
    """True when ``n`` is a power of two within the layout's table length range."""
    return TABLE_LEN_MIN <= n <= TABLE_LEN_MAX and n & (n - 1) == 0


def crc32(data: bytes) -> int:
    """CRC-32/ISO-HDLC (the zlib/PNG CRC) of ``data``; check value of b"123456789" is 0xCBF43926."""
    return zlib.crc32(data) & 0xFFFFFFFF


def put_field(buf: bytearray, name: str, n: int, value: Any) -> None:
    """Write field ``name`` of a block of ``table_len`` ``n`` into ``buf`` (little-endian)."""
    f = FIELDS[name]
    off = field_offset(name, n)
    if f["type"] == "u8":
        raw = bytes(value)
        buf[off:off + len(raw)] = raw
    elif field_count(name, n) == 1 and not isinstance(value, (tuple, list, np.ndarray)):
        struct.pack_into(STRUCT[f["type"]], buf, off, value)
    else:
        dt = {"u16": "<u2", "u32": "<u4", "f32": "<f4"}[f["type"]]
        raw = np.asarray(value, dtype=dt).tobytes()
        buf[off:off + len(raw)] = raw


def get_field(data: bytes, name: str, n: int) -> Any:
    """Read field ``name`` of a block of ``table_len`` ``n`` from ``data`` (int, bytes or array)."""
    f = FIELDS[name]
    off = field_offset(name, n)
    count = field_count(name, n)
    if f["type"] == "u8":
        return bytes(data[off:off + count])
    if FIELDS[name].get("count", 1) == 1:
        return struct.unpack_from(STRUCT[f["type"]], data, off)[0]
    dt = {"u16": "<u2", "u32": "<u4", "f32": "<f4"}[f["type"]]
    return np.frombuffer(bytes(data[off:off + count * SIZE[f["type"]]]), dtype=dt)
