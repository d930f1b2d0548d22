"""The parameter block's byte layouts (``docs/firmware-contract.md`` section 2), read from
``layout_v1.toml`` and ``layout_v2.toml`` next to this module, the one place each is defined: field
offsets, counts and types, the table length rule, the CRC, and raw field access on a byte image.

Layout 2 (revision 1.2) is layout 1 with the mechanical-order extension between the tables and
the CRC: ``layout_v2.toml`` lists what differs and :func:`_load_layout` merges. Every function
takes the layout ``version`` (default 1, so layout-1 callers read as before).

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


def _read(version: int) -> dict[str, Any]:
    text = resources.files("eol_cal.firmware").joinpath(f"layout_v{version}.toml").read_text("utf-8")
    return tomllib.loads(text)


def _load_layout(version: int) -> dict[str, Any]:
    layout = _read(version)
    base_version = layout.pop("extends", None)
    if base_version is not None:
        base = _load_layout(base_version)
        own = {f["name"] for f in layout["field"]}
        # a shared field keeps its place and offset; only what it says about its value may differ
        meaning = layout.pop("meaning", {})
        fields = [{**f, "meaning": meaning.get(f["name"], f["meaning"])} for f in base["field"] if f["name"] not in own]
        layout = {**base, **layout, "field": fields + layout["field"]}
    for f in layout["field"]:
        if f["name"] == "magic":
            f["value"] = MAGIC  # the layout says where the marker is, the contract what it is
    return layout


LAYOUTS: dict[int, dict[str, Any]] = {v: _load_layout(v) for v in (1, 2)}
"""Every layout the tool reads and writes, by version (keys as in ``layout_v1.toml``)."""

LAYOUT: dict[str, Any] = LAYOUTS[1]
"""The parsed layout 1 (the fields every layout shares sit at its offsets)."""

FIELDS_BY_VERSION: dict[int, dict[str, dict[str, Any]]] = {
    v: {f["name"]: f for f in lay["field"]} for v, lay in LAYOUTS.items()}
FIELDS: dict[str, dict[str, Any]] = FIELDS_BY_VERSION[1]

LAYOUT_VERSION: int = LAYOUT["layout_version"]
#: the mechanical-order layout of revision 1.2
LAYOUT_VERSION_MECH: int = 2
SUPPORTED_LAYOUTS: tuple[int, ...] = tuple(LAYOUTS)
BANK_WORD_ADDR: tuple[int, int] = tuple(LAYOUT["bank_word_addr"])
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

if any(lay["layout_version"] != v for v, lay in LAYOUTS.items()) or BANK_BYTES != 2 * BANK_WORDS:
    # the layout files are package data: a wrong one is a broken installation, not bad input
    raise ImportError(f"layout files do not match their versions ({[lay['layout_version'] for lay in LAYOUTS.values()]}), "
                      f"or bank {BANK_BYTES} bytes for {BANK_WORDS} words")


def block_bytes(table_len: int, version: int = 1) -> int:
    """Total size of a block with ``table_len`` table entries, CRC included (bytes): 104 + 8*N in
    layout 1, 3248 + 8*N in layout 2."""
    lay = LAYOUTS[version]
    return lay["header_bytes"] + lay["bytes_per_n"] * table_len + lay["trailer_bytes"]


def fields(version: int = 1) -> dict[str, dict[str, Any]]:
    """The fields of layout ``version`` by name, in address order."""
    return FIELDS_BY_VERSION[version]


def field_offset(name: str, table_len: int = 0, version: int = 1) -> int:
    """Byte offset of field ``name`` from the bank start for a block of ``table_len`` entries."""
    f = FIELDS_BY_VERSION[version][name]
    return f["offset"] + f.get("offset_per_n", 0) * table_len


def field_count(name: str, table_len: int = 0, version: int = 1) -> int:
    """Number of elements of field ``name`` (``table_len`` for the tables)."""
    count = FIELDS_BY_VERSION[version][name].get("count", 1)
    return table_len if count == "N" else count


def table_len_ok(n: int) -> bool:
    """True when ``n`` is a power of two within the layout's table length range."""
    return TABLE_LEN_MIN <= n <= TABLE_LEN_MAX and n & (n - 1) == 0


def crc32(data: bytes) -> int:
    """CRC-32/ISO-HDLC (the zlib/PNG CRC) of ``data``; check value of b"123456789" is 0xCBF43926."""
    return zlib.crc32(data) & 0xFFFFFFFF


def put_field(buf: bytearray, name: str, n: int, value: Any, version: int = 1) -> None:
    """Write field ``name`` of a block of ``table_len`` ``n`` into ``buf`` (little-endian)."""
    f = FIELDS_BY_VERSION[version][name]
    off = field_offset(name, n, version)
    if f["type"] == "u8":
        raw = bytes(value)
        buf[off:off + len(raw)] = raw
    elif field_count(name, n, version) == 1 and not isinstance(value, (tuple, list, np.ndarray)):
        struct.pack_into(STRUCT[f["type"]], buf, off, value)
    else:
        dt = {"u16": "<u2", "u32": "<u4", "f32": "<f4"}[f["type"]]
        raw = np.asarray(value, dtype=dt).tobytes()
        buf[off:off + len(raw)] = raw


def get_field(data: bytes, name: str, n: int, version: int = 1) -> Any:
    """Read field ``name`` of a block of ``table_len`` ``n`` from ``data`` (int, bytes or array)."""
    f = FIELDS_BY_VERSION[version][name]
    off = field_offset(name, n, version)
    count = field_count(name, n, version)
    if f["type"] == "u8":
        return bytes(data[off:off + count])
    if f.get("count", 1) == 1:
        return struct.unpack_from(STRUCT[f["type"]], data, off)[0]
    dt = {"u16": "<u2", "u32": "<u4", "f32": "<f4"}[f["type"]]
    return np.frombuffer(bytes(data[off:off + count * SIZE[f["type"]]]), dtype=dt)
