"""Structural check of an MDF4 file before asammdf decodes it (an untrusted capture).

asammdf trusts the file: a block link that points back at its own block makes it loop for
ever, a compressed block that claims 2^62 bytes of original data kills the process, one that
claims 2^31 takes 2 GB and 20 s, a flipped bit in compressed data ends in a decompression
traceback. This module walks the file's block graph itself, in pure Python over the raw bytes,
and refuses it (:class:`~eol_cal.errors.InputError` naming the file, the block and the reason)
unless:

- the file starts with a finalised MDF 4 identification block and the header block at 64;
- every block reached from the header has a known id (``##DG``, ``##CN``, ...), a length that
  holds its links and its fixed fields and ends inside the file, and sits 8-byte aligned;
- every link is 0 or the offset of such a block, of a type allowed at that link; the graph is
  walked with each block visited once and has no cycle (a link back to its own block or to any
  block on the way to it is refused, so asammdf never walks in circles); a block that is not
  text, metadata, a conversion or a source (``##TX``, ``##MD``, ``##CC``, ``##SI``) is linked to
  at most once;
- compressed data blocks (``##DZ``) use deflate (plain or transposed), claim an original
  length of at most :data:`MAX_DZ_RATIO` times their compressed length (deflate cannot do
  better than about 1032:1) and actually inflate to exactly that length (a bit flip is caught
  here by the stream's own checksum, adler-32, naming the block);
- no channel group holds variable-length signal data (flag bit 0; its size fields mean
  something else, and asammdf trusted them into a ``malloc`` abort);
- data lists (``##DL``) hold as many data links as they count; a channel group's records fit
  in its data group's data (the only group of a sorted data group fills it exactly: asammdf
  read 0 claimed records as an endless run of empty ones), and every
  fixed-size channel's bytes fit in its record;
- the bytes the data blocks decode to, summed over the file, stay under
  :data:`MAX_DECODED_BYTES`, the memory bound of a decode.

The walk reads each block's header, links and fixed fields once, and inflates each compressed
block once with an output cap, so its time and memory are linear in the file size (bounded by
:data:`MAX_DECODED_BYTES` for the inflated data).
"""

from __future__ import annotations

import contextlib
import mmap
import os
import struct
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple, cast

from isal import isal_zlib

from eol_cal.errors import InputError

#: what a corrupt compressed block raises (isal's stub declares its error an instance, not a class)
_INFLATE_ERRORS: tuple[type[BaseException], ...] = (cast(type[BaseException], isal_zlib.error), zlib.error)

#: largest original/compressed length ratio a compressed data block may claim; deflate's own
#: limit is about 1032:1 (a 258-byte match per 2 bits), so a larger claim is a lie about the size
MAX_DZ_RATIO = 1100
#: memory bound of a decode: the data blocks of one file may decode to at most this many bytes
#: (an end-of-line capture of 10 channels at 20 kHz for a minute decodes to ~100 MB)
MAX_DECODED_BYTES = 1 << 30
#: most links one block may carry (a data list of this many data blocks is ~16 GB of data)
MAX_LINKS = 1 << 20
#: files up to this size are read whole: one read instead of a mapping, its page faults and the
#: check's many small reads through it (~0.1 ms of a ~1 ms read of a 64 KB capture); a larger
#: file is mapped
READ_WHOLE_BYTES = 16 << 20

_ID_BYTES = 64
_HEADER = struct.Struct("<4sIQQ")

_TEXT = frozenset({"TX", "MD"})
#: data blocks stored as they decode (no compression, no list)
_PLAIN_DATA = frozenset({"DT", "SD", "RD", "DV", "DI", "RV", "RI"})
_DATA = frozenset({"DT", "DZ", "DL", "HL", "SD", "RD", "DV", "DI", "LD", "RV", "RI"})
#: block types that may be linked from more than one place (writers share texts and conversions)
_SHAREABLE = frozenset({"TX", "MD", "CC", "SI"})

#: every MDF 4.2 block type, and the bytes of fixed fields after its links
_FIXED_DATA = {
    "HD": 32, "MD": 0, "TX": 0, "FH": 16, "CH": 8, "AT": 40, "EV": 32, "DG": 8, "CG": 32, "SI": 8, "CN": 72,
    "CC": 24, "CA": 16, "DT": 0, "SR": 24, "RD": 0, "SD": 0, "DL": 8, "DZ": 24, "HL": 8, "LD": 8, "DV": 0,
    "DI": 0, "RV": 0, "RI": 0, "GD": 8,
}
#: allowed target types of the links at each position (None: any block); positions past the
#: list (attachments, element links, conversion references) take any known block
_LINK_TARGETS: dict[str, Sequence[frozenset[str] | None]] = {
    "HD": (frozenset({"DG"}), frozenset({"FH"}), frozenset({"CH"}), frozenset({"AT"}), frozenset({"EV"}), _TEXT),
    "FH": (frozenset({"FH"}), _TEXT),
    "CH": (frozenset({"CH"}), frozenset({"CH"}), _TEXT, _TEXT),
    "AT": (frozenset({"AT"}), _TEXT, _TEXT, _TEXT),
    "EV": (frozenset({"EV"}), frozenset({"EV"}), frozenset({"EV"}), _TEXT, _TEXT),
    "DG": (frozenset({"DG"}), frozenset({"CG"}), _DATA, _TEXT),
    "CG": (frozenset({"CG"}), frozenset({"CN"}), _TEXT, frozenset({"SI"}), frozenset({"SR"}), _TEXT,
           frozenset({"CG"})),
    "SI": (_TEXT, _TEXT, _TEXT),
    "CN": (frozenset({"CN"}), frozenset({"CN", "CA"}), _TEXT, frozenset({"SI"}), frozenset({"CC"}), None, _TEXT,
           _TEXT),
    "CC": (_TEXT, _TEXT, _TEXT, frozenset({"CC"})),
    "SR": (frozenset({"SR"}), _DATA),
    "DL": (frozenset({"DL"}),),
    "HL": (frozenset({"DL"}),),
    "LD": (frozenset({"LD"}),),
}
#: links each block type must carry (lo, hi): readers parse the standard links by position
_LINK_COUNT = {
    "HD": (6, 6), "FH": (2, 2), "CH": (4, MAX_LINKS), "AT": (4, 4), "EV": (5, MAX_LINKS), "DG": (4, 4),
    "CG": (6, 7), "SI": (3, 3), "CN": (8, MAX_LINKS), "CC": (4, MAX_LINKS), "CA": (1, MAX_LINKS), "SR": (2, 2),
    "DL": (1, MAX_LINKS), "HL": (1, 1), "LD": (1, MAX_LINKS), "GD": (1, 1),
    "MD": (0, 0), "TX": (0, 0), "DT": (0, 0), "RD": (0, 0), "SD": (0, 0), "DZ": (0, 0), "DV": (0, 0), "DI": (0, 0),
    "RV": (0, 0), "RI": (0, 0),
}
#: data-type codes of fixed-size numbers in a record (unsigned/signed integers, floats, LE/BE)
_NUMERIC_TYPES = range(6)
_MAX_DATA_TYPE = 16


class Block(NamedTuple):
    """One block of the file as the check read it (a named tuple: the walk makes one a block,
    at a third of a frozen dataclass's cost)."""

    offset: int
    kind: str
    length: int
    links: tuple[int, ...]

    @property
    def data_at(self) -> int:
        """Offset of the block's fields after its links."""
        return self.offset + 24 + 8 * len(self.links)

    def where(self) -> str:
        return _block_where(self.kind, self.offset)


def _block_where(kind: str, offset: int) -> str:
    """A block's place in a refusal (``block ##DZ at 0x320``), also for one not read into a :class:`Block`."""
    return f"block ##{kind} at 0x{offset:x}"


@dataclass(frozen=True)
class Mdf4Layout:
    """What the check found: the blocks by offset, the bytes their data decodes to, and each
    compressed data block's inflated data by the block's offset (the check inflates it anyway:
    a decoder takes it from here instead of inflating it again)."""

    blocks: dict[int, Block]
    decoded_bytes: int
    inflated: dict[int, bytes] = field(default_factory=dict)
    #: the header block's comment as stored (XML of a ##MD block, or a ##TX text), "" when none:
    #: read here because asammdf rebuilds it from a dict, which hides a key given twice
    header_comment: str = ""


class _Refusal(Exception):
    def __init__(self, where: str, reason: str) -> None:
        self.where, self.reason = where, reason


def check_mdf4_file(path: str | Path) -> Mdf4Layout:
    """Check the structure of the MDF4 file at ``path`` (see the module docstring).

    Raises
    ------
    InputError
        Naming the file, the block (``block ##DZ at 0x320``) and the reason.
    """
    with checked_mdf4(path) as (_, layout):
        return layout


@contextlib.contextmanager
def checked_mdf4(path: str | Path) -> Iterator[tuple[bytes | mmap.mmap, Mdf4Layout]]:
    """:func:`check_mdf4_file`, and the file's bytes with its layout for a decoder while the
    context lasts: read whole up to :data:`READ_WHOLE_BYTES`, else mapped read-only (a larger
    file is checked without being read whole)."""
    file = str(path)
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if size < _ID_BYTES + _HEADER.size:
            raise InputError(file, None, f"{size} bytes: too short for an MDF file (identification and header block)")
        if size <= READ_WHOLE_BYTES:
            data = fh.read()
            yield data, check_mdf4_bytes(data, file)
            return
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
            yield mapped, check_mdf4_bytes(mapped, file)


def check_mdf4_bytes(data: bytes | mmap.mmap, file: str = "<bytes>") -> Mdf4Layout:
    """Check an MDF4 image in memory; :class:`InputError` as :func:`check_mdf4_file`."""
    try:
        return _check(data)
    except _Refusal as exc:
        raise InputError(file, exc.where, exc.reason) from None


def _check(data: bytes | mmap.mmap) -> Mdf4Layout:
    _check_identification(data)
    blocks = _walk(data)
    decoded = 0
    inflated: dict[int, bytes] = {}
    for block in blocks.values():
        decoded += _check_fields(data, block, blocks, inflated)
        if decoded > MAX_DECODED_BYTES:
            raise _Refusal("data", f"the data blocks decode to more than {MAX_DECODED_BYTES} bytes, the memory bound "
                                   "of a capture")
    for block in blocks.values():
        if block.kind == "DG":
            _check_records(data, block, blocks)
    return Mdf4Layout(blocks, decoded, inflated, _text(data, blocks, blocks[_ID_BYTES].links[5]))


def _text(data: bytes | mmap.mmap, blocks: dict[int, Block], link: int) -> str:
    """The text of a ##TX/##MD block (UTF-8, up to its first NUL); "" for link 0."""
    if not link:
        return ""
    block = blocks[link]
    raw = bytes(data[block.data_at:block.offset + block.length]).split(b"\0", 1)[0]
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise _Refusal(block.where(), f"text is not UTF-8 (byte 0x{raw[exc.start]:02x} at {exc.start})") from None


def _check_identification(data: bytes | mmap.mmap) -> None:
    ident = bytes(data[:8])
    if ident == b"UnFinMF ":
        raise _Refusal("identification block", "an unfinalised MDF file (the writer did not finish it)")
    if ident != b"MDF     ":
        raise _Refusal("identification block", f"not a readable MDF file (starts with {ident!r}, not b'MDF     ')")
    version = bytes(data[8:16]).decode("ascii", "replace").strip()
    if not version.startswith("4."):
        raise _Refusal("identification block", f"MDF version {version}; capture format v1 takes MDF 4")


#: each known block id as stored (``b"##DG"``): its type, bytes of fixed fields and fewest and most
#: links, found with one look-up of the raw id (the walk reads every block's header through it)
_SPECS: dict[bytes, tuple[str, int, int, int]] = {
    f"##{kind}".encode("ascii"): (kind, fixed, *_LINK_COUNT[kind]) for kind, fixed in _FIXED_DATA.items()
}


def _link_where(parent: Block | None, k: int) -> str:
    """Where a link is, for a refusal: link ``k`` of ``parent``, or the header's own place."""
    return "header block" if parent is None else f"{parent.where()}, link {k}"


def _read_block(data: bytes | mmap.mmap, offset: int, parent: Block | None, k: int = 0) -> Block:
    """The block at ``offset``, reached by link ``k`` of ``parent`` (``None``: the header block);
    the refusal's place is put in words only when one is raised (the walk reads every block)."""
    size = len(data)
    if offset % 8 or offset < _ID_BYTES or offset + _HEADER.size > size:
        raise _Refusal(_link_where(parent, k),
                       f"links to 0x{offset:x}, not a block inside the file ({size} bytes, blocks 8-byte aligned)")
    raw_id, _, length, count = _HEADER.unpack_from(data, offset)
    spec = _SPECS.get(raw_id)
    if spec is None:
        if raw_id[:2] != b"##":
            raise _Refusal(_link_where(parent, k), f"links to 0x{offset:x}, where no block starts (bytes {raw_id!r})")
        raise _Refusal(_block_where(raw_id[2:].decode("ascii", "replace"), offset), "unknown block type")
    kind, fixed, lo, hi = spec
    if not lo <= count <= hi:
        raise _Refusal(_block_where(kind, offset),
                       f"{count} links; a ##{kind} block has {lo}" + (f"..{hi}" if hi != lo else ""))
    need = _HEADER.size + 8 * count + fixed
    if length < need:
        raise _Refusal(_block_where(kind, offset),
                       f"length {length} bytes cannot hold its {count} links and fixed fields ({need} bytes)")
    if offset + length > size:
        raise _Refusal(_block_where(kind, offset),
                       f"length {length} bytes runs past the end of the file ({size} bytes)")
    links = struct.unpack_from(f"<{count}Q", data, offset + _HEADER.size) if count else ()
    return Block(offset, kind, length, links)


def _walk(data: bytes | mmap.mmap) -> dict[int, Block]:
    """Every block reachable from the header, each read once; refuses cycles and shared blocks."""
    header = _read_block(data, _ID_BYTES, None)
    if header.kind != "HD":
        raise _Refusal("header block", f"##{header.kind} at 0x40 where ##HD must be")
    blocks: dict[int, Block] = {_ID_BYTES: header}
    linked_from: dict[int, Block] = {}
    # iterative depth-first walk: a link to a block still on the path is a cycle. A stack entry is
    # a block and its next link; one block's links are taken in a loop until one leads to a block
    # not seen yet (the block is put back to resume there, under the child)
    on_path: set[int] = {_ID_BYTES}
    stack: list[tuple[Block, int]] = [(header, 0)]
    while stack:
        block, k = stack.pop()
        links = block.links
        allowed = _LINK_TARGETS.get(block.kind, ())
        while k < len(links):
            target = links[k]
            k += 1
            if not target:
                continue
            if target in on_path:
                what = "its own block" if target == block.offset else f"block 0x{target:x} that leads to it"
                raise _Refusal(_link_where(block, k - 1), f"links back to {what} (a cycle)")
            child = blocks.get(target)
            if child is None:
                child = blocks[target] = _read_block(data, target, block, k - 1)
            kinds = allowed[k - 1] if k - 1 < len(allowed) else None
            if kinds is not None and child.kind not in kinds:
                raise _Refusal(_link_where(block, k - 1), f"links to a ##{child.kind} block where "
                                                          f"{'/'.join(sorted('##' + x for x in kinds))} must be")
            if target in linked_from:
                if child.kind not in _SHAREABLE:
                    raise _Refusal(_link_where(block, k - 1),
                                   f"links to {child.where()}, already linked from {linked_from[target].where()}")
                continue  # shared text or conversion: read and checked once
            linked_from[target] = block
            on_path.add(target)
            stack.append((block, k))
            stack.append((child, 0))
            break
        else:
            on_path.discard(block.offset)
    return blocks


def _u8(data: bytes | mmap.mmap, at: int) -> int:
    return data[at]


def _check_fields(data: bytes | mmap.mmap, block: Block, blocks: dict[int, Block], inflated: dict[int, bytes]) -> int:
    """The fixed fields of one block; returns the bytes its data decodes to (data blocks); a
    compressed block's inflated data goes into ``inflated``."""
    at = block.data_at
    if block.kind in _PLAIN_DATA:
        return block.length - _HEADER.size - 8 * len(block.links)
    if block.kind == "DZ":
        inflated[block.offset] = _check_dz(data, block)
        return len(inflated[block.offset])
    if block.kind == "DL":
        flags = _u8(data, at)
        count = struct.unpack_from("<I", data, at + 4)[0]
        if count != len(block.links) - 1:
            raise _Refusal(block.where(), f"counts {count} data blocks but links {len(block.links) - 1}")
        if not flags & 1:  # offsets of each data block follow
            need = _HEADER.size + 8 * len(block.links) + 8 + 8 * count
            if block.length < need:
                raise _Refusal(block.where(), f"length {block.length} cannot hold {count} offsets")
        for k, link in enumerate(block.links[1:], start=1):
            if link and blocks[link].kind not in _DATA:
                raise _Refusal(f"{block.where()}, link {k}", f"links to a ##{blocks[link].kind} block, not data")
        return 0
    if block.kind == "CN":
        data_type = _u8(data, at + 2)
        if data_type > _MAX_DATA_TYPE:
            raise _Refusal(block.where(), f"data type {data_type} is not an MDF 4 data type")
    return 0


def _check_dz(data: bytes | mmap.mmap, block: Block) -> bytes:
    at = block.data_at
    original_type = bytes(data[at:at + 2]).decode("ascii", "replace")
    zip_type = _u8(data, at + 2)
    param, original, compressed = struct.unpack_from("<IQQ", data, at + 4)
    where = block.where()
    room = block.length - (at + 24 - block.offset)
    if original_type not in ("DT", "SD", "RD", "DV", "DI", "RV", "RI"):
        raise _Refusal(where, f"original block type {original_type!r} cannot be compressed")
    if zip_type not in (0, 1):
        raise _Refusal(where, f"compression {zip_type} (eol-cal reads deflate (0) and transposed deflate (1))")
    if zip_type == 1 and param < 1:
        raise _Refusal(where, "transposed deflate with 0 columns")
    if not 0 < compressed <= room:
        raise _Refusal(where, f"compressed length {compressed} bytes does not fit the block ({room} bytes of data)")
    if original > MAX_DZ_RATIO * compressed:
        raise _Refusal(where, f"original length {original} bytes is more than {MAX_DZ_RATIO} times the compressed "
                              f"{compressed} bytes (deflate cannot compress that much)")
    if original > MAX_DECODED_BYTES:
        raise _Refusal(where, f"original length {original} bytes is over the memory bound of a capture "
                              f"({MAX_DECODED_BYTES} bytes)")
    # ISA-L's inflate (isal, asammdf's own dependency): zlib's stream format and checks (the
    # adler-32 trailer included), the same bytes out, in under half zlib's time (the largest part
    # of reading a capture)
    inflater = isal_zlib.decompressobj()
    try:
        # one byte more than claimed, to notice data that inflates longer than it says
        out = inflater.decompress(bytes(data[at + 24:at + 24 + compressed]), original + 1)
    except _INFLATE_ERRORS as exc:
        raise _Refusal(where, f"compressed data is corrupt ({exc})") from None
    if len(out) != original or not inflater.eof:
        raise _Refusal(where, f"compressed data inflates to {len(out)}{'+' if not inflater.eof else ''} bytes, "
                              f"not the {original} it claims")
    return out


def _data_bytes(blocks: dict[int, Block], data: bytes | mmap.mmap, link: int) -> int:
    """Bytes the data behind ``link`` (a data block, a list of them, a header list) decodes to."""
    total = 0
    todo = [link]
    while todo:
        offset = todo.pop()
        if not offset:
            continue
        block = blocks[offset]
        if block.kind == "DZ":
            total += struct.unpack_from("<Q", data, block.data_at + 8)[0]
        elif block.kind in ("DL", "HL", "LD"):
            todo.extend(block.links)
        elif block.kind in _DATA:
            total += block.length - _HEADER.size - 8 * len(block.links)
    return total


def _check_records(data: bytes | mmap.mmap, dg: Block, blocks: dict[int, Block]) -> None:
    """A data group's channel groups: their records fit the data; each channel fits its record."""
    record_id = _u8(data, dg.data_at)
    if record_id not in (0, 1, 2, 4, 8):
        raise _Refusal(dg.where(), f"record id size {record_id} is not 0, 1, 2, 4 or 8 bytes")
    available = _data_bytes(blocks, data, dg.links[2])
    needed = 0
    cg_at = dg.links[1]
    while cg_at:
        cg = blocks[cg_at]
        cycles, flags = struct.unpack_from("<QH", data, cg.data_at + 8)
        record, invalid = struct.unpack_from("<II", data, cg.data_at + 24)
        if flags & 1:
            # a VLSD group's size fields mean something else (asammdf trusted them into a malloc
            # abort and MemoryErrors); capture channels are fixed-size numbers
            raise _Refusal(cg.where(), "a variable-length signal data group (flag bit 0): capture channels are "
                                       "fixed-size numbers")
        sorted_alone = record_id == 0 and cg_at == dg.links[1] and not cg.links[0]
        if sorted_alone and cycles * (record + invalid) != available:
            # the only group of a sorted data group owns all its data; claimed 0 records made
            # asammdf split the data into empty records without end (memory without bound)
            raise _Refusal(cg.where(), f"claims {cycles} records of {record + invalid} bytes, but its data group "
                                       f"holds {available} bytes of them")
        needed += cycles * (record_id + record + invalid)
        _check_channels(data, cg, blocks, record)
        cg_at = cg.links[0]
    if needed > available:
        raise _Refusal(dg.where(), f"its channel groups declare {needed} bytes of records, its data holds {available}")


def _check_channels(data: bytes | mmap.mmap, cg: Block, blocks: dict[int, Block], record: int) -> None:
    cn_at = cg.links[1]
    while cn_at:
        cn = blocks[cn_at]
        channel_type, _, data_type, bit_offset, byte_offset, bit_count = struct.unpack_from("<BBBBII", data, cn.data_at)
        if channel_type in (3, 6):  # virtual channels take no record bytes
            cn_at = cn.links[0]
            continue
        if data_type in _NUMERIC_TYPES and not 1 <= bit_count <= 64:
            raise _Refusal(cn.where(), f"a number of {bit_count} bits (1..64)")
        end = byte_offset + (bit_offset + bit_count + 7) // 8
        if end > record:
            raise _Refusal(cn.where(), f"its bytes {byte_offset}..{end} lie outside the {record}-byte record")
        cn_at = cn.links[0]
