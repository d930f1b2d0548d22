"""Decode an MDF4 capture straight from its checked bytes into numpy columns, without asammdf,
for the plain layout capture files have (eol-cal's own, and most loggers').

:func:`eol_cal.capture.mdf4_check.check_mdf4_bytes` has walked every block, checked every size
and inflated every compressed data block already; what remains for a plain file is to cut the
records into channels. asammdf builds its whole object model for that and, channel by channel,
inflates the data again: ~3 ms of a ~4 ms read of a 7000-sample capture (docs/benchmarks.md,
"Lot refit throughput").

:func:`decode_checked` takes a file only when every part of it is plain, and otherwise returns
``None`` so that the caller decodes it with asammdf as before:

- the header comment is an ``##MD`` block whose XML (no namespaces) holds only ``<e name=...>``
  properties, each once, with texts that asammdf's re-serialisation of the comment keeps as they
  are (no line breaks or tabs, no whitespace at either end);
- every data group has no record ids and one channel group of fixed-length records (no
  variable-length data, no invalidation bytes), its data one ``##DT``, one ``##DZ`` of a
  ``##DT`` (deflate or transposed deflate), or a ``##DL`` list of those, exactly
  ``cycles * record`` bytes long;
- every channel is a fixed-length value or the time master (one per group), a little-endian
  unsigned or signed integer of 8/16/32/64 bits or a float of 32/64 bits at a whole byte, with no
  conversion, no composition, no own data and no invalidation, its name and unit in ``##TX``
  blocks of UTF-8 text.

The columns are then those asammdf gives (names, units, samples, time stamps), which
``tests/test_capture_decode.py`` checks file by file, hostile mutations included.
"""

from __future__ import annotations

import mmap
import struct
import xml.etree.ElementTree as ET
from collections.abc import Callable, Sequence

import numpy as np

from eol_cal.capture.mdf4_check import Block, Mdf4Layout

#: a channel group as the decoders hand it over: (channel name, loader of (samples, unit or None,
#: time stamps (s))) per channel in the group's order, the master left out
Group = list[tuple[str, Callable[[], tuple[np.ndarray, str | None, np.ndarray]]]]

#: the checked file's bytes (a read-only map of the file, or bytes)
Data = bytes | mmap.mmap

_CN = struct.Struct("<BBBBIIII")
_CG = struct.Struct("<QQHHxxxxII")
_DZ = struct.Struct("<2sBxIQQ")
#: channel flags that say nothing about the samples (precision, ranges, limits, discrete,
#: calibration, monotonous): anything else (invalidation, bus events, ...) is left to asammdf
_PLAIN_CN_FLAGS = 0b1000_1111_1100
_INT = {0: "<u", 2: "<i"}


class _NotPlain(Exception):
    """Something of the file is outside what this decoder takes: asammdf decodes it."""


def decode_checked(data: Data, layout: Mdf4Layout, header: ET.Element | None) -> list[Group] | None:
    """The channel groups of a checked MDF4 file, or ``None`` when it is not plain (see the module
    docstring: the caller decodes it with asammdf). ``header``: the file's header comment as
    parsed (:func:`eol_cal.capture.mdf4_io.header_xml`; ``None`` when it is not XML)."""
    try:
        _check_header(data, layout, header)
        return [_group(data, layout, dg) for dg in _chain(layout, layout.blocks[64].links[0], 0)]
    except (_NotPlain, KeyError, IndexError, ValueError, struct.error):
        # a checked file holds together; whatever else is odd about it, asammdf decodes as before
        return None


def _chain(layout: Mdf4Layout, first: int, link: int) -> list[Block]:
    """The blocks of a linked list from ``first``, following link number ``link``."""
    out = []
    while first:
        block = layout.blocks[first]
        out.append(block)
        first = block.links[link]
    return out


def _text(data: Data, layout: Mdf4Layout, offset: int, kinds: tuple[str, ...] = ("TX",)) -> str:
    """A text block as asammdf reads it (up to the first NUL, blanks stripped), strict UTF-8."""
    if not offset:
        return ""
    block = layout.blocks[offset]
    if block.kind not in kinds:
        raise _NotPlain
    raw = data[block.offset + 24:block.offset + block.length].split(b"\0", 1)[0].strip(b" \r\t\n")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise _NotPlain from None


def _check_header(data: Data, layout: Mdf4Layout, root: ET.Element | None) -> None:
    """The header comment is an ``##MD`` block of plain properties (the module docstring);
    ``root`` its XML as parsed for the properties (the stored text; this text without blanks at
    either end is the same document where that one parses)."""
    offset = layout.blocks[64].links[5]
    if not offset or layout.blocks[offset].kind != "MD":
        raise _NotPlain
    if root is None:
        # not XML to the properties' reader (no "<" first: a byte order mark before it, say):
        # the text judged on its own, as expat reads it
        try:
            root = ET.fromstring(_text(data, layout, offset, ("MD",)))
        except ET.ParseError:
            raise _NotPlain from None
    if root.tag != "HDcomment" or any("}" in str(e.tag) for e in root.iter()):
        raise _NotPlain
    names = set()
    for common in root.findall("common_properties"):
        for element in common:
            name = element.get("name")
            value = element.text or ""
            if element.tag != "e" or not name or name in names or len(element) or value != value.strip() \
                    or any(c in value for c in "\r\n\t"):
                raise _NotPlain
            names.add(name)


def _records(data: Data, layout: Mdf4Layout, link: int) -> bytes:
    """The bytes of a data group's data blocks, concatenated."""
    if not link:
        raise _NotPlain
    block = layout.blocks[link]
    if block.kind == "DT":
        return data[block.offset + 24:block.offset + block.length]
    if block.kind == "DZ":
        original, zip_type, param, _, _ = _DZ.unpack_from(data, block.data_at)
        if original != b"DT":
            raise _NotPlain
        raw = layout.inflated[block.offset]
        if zip_type == 0:
            return raw
        lines = len(raw) // param
        body = np.frombuffer(raw, np.uint8, lines * param).reshape(param, lines).T.tobytes()
        return body + raw[lines * param:]
    if block.kind == "DL":
        return b"".join(_records(data, layout, k) for dl in _chain(layout, link, 0) for k in dl.links[1:])
    raise _NotPlain


def _group(data: Data, layout: Mdf4Layout, dg: Block) -> Group:
    if data[dg.data_at] != 0:  # record ids
        raise _NotPlain
    groups: Sequence[Block | None] = _chain(layout, dg.links[1], 0) or [None]
    (cg,) = groups
    if cg is None or cg.links[0]:
        raise _NotPlain
    _, cycles, flags, _, record, invalid = _CG.unpack_from(data, cg.data_at)
    if flags or invalid or not cycles or not record:
        raise _NotPlain
    fields: list[tuple[str, str, str | None, int, int]] = []  # (name, dtype, unit, offset, kind)
    master = None
    for cn in _chain(layout, cg.links[1], 0):
        kind, sync, dtype_code, bit_offset, byte_offset, bits, cn_flags, _ = _CN.unpack_from(data, cn.data_at)
        if any(cn.links[k] for k in (1, 4, 5)) or kind not in (0, 2) or bit_offset or cn_flags & ~_PLAIN_CN_FLAGS:
            raise _NotPlain
        if dtype_code in _INT and bits in (8, 16, 32, 64):
            fmt = f"{_INT[dtype_code]}{bits // 8}"
        elif dtype_code == 4 and bits in (32, 64):
            fmt = f"<f{bits // 8}"
        else:
            raise _NotPlain
        name = _text(data, layout, cn.links[2])
        if not name:  # asammdf refuses a signal without a name
            raise _NotPlain
        unit = _text(data, layout, cn.links[6]) or None
        if kind == 2:
            if master is not None or sync != 1:
                raise _NotPlain
            master = len(fields)
        fields.append((name, fmt, unit, byte_offset, kind))
    payload = _records(data, layout, dg.links[2])
    if master is None or len(payload) != cycles * record:
        raise _NotPlain
    rows = np.frombuffer(payload, np.dtype({"names": [f"c{k}" for k in range(len(fields))],
                                            "formats": [f[1] for f in fields],
                                            "offsets": [f[3] for f in fields], "itemsize": record}))
    times = rows[f"c{master}"].astype(np.float64)

    def loader(k: int, unit: str | None) -> Callable[[], tuple[np.ndarray, str | None, np.ndarray]]:
        return lambda: (rows[f"c{k}"].copy(), unit, times)

    return [(name, loader(k, unit)) for k, (name, _, unit, _, kind) in enumerate(fields) if kind != 2]
