"""The F28335 calibration parameter block (``docs/firmware-contract.md`` section 2): pack, unpack, check.

The byte layout is read from ``layout_v1.toml`` next to this module, the one place it is
defined; the C header ``firmware_params/eol_param_block.h`` is generated from the same file
(:mod:`eol_cal.firmware.gen_header`).

Invariant: :func:`pack` only ever returns a block that :func:`check` calls valid; blocks with
invalid headers exist only as bytes (tests and golden vectors patch them on purpose).
"""

from __future__ import annotations

import io
import math
import operator
import os
import struct
import tomllib
import zlib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from eol_cal.errors import InputError
# the contract's constants, also read through this module (block.FLAG_COMP_ENABLE, block.STATUS_VALID)
from eol_cal.firmware.contract import (  # noqa: F401
    FLAG_COMP_ENABLE,
    FLAG_INTERP_ENABLE,
    FLAGS,
    FLAGS_KNOWN,
    MAGIC,
    STATUS_CRC_MISMATCH,
    STATUS_HEADER_INVALID,
    STATUS_VALID,
)


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
BANK_WORDS: int = LAYOUT["bank_words"]
BANK_BYTES: int = LAYOUT["bank_bytes"]
HEADER_BYTES: int = LAYOUT["header_bytes"]
TABLE_LEN_MIN: int = LAYOUT["table_len_min"]
TABLE_LEN_MAX: int = LAYOUT["table_len_max"]
def flag_names(flags: int) -> str:
    """The block's flags by name, ``COMP_ENABLE|INTERP_ENABLE`` (``none`` when no bit is set)."""
    names = [name for name, f in FLAGS.items() if flags & (1 << f.bit)]
    return "|".join(names) or "none"


SEQUENCE_INVALID = (0, 0xFFFFFFFF)

_STRUCT = {"u16": "<H", "u32": "<I", "f32": "<f"}
_SIZE = {"u8": 1, "u16": 2, "u32": 4, "f32": 4}

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


def _f32(x: Any, name: str) -> float:
    try:
        with np.errstate(over="ignore"):
            return float(np.float32(float(x)))
    except (TypeError, ValueError) as exc:
        raise InputError(None, name, f"not a number: {x!r}") from exc


def _int(x: Any, name: str) -> int:
    try:
        return operator.index(x)
    except TypeError as exc:
        raise InputError(None, name, f"not an integer: {x!r}") from exc


_INT_FIELDS = ("sequence", "flags", "calibrated_at", "poles", "encoder_ppr", "layout_version")
_F32_FIELDS = ("tick_hz", "kt", "c6", "phase_c6", "k6", "phase_k6", "lead_s", "iqc_limit")


@dataclass(frozen=True, eq=False)
class ParamBlock:
    """The decoded content of a parameter block (every field of the contract's table).

    Floats are held rounded to binary32, exactly as stored, so ``unpack(pack(b)) == b``.
    ``magic``, ``block_bytes``, ``table_len``, ``reserved`` and ``crc32`` are derived by
    :func:`pack` and are not attributes.

    Attributes
    ----------
    sequence : int
        Write counter, 1 .. 0xFFFFFFFE.
    flags : int
        ``FLAG_COMP_ENABLE | FLAG_INTERP_ENABLE`` bits.
    serial : str
        Motor serial, ASCII, at most 16 characters.
    calibrated_at : int
        Unix time of the calibration (s, UTC).
    poles : int
        Number of poles P.
    encoder_ppr : int
        Rising edges of encoder channel A per mechanical revolution (N_enc).
    tick_hz : float
        Estimator tick rate = PWM frequency (Hz).
    kt : float
        Torque constant 3P/4 * psi_f (N*m/A).
    hall_angle : tuple of 6 float
        Electrical angle (rad) at which hall state s begins in forward rotation, index s-1.
    c6, phase_c6 : float
        Load-independent 6th-harmonic ripple amplitude (N*m) and phase (rad).
    k6, phase_k6 : float
        Load-proportional 6th-harmonic ripple coefficient (N*m/A) and phase (rad).
    lead_s : float
        Look-up lead time (s): the table is read at theta_hat + omega_hat*lead_s.
    iqc_limit : float
        Clamp of abs(i_qc) (A).
    table_const : ndarray of float32, shape (N,)
        Load-independent part of i_qc at table angle j (A).
    table_per_amp : ndarray of float32, shape (N,)
        Part of i_qc per ampere of i_qo at table angle j (A/A).
    layout_version : int
        Layout version (1).
    """

    sequence: int
    flags: int
    serial: str
    calibrated_at: int
    poles: int
    encoder_ppr: int
    tick_hz: float
    kt: float
    hall_angle: tuple[float, ...]
    c6: float
    phase_c6: float
    k6: float
    phase_k6: float
    lead_s: float
    iqc_limit: float
    table_const: np.ndarray = field(repr=False)
    table_per_amp: np.ndarray = field(repr=False)
    layout_version: int = LAYOUT_VERSION

    def __post_init__(self) -> None:
        put = object.__setattr__
        for name in _INT_FIELDS:
            put(self, name, _int(getattr(self, name), name))
        for name in _F32_FIELDS:
            put(self, name, _f32(getattr(self, name), name))
        if not isinstance(self.serial, str):
            raise InputError(None, "serial", f"not a string: {self.serial!r}")
        hall = tuple(_f32(a, "hall_angle") for a in self.hall_angle)
        if len(hall) != field_count("hall_angle"):
            raise InputError(None, "hall_angle", f"needs 6 angles, got {len(hall)}")
        put(self, "hall_angle", hall)
        tables = []
        for name in ("table_const", "table_per_amp"):
            with np.errstate(over="ignore"):
                arr = np.array(getattr(self, name), dtype=np.float32, copy=True)
            if arr.ndim != 1:
                raise InputError(None, name, f"must be 1-D, got shape {arr.shape}")
            arr.setflags(write=False)
            put(self, name, arr)
            tables.append(arr)
        if tables[0].shape != tables[1].shape:
            raise InputError(None, "table_per_amp",
                             f"length {tables[1].size} differs from table_const's {tables[0].size}")

    @property
    def table_len(self) -> int:
        """N, the number of table entries."""
        return int(self.table_const.size)

    @property
    def block_bytes(self) -> int:
        """Size of the packed block, CRC included (bytes)."""
        return block_bytes(self.table_len)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ParamBlock):
            return NotImplemented
        scalars = [n for n in self.__dataclass_fields__ if n not in ("table_const", "table_per_amp")]
        # Compare floats by bit pattern so that NaN == NaN and -0.0 != 0.0, like the bytes do.
        return (all(_bits(getattr(self, n)) == _bits(getattr(other, n)) for n in scalars)
                and self.table_const.tobytes() == other.table_const.tobytes()
                and self.table_per_amp.tobytes() == other.table_per_amp.tobytes())

    __hash__ = None  # type: ignore[assignment]

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dict of every stored field, derived ones included (tables as lists).

        Non-finite floats (only in blocks that :func:`pack` would refuse) appear as strings.
        """
        d: dict[str, Any] = {"magic": MAGIC}
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            if isinstance(v, np.ndarray):
                v = [_json_float(float(x)) for x in v]
            elif isinstance(v, tuple):
                v = [_json_float(x) for x in v]
            elif isinstance(v, float):
                v = _json_float(v)
            d[name] = v
        d["table_len"] = self.table_len
        d["block_bytes"] = self.block_bytes
        return d


def _json_float(x: float) -> float | str:
    # JSON has no NaN/inf; a corrupted block can hold them, so they become "nan", "inf", "-inf"
    return x if math.isfinite(x) else str(x)


def _bits(v: Any) -> Any:
    if isinstance(v, float):
        return struct.pack("<f", v)
    if isinstance(v, tuple):
        return tuple(_bits(x) for x in v)
    return v


def pack_problems(block: ParamBlock) -> list[tuple[str, str]]:
    """Why ``block`` cannot be packed into a valid block: a list of (field, reason), empty if it can."""
    problems: list[tuple[str, str]] = []
    if block.layout_version not in SUPPORTED_LAYOUTS:
        problems.append(("layout_version", f"{block.layout_version} not supported {SUPPORTED_LAYOUTS}"))
    if not 0 < block.sequence < 0xFFFFFFFF:
        problems.append(("sequence", f"{block.sequence} outside 1..0xFFFFFFFE"))
    if block.flags & ~FLAGS_KNOWN or block.flags < 0:
        problems.append(("flags", f"0x{block.flags:x} has bits other than COMP_ENABLE|INTERP_ENABLE"))
    try:
        raw = block.serial.encode("ascii")
        if len(raw) > field_count("serial"):
            problems.append(("serial", f"{len(raw)} characters, at most {field_count('serial')}"))
        if b"\0" in raw:
            problems.append(("serial", "contains NUL"))
    except UnicodeEncodeError:
        problems.append(("serial", f"not ASCII: {block.serial!r}"))
    if not 0 <= block.calibrated_at <= 0xFFFFFFFF:
        problems.append(("calibrated_at", f"{block.calibrated_at} outside u32"))
    if not (2 <= block.poles <= 0xFFFF and block.poles % 2 == 0):
        problems.append(("poles", f"{block.poles}: needs an even number from 2"))
    if not 1 <= block.encoder_ppr <= 0xFFFF:
        problems.append(("encoder_ppr", f"{block.encoder_ppr} outside 1..65535"))
    for name in _F32_FIELDS:
        if not math.isfinite(getattr(block, name)):
            problems.append((name, f"not finite in binary32: {getattr(block, name)}"))
    if not math.isfinite(block.tick_hz) or block.tick_hz <= 0:
        problems.append(("tick_hz", f"{block.tick_hz} Hz: must be > 0"))
    if not math.isfinite(block.iqc_limit) or block.iqc_limit < 0:
        problems.append(("iqc_limit", f"{block.iqc_limit} A: must be >= 0"))
    if not all(math.isfinite(a) for a in block.hall_angle):
        problems.append(("hall_angle", "not finite"))
    if not table_len_ok(block.table_len):
        problems.append(("table_len", f"{block.table_len}: needs a power of two in "
                                      f"{TABLE_LEN_MIN}..{TABLE_LEN_MAX}"))
    for name in ("table_const", "table_per_amp"):
        if not np.all(np.isfinite(getattr(block, name))):
            problems.append((name, "not finite in binary32"))
    return problems


def _put(buf: bytearray, name: str, n: int, value: Any) -> None:
    f = FIELDS[name]
    off = field_offset(name, n)
    if f["type"] == "u8":
        raw = bytes(value)
        buf[off:off + len(raw)] = raw
    elif field_count(name, n) == 1 and not isinstance(value, (tuple, list, np.ndarray)):
        struct.pack_into(_STRUCT[f["type"]], buf, off, value)
    else:
        dt = {"u16": "<u2", "u32": "<u4", "f32": "<f4"}[f["type"]]
        raw = np.asarray(value, dtype=dt).tobytes()
        buf[off:off + len(raw)] = raw


def _get(data: bytes, name: str, n: int) -> Any:
    f = FIELDS[name]
    off = field_offset(name, n)
    count = field_count(name, n)
    if f["type"] == "u8":
        return bytes(data[off:off + count])
    if FIELDS[name].get("count", 1) == 1:
        return struct.unpack_from(_STRUCT[f["type"]], data, off)[0]
    dt = {"u16": "<u2", "u32": "<u4", "f32": "<f4"}[f["type"]]
    return np.frombuffer(bytes(data[off:off + count * _SIZE[f["type"]]]), dtype=dt)


def pack(block: ParamBlock) -> bytes:
    """Byte image of ``block``: fills magic, block_bytes, table_len, reserved and the CRC.

    Raises
    ------
    InputError
        When a field cannot be stored in a valid block (see :func:`pack_problems`).
    """
    problems = pack_problems(block)
    if problems:
        raise InputError(None, problems[0][0], "; ".join(f"{f}: {r}" for f, r in problems))
    n = block.table_len
    size = block_bytes(n)
    buf = bytearray(size)
    derived = {"block_bytes": size, "table_len": n}
    for f in LAYOUT["field"]:
        name = f["name"]
        if name == "crc32":
            continue
        if f["role"] == "const":
            value = f["value"]
        elif f["role"] == "derived":
            value = derived[name]
        elif name == "serial":
            value = block.serial.encode("ascii").ljust(field_count("serial"), b"\0")
        else:
            value = getattr(block, name)
        _put(buf, name, n, value)
    crc_at = field_offset("crc32", n)
    _put(buf, "crc32", n, crc32(bytes(buf[:crc_at])))
    return bytes(buf)


def with_crc(data: bytes) -> bytes:
    """``data`` with the CRC field rewritten for its own ``table_len`` (for deliberately edited blocks).

    Trailing bytes after the block are kept. Raises :class:`InputError` when the header's
    ``table_len`` does not tell where the CRC sits inside ``data``.
    """
    n = _get(data, "table_len", 0) if len(data) >= HEADER_BYTES else -1
    crc_at = field_offset("crc32", n)
    if n < 0 or len(data) < crc_at + 4:
        raise InputError(None, "table_len", "data too short to hold the CRC")
    buf = bytearray(data)
    _put(buf, "crc32", n, crc32(bytes(buf[:crc_at])))
    return bytes(buf)


@dataclass(frozen=True)
class BlockCheck:
    """Outcome of the firmware's check routine (UDS routine 0x0202) on a bank image.

    Attributes
    ----------
    status : int
        0 valid, 1 CRC mismatch, 2 header invalid (the routine's status byte).
    reasons : tuple of str
        Why the block is invalid (empty when valid).
    warnings : tuple of str
        Deviations the contract does not count as invalid (non-zero reserved, unknown flag bits).
    crc_stored, crc_computed : int or None
        The CRC field and the CRC of the covered bytes, when the header locates them.
    """

    status: int
    reasons: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    crc_stored: int | None = None
    crc_computed: int | None = None

    @property
    def valid(self) -> bool:
        return self.status == STATUS_VALID


def check(data: bytes) -> BlockCheck:
    """Apply every rule of the contract's "valid" to a bank image.

    Rules, in the order the firmware applies them: magic; supported layout version; (then all
    of) ``table_len`` a power of two in 16..1024, ``block_bytes == 104 + 8*table_len``,
    ``sequence`` not 0 nor 0xFFFFFFFF, the image long enough for ``block_bytes``; any of those
    failing gives status 2. Only then the CRC: a mismatch gives status 1. Bytes after the block
    (an erased bank's 0xFF) are allowed.
    """
    data = bytes(data)
    if len(data) < HEADER_BYTES:
        return BlockCheck(STATUS_HEADER_INVALID, (f"truncated: {len(data)} bytes, the header needs "
                                                  f"{HEADER_BYTES}",))
    magic = _get(data, "magic", 0)
    if magic != MAGIC:
        erased = " (erased bank)" if data[:HEADER_BYTES] == b"\xff" * HEADER_BYTES else ""
        return BlockCheck(STATUS_HEADER_INVALID, (f"magic 0x{magic:04x} is not 0x{MAGIC:04x}{erased}",))
    version = _get(data, "layout_version", 0)
    if version not in SUPPORTED_LAYOUTS:
        return BlockCheck(STATUS_HEADER_INVALID,
                          (f"layout_version {version} not supported {list(SUPPORTED_LAYOUTS)}",))
    reasons = []
    n = _get(data, "table_len", 0)
    size = _get(data, "block_bytes", 0)
    seq = _get(data, "sequence", 0)
    n_ok = table_len_ok(n)
    if not n_ok:
        reasons.append(f"table_len {n} is not a power of two in {TABLE_LEN_MIN}..{TABLE_LEN_MAX}")
    if size != block_bytes(n):
        reasons.append(f"block_bytes {size} is not 104 + 8*table_len = {block_bytes(n)}")
    if seq in SEQUENCE_INVALID:
        reasons.append(f"sequence 0x{seq:08x} is invalid")
    if n_ok and len(data) < block_bytes(n):
        reasons.append(f"truncated: {len(data)} bytes, the block needs {block_bytes(n)}")
    warnings = []
    if _get(data, "reserved", 0) != 0:
        warnings.append(f"reserved is 0x{_get(data, 'reserved', 0):04x}, not 0")
    flags = _get(data, "flags", 0)
    if flags & ~FLAGS_KNOWN:
        warnings.append(f"flags 0x{flags:08x} has unknown bits")
    if reasons:
        return BlockCheck(STATUS_HEADER_INVALID, tuple(reasons), tuple(warnings))
    crc_at = field_offset("crc32", n)
    stored = _get(data, "crc32", n)
    computed = crc32(data[:crc_at])
    if stored != computed:
        return BlockCheck(STATUS_CRC_MISMATCH,
                          (f"CRC mismatch: stored 0x{stored:08x}, computed 0x{computed:08x}",),
                          tuple(warnings), stored, computed)
    return BlockCheck(STATUS_VALID, (), tuple(warnings), stored, computed)


def unpack(data: bytes, source: str = "<bytes>") -> ParamBlock:
    """Decode a block image (trailing bytes allowed); the CRC and sequence are NOT required valid.

    Use :func:`check` for validity. ``source`` names the file in errors.

    Raises
    ------
    InputError
        When the bytes cannot be decoded as a layout-1 block: too short, wrong magic,
        unsupported layout, table_len out of range, non-ASCII serial.
    """
    data = bytes(data)
    if len(data) < HEADER_BYTES:
        raise InputError(source, "block_bytes", f"{len(data)} bytes, the header needs {HEADER_BYTES}")
    magic = _get(data, "magic", 0)
    if magic != MAGIC:
        raise InputError(source, "magic", f"0x{magic:04x} is not 0x{MAGIC:04x}")
    version = _get(data, "layout_version", 0)
    if version not in SUPPORTED_LAYOUTS:
        raise InputError(source, "layout_version", f"{version} not supported {list(SUPPORTED_LAYOUTS)}")
    n = _get(data, "table_len", 0)
    if not table_len_ok(n):
        raise InputError(source, "table_len", f"{n} is not a power of two in {TABLE_LEN_MIN}..{TABLE_LEN_MAX}")
    if len(data) < block_bytes(n):
        raise InputError(source, "block_bytes", f"{len(data)} bytes, the block needs {block_bytes(n)}")
    raw_serial = _get(data, "serial", n).rstrip(b"\0")
    try:
        serial = raw_serial.decode("ascii")
    except UnicodeDecodeError as exc:
        raise InputError(source, "serial", f"not ASCII: {raw_serial!r}") from exc
    kwargs: dict[str, Any] = {"serial": serial}
    for f in LAYOUT["field"]:
        if f["role"] == "field" and f["name"] != "serial":
            kwargs[f["name"]] = _get(data, f["name"], n)
    kwargs["hall_angle"] = tuple(float(a) for a in kwargs["hall_angle"])
    return ParamBlock(**kwargs)


def to_intel_hex(data: bytes, bank: int) -> str:
    """Intel HEX text of a bank image placed at its F28335 flash address.

    The contract gives word addresses; HEX records count bytes, so the image starts at byte
    address ``2 * BANK_WORD_ADDR[bank]`` (0x650000 for bank 0, 0x660000 for bank 1) with the
    low byte of each word first. This is eol-cal's choice, documented in firmware_params/README.md.
    """
    from intelhex import IntelHex

    if bank not in (0, 1):
        raise InputError(None, "bank", f"{bank!r}: must be 0 or 1")
    if len(data) > BANK_BYTES:
        raise InputError(None, "block_bytes", f"{len(data)} bytes exceed a bank ({BANK_BYTES})")
    if len(data) % 2:
        raise InputError(None, "block_bytes", f"{len(data)} bytes: the flash takes whole 16-bit words")
    ih = IntelHex()
    ih.frombytes(bytes(data), offset=2 * BANK_WORD_ADDR[bank])
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
    from intelhex import IntelHex, IntelHexError

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
        start = 2 * BANK_WORD_ADDR[b]
        if start <= addrs[0] and addrs[-1] < start + BANK_BYTES:
            return b, ih.tobinstr(start=start, end=addrs[-1])
    ranges = ", ".join(f"bank {b}: bytes 0x{2 * BANK_WORD_ADDR[b]:x}..0x{2 * BANK_WORD_ADDR[b] + BANK_BYTES - 1:x}"
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
    from eol_cal.inputs import read_bytes

    source = source or str(path)
    data = read_bytes(path, "file", max_bytes=4 * BANK_BYTES)  # no FIFO, no device, no gigabytes
    if data[:1] == b":" or Path(path).suffix.lower() in HEX_SUFFIXES:
        try:
            text = data.decode("ascii")
        except UnicodeDecodeError as exc:
            raise InputError(source, "hex", "not ASCII text") from exc
        return intel_hex_bank(text, source)[1]
    return data
