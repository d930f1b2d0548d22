"""The firmware's check routine on a bank image (``docs/firmware-contract.md`` section 2, "valid"):
the status the ECU answers, with reasons and warnings."""

from __future__ import annotations

from dataclasses import dataclass

from eol_cal.firmware.block_layout import (
    HEADER_BYTES,
    SEQUENCE_INVALID,
    SUPPORTED_LAYOUTS,
    TABLE_LEN_MAX,
    TABLE_LEN_MIN,
    block_bytes,
    crc32,
    field_offset,
    flag_names,
    table_len_ok,
)
from eol_cal.firmware.block_layout import get_field as _get
from eol_cal.firmware.contract import (
    FLAG_MECH_COMP_ENABLE,
    FLAGS_KNOWN,
    FLAGS_MECH_NEEDS,
    MAGIC,
    STATUS_CRC_MISMATCH,
    STATUS_HEADER_INVALID,
    STATUS_VALID,
)
from eol_cal.firmware.mech_params import FP_MAX, MECH_TABLE_LEN
from eol_cal.firmware.options import ignored_options


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
    of) ``table_len`` a power of two in 16..1024, ``block_bytes == 104 + 8*table_len`` (layout 1)
    or ``3248 + 8*table_len`` (layout 2),
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
    want = block_bytes(n, version)
    if size != want:
        reasons.append(f"block_bytes {size} is not {block_bytes(0, version)} + 8*table_len = {want}")
    if seq in SEQUENCE_INVALID:
        reasons.append(f"sequence 0x{seq:08x} is invalid")
    if n_ok and len(data) < want:
        reasons.append(f"truncated: {len(data)} bytes, the block needs {want}")
    warnings = []
    if _get(data, "reserved", 0) != 0:
        warnings.append(f"reserved is 0x{_get(data, 'reserved', 0):04x}, not 0")
    warnings += flag_warnings(_get(data, "flags", 0), version)
    if version >= 2 and n_ok and len(data) >= want:
        warnings += mech_warnings(data, n)
    if reasons:
        return BlockCheck(STATUS_HEADER_INVALID, tuple(reasons), tuple(warnings))
    crc_at = field_offset("crc32", n, version)
    stored = _get(data, "crc32", n, version)
    computed = crc32(data[:crc_at])
    if stored != computed:
        return BlockCheck(STATUS_CRC_MISMATCH,
                          (f"CRC mismatch: stored 0x{stored:08x}, computed 0x{computed:08x}",),
                          tuple(warnings), stored, computed)
    return BlockCheck(STATUS_VALID, (), tuple(warnings), stored, computed)




def mech_warnings(data: bytes, table_len: int) -> list[str]:
    """What a layout-2 block's extension holds that the contract does not make invalid but a
    reader should know (revision 1.2): a ``mech_table_len`` or ``fp_len`` the firmware cannot use
    or a non-zero ``reserved2`` (it then ignores ``MECH_COMP_ENABLE``), and ``MECH_COMP_ENABLE``
    without a fingerprint (``fp_dirs`` 0) or with ``fp_len`` not the encoder's pulses."""
    def get(name: str) -> int:
        return _get(data, name, table_len, 2)

    warnings = []
    if get("mech_table_len") != MECH_TABLE_LEN:
        warnings.append(f"mech_table_len is {get('mech_table_len')}, not {MECH_TABLE_LEN}: the firmware "
                        "ignores MECH_COMP_ENABLE")
    if get("fp_len") > FP_MAX:
        warnings.append(f"fp_len is {get('fp_len')}, more than the {FP_MAX} pulses the fingerprint holds: the "
                        "firmware ignores MECH_COMP_ENABLE")
    if get("reserved2") != 0:
        warnings.append(f"reserved2 is 0x{get('reserved2'):04x}, not 0")
    if get("flags") & FLAG_MECH_COMP_ENABLE:
        if get("fp_dirs") == 0:
            warnings.append("MECH_COMP_ENABLE is set but fp_dirs is 0 (no fingerprint measured): the firmware "
                            "ignores it")
        if get("fp_len") != get("encoder_ppr"):
            warnings.append(f"MECH_COMP_ENABLE is set but fp_len {get('fp_len')} is not encoder_ppr "
                            f"{get('encoder_ppr')}: the firmware ignores it")
    return warnings


def flag_warnings(flags: int, version: int = 1) -> list[str]:
    """What the contract allows in a ``flags`` word but a reader should know: bits it does not
    define, estimator options set without ``INTERP_ENABLE``, ``MECH_COMP_ENABLE`` in a layout-1
    block or without the bits it needs (the firmware ignores them)."""
    warnings = []
    if flags & FLAG_MECH_COMP_ENABLE:
        if version < 2:
            warnings.append(f"flags 0x{flags:08x} sets MECH_COMP_ENABLE in a layout-{version} block: "
                            "the firmware needs layout 2's mechanical part and ignores it")
        elif flags & FLAGS_MECH_NEEDS != FLAGS_MECH_NEEDS:
            warnings.append(f"flags 0x{flags:08x} sets MECH_COMP_ENABLE without "
                            f"{flag_names(FLAGS_MECH_NEEDS & ~flags)}: the firmware ignores it")
    if flags & ~FLAGS_KNOWN:
        warnings.append(f"flags 0x{flags:08x} has unknown bits (0x{flags & ~FLAGS_KNOWN:x})")
    ignored = ignored_options(flags)
    if ignored:
        warnings.append(f"flags 0x{flags:08x} sets estimator options {flag_names(ignored)} without "
                        f"INTERP_ENABLE: the firmware honours them only with the interpolated angle")
    return warnings
