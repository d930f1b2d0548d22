"""The F28335 calibration parameter block (``docs/firmware-contract.md`` section 2): pack, unpack, check.

Split by concern: the byte layout (read from ``layout_v1.toml``, the one place it is defined) is
:mod:`eol_cal.firmware.block_layout`, the firmware's check routine
:mod:`eol_cal.firmware.block_check`, block files and Intel HEX :mod:`eol_cal.firmware.block_file`;
this module holds the decoded block and packs/unpacks it, and re-exports the other three, so
``block.X`` names every public piece. The C header ``firmware_params/eol_param_block.h`` is
generated from the same layout (:mod:`eol_cal.firmware.gen_header`).

Invariant: :func:`pack` only ever returns a block that :func:`check` calls valid; blocks with
invalid headers exist only as bytes (tests and golden vectors patch them on purpose).

Two layouts (contract revision 1.2): a block without ``mech`` is layout 1, exactly as before; a
block with ``mech`` (:class:`eol_cal.firmware.mech_params.MechParams`) is layout 2.
"""

from __future__ import annotations

import functools
import math
import operator
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from eol_cal.errors import InputError
# the check routine and block files, also read through this module (block.check, block.read_block_file)
from eol_cal.firmware.block_check import BlockCheck, check, flag_warnings  # noqa: F401
from eol_cal.firmware.block_file import (  # noqa: F401
    HEX_SUFFIXES,
    from_intel_hex,
    intel_hex_bank,
    read_block_file,
    to_intel_hex,
)
# the layout, also read through this module (block.FIELDS, block.field_offset, ...)
from eol_cal.firmware.block_layout import (  # noqa: F401
    BANK_BYTE_ADDR,
    BANK_BYTES,
    BANK_WORD_ADDR,
    BANK_WORDS,
    FIELDS,
    FIELDS_BY_VERSION,
    HEADER_BYTES,
    LAYOUT,
    LAYOUTS,
    LAYOUT_VERSION,
    LAYOUT_VERSION_MECH,
    SEQUENCE_INVALID,
    SIZE as _SIZE,
    SUPPORTED_LAYOUTS,
    TABLE_LEN_MAX,
    TABLE_LEN_MIN,
    block_bytes,
    crc32,
    field_count,
    field_offset,
    flag_names,
    table_len_ok,
)
from eol_cal.firmware.block_layout import get_field as _get
from eol_cal.firmware.block_layout import put_field as _put
# the contract's constants, also read through this module (block.FLAG_COMP_ENABLE, block.STATUS_VALID)
from eol_cal.firmware.contract import (  # noqa: F401
    FLAG_COMP_ENABLE,
    FLAG_INTERP_ENABLE,
    FLAG_MECH_COMP_ENABLE,
    FLAGS,
    FLAGS_ESTIMATOR,
    FLAGS_KNOWN,
    MAGIC,
    STATUS_CRC_MISMATCH,
    STATUS_HEADER_INVALID,
    STATUS_VALID,
)
from eol_cal.firmware.mech_params import FP_MAX, MechParams, mech_problems


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
        ``FLAG_COMP_ENABLE``, ``FLAG_INTERP_ENABLE`` and the estimator option bits 2-5
        (``contract.ESTIMATOR_OPTIONS``, honoured only with ``FLAG_INTERP_ENABLE``).
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
        Layout version: 1 without ``mech``, 2 with it (the default follows ``mech``).
    mech : MechParams, optional
        The mechanical-order extension of layout 2 (contract revision 1.2).
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
    layout_version: int | None = None
    mech: MechParams | None = None

    def __post_init__(self) -> None:
        put = object.__setattr__
        if self.layout_version is None:
            put(self, "layout_version", LAYOUT_VERSION_MECH if self.mech is not None else LAYOUT_VERSION)
        if self.mech is not None and not isinstance(self.mech, MechParams):
            raise InputError(None, "mech", f"not MechParams: {type(self.mech).__name__}")
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

    @functools.cached_property
    def image(self) -> bytes:
        """The block's byte image, :func:`pack`'s, made once per block: the block cannot change
        (frozen fields, read-only tables, a frozen mechanical part), and a simulated ECU reads its
        CRC every run (a layout-2 block's image costs ~0.3 ms, a simulated second's 4 %)."""
        return pack(self)

    @property
    def crc(self) -> int:
        """The CRC32 its image stores (what :func:`check` reports as ``crc_stored``)."""
        assert self.layout_version is not None  # __post_init__ sets it
        return int(_get(self.image, "crc32", self.table_len, self.layout_version))

    @property
    def table_len(self) -> int:
        """N, the number of table entries."""
        return int(self.table_const.size)

    @property
    def block_bytes(self) -> int:
        """Size of the packed block, CRC included (bytes)."""
        return block_bytes(self.table_len, self.layout_version if self.layout_version in LAYOUTS else 1)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ParamBlock):
            return NotImplemented
        scalars = [n for n in self.__dataclass_fields__ if n not in ("table_const", "table_per_amp", "mech")]
        # Compare floats by bit pattern so that NaN == NaN and -0.0 != 0.0, like the bytes do.
        return (all(_bits(getattr(self, n)) == _bits(getattr(other, n)) for n in scalars)
                and self.mech == other.mech
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
            if name == "mech":
                if v is not None:
                    d["mech"] = v.to_dict()
                continue
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


def serial_problem(serial: str) -> str | None:
    """Why ``serial`` cannot name a motor in a block (None when it can): 1 to 16 printable ASCII
    characters without surrounding blanks (an empty serial passed ``table`` into a block)."""
    try:
        raw = serial.encode("ascii")
    except UnicodeEncodeError:
        return f"not ASCII: {serial!r}"
    if not raw.strip():
        return "empty"
    if len(raw) > field_count("serial"):
        return f"{len(raw)} characters, at most {field_count('serial')}"
    if b"\0" in raw:
        return "contains NUL"
    if not serial.isprintable() or serial != serial.strip():
        return f"{serial!r}: control characters or surrounding blanks"
    return None


def pack_problems(block: ParamBlock) -> list[tuple[str, str]]:
    """Why ``block`` cannot be packed into a valid block: a list of (field, reason), empty if it can."""
    problems: list[tuple[str, str]] = []
    if block.layout_version not in SUPPORTED_LAYOUTS:
        problems.append(("layout_version", f"{block.layout_version} not supported {SUPPORTED_LAYOUTS}"))
    elif (block.layout_version == LAYOUT_VERSION_MECH) != (block.mech is not None):
        problems.append(("layout_version", f"layout {block.layout_version} "
                         + ("needs the mechanical part (mech)" if block.mech is None else "has no mechanical part")))
    if block.flags & FLAG_MECH_COMP_ENABLE and block.mech is None:
        problems.append(("flags", "MECH_COMP_ENABLE needs a layout-2 block (the mechanical part)"))
    if block.mech is not None:
        problems += mech_problems(block.mech, block.encoder_ppr)
    if not 0 < block.sequence < 0xFFFFFFFF:
        problems.append(("sequence", f"{block.sequence} outside 1..0xFFFFFFFE"))
    if block.flags & ~FLAGS_KNOWN or block.flags < 0:
        problems.append(("flags", f"0x{block.flags:x} has bits the contract does not define "
                                  f"(known: {flag_names(FLAGS_KNOWN)})"))
    why = serial_problem(block.serial)
    if why is not None:
        problems.append(("serial", why))
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
    v = block.layout_version
    assert v is not None  # __post_init__ sets the default layout, and pack_problems refused an unsupported one
    size = block_bytes(n, v)
    buf = bytearray(size)
    derived = {"block_bytes": size, "table_len": n}
    mech = block.mech
    if mech is not None:
        derived["fp_len"] = mech.fp_len
    for f in LAYOUTS[v]["field"]:
        name = f["name"]
        if name == "crc32":
            continue
        if f["role"] == "const":
            value = f["value"]
        elif f["role"] == "derived":
            value = derived[name]
        elif name == "serial":
            value = block.serial.encode("ascii").ljust(field_count("serial"), b"\0")
        elif name == "fingerprint":
            assert mech is not None  # a layout-2 field, and pack_problems refused layout 2 without the mechanical part
            value = np.zeros(2 * FP_MAX, np.float32)
            value[:mech.fingerprint.size] = mech.fingerprint
        elif name in FIELDS:
            value = getattr(block, name)
        else:
            value = getattr(mech, name)
        _put(buf, name, n, value, v)
    crc_at = field_offset("crc32", n, v)
    _put(buf, "crc32", n, crc32(bytes(buf[:crc_at])), v)
    return bytes(buf)


def with_crc(data: bytes, version: int | None = None) -> bytes:
    """``data`` with the CRC field rewritten for its own ``table_len`` (for deliberately edited blocks).

    The CRC sits where layout ``version`` puts it; by default the header's layout when it is
    supported and the image long enough for it, else layout 1 (an edited header, e.g. a wrong
    layout version, keeps its CRC where the image has it). Trailing bytes after the block are
    kept. Raises :class:`InputError` when the header's ``table_len`` does not tell where the CRC
    sits inside ``data``.
    """
    n = _get(data, "table_len", 0) if len(data) >= HEADER_BYTES else -1
    if version is None:
        v = _get(data, "layout_version", 0) if len(data) >= HEADER_BYTES else 1
        version = v if v in LAYOUTS and n >= 0 and len(data) >= block_bytes(n, v) else 1
    v = version
    crc_at = field_offset("crc32", n, v)
    if n < 0 or len(data) < crc_at + 4:
        raise InputError(None, "table_len", "data too short to hold the CRC")
    buf = bytearray(data)
    _put(buf, "crc32", n, crc32(bytes(buf[:crc_at])), v)
    return bytes(buf)


def unpack(data: bytes, source: str = "<bytes>") -> ParamBlock:
    """Decode a block image (trailing bytes allowed); the CRC and sequence are NOT required valid.

    Use :func:`check` for validity. ``source`` names the file in errors.

    Raises
    ------
    InputError
        When the bytes cannot be decoded as a block of a supported layout: too short, wrong
        magic, unsupported layout, table_len out of range, non-ASCII serial, a fingerprint
        longer than its room.
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
    if len(data) < block_bytes(n, version):
        raise InputError(source, "block_bytes", f"{len(data)} bytes, the block needs {block_bytes(n, version)}")
    raw_serial = _get(data, "serial", n).rstrip(b"\0")
    try:
        serial = raw_serial.decode("ascii")
    except UnicodeDecodeError as exc:
        raise InputError(source, "serial", f"not ASCII: {raw_serial!r}") from exc
    kwargs: dict[str, Any] = {"serial": serial}
    mech: dict[str, Any] = {}
    for f in LAYOUTS[version]["field"]:
        if f["role"] == "field" and f["name"] != "serial":
            (kwargs if f["name"] in FIELDS else mech)[f["name"]] = _get(data, f["name"], n, version)
    kwargs["hall_angle"] = tuple(float(a) for a in kwargs["hall_angle"])
    if version == LAYOUT_VERSION_MECH:
        fp_len = _get(data, "fp_len", n, version)
        if fp_len > FP_MAX:
            raise InputError(source, "fp_len", f"{fp_len} pulses, the fingerprint holds at most {FP_MAX}")
        mech["fingerprint"] = mech["fingerprint"][:2 * fp_len]
        kwargs["mech"] = MechParams(**mech)
    return ParamBlock(**kwargs)
