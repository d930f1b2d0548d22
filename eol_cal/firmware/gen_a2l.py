"""The A2L description of the parameter block (``docs/firmware-contract.md`` section 5).

ASAM MCD-2 MC (``ASAP2_VERSION 1 71``) text for calibration tools (CANape, INCA), built from the
same layout files as the C header (``layout_v1.toml``, ``layout_v2.toml`` through
:mod:`eol_cal.firmware.block`) and
the contract's constants (:mod:`eol_cal.firmware.contract`); nothing here restates an offset, a
type or a unit. ``python -m eol_cal.firmware.gen_header`` writes the checked-in
``firmware_params/eol_param_block.a2l`` (layout 1) and ``eol_param_block_v2.a2l`` (layout 2), bank 0,
the default table length;
``eol-cal block a2l`` writes one for either bank and any table length.

Addresses are BYTE addresses, ``2 x`` the F28335's 16-bit word address, as in the Intel HEX files
(bank 0 starts at 0x650000). The byte image is little-endian (``BYTE_ORDER MSB_LAST``).
"""

from __future__ import annotations

import operator
from typing import Any


from eol_cal.errors import InputError
from eol_cal.firmware import block as B
from eol_cal.firmware import contract as C
from eol_cal.firmware.block_layout import BANK_BYTE_ADDR
from eol_cal.firmware.block_sanity import field_limits
from eol_cal.firmware.contract import DEFAULT_TABLE_LEN
from eol_cal.domain.motor_params import MotorParams, load_motor

#: A2L data type of each layout element type
DATATYPE: dict[str, str] = {"u8": "UBYTE", "u16": "UWORD", "u32": "ULONG", "f32": "FLOAT32_IEEE"}
#: more named flag bits than this would make the flags word's verbal table (2**bits rows) unwieldy
_MAX_VERBAL_FLAG_BITS = 8


def bank_byte_address(bank: int) -> int:
    """Byte address of ``bank``'s start: ``2 x`` its word address (the contract's Intel HEX rule).

    Raises
    ------
    InputError
        When ``bank`` is not 0 or 1.
    """
    if bank not in (0, 1):
        raise InputError(None, "bank", f"{bank!r}: must be 0 or 1")
    return BANK_BYTE_ADDR[bank]


def record_layout_name(type_: str) -> str:
    """Name of the RECORD_LAYOUT of a layout element type (``f32`` -> ``RL_FLOAT32_IEEE``)."""
    return f"RL_{DATATYPE[type_]}"


def compu_method_name(unit: str) -> str:
    """Name of the identical COMPU_METHOD of a unit (``N*m/A`` -> ``CM_N_m_per_A``, none -> ``CM_1``)."""
    if not unit:
        return "CM_1"
    safe = unit.replace("/", "_per_").replace("*", "_").replace(".", "_")
    if not all(c.isalnum() or c == "_" for c in safe):
        raise ValueError(f"unit {unit!r} cannot name an A2L COMPU_METHOD")
    return f"CM_{safe}"


def flag_characteristic_name(flag: str) -> str:
    """Name of the CHARACTERISTIC of one named bit of ``flags`` (``flags.COMP_ENABLE``)."""
    return f"flags.{flag}"


def _q(text: str) -> str:
    """An A2L string literal (a quote is written as two)."""
    return '"' + text.replace("\\", "\\\\").replace('"', '""') + '"'


def _number(x: float) -> str:
    """A limit as A2L text: an integer as is, a float with the digits that give it back."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 2**53 else repr(float(x))


def _limits(f: dict[str, Any], table_len: int, version: int, motor: MotorParams) -> tuple[str, str]:
    """Lower and upper limit of a field: the contract's bounds (:func:`block_sanity.field_limits`)."""
    lo, hi = field_limits(f["name"], version, table_len, motor)
    return _number(lo), _number(hi)


#: fields a calibration tool must not change although pack takes them from the caller: the layout
#: version is the file's own (another value makes it another layout, described by another file)
READ_ONLY_FIELDS = frozenset({"layout_version"})


def check_table_len(table_len: int) -> int:
    """``table_len`` as an int when it is a table length a block can have, else :class:`InputError`."""
    try:
        n = operator.index(table_len)
    except TypeError:
        n = -1
    if isinstance(table_len, bool) or not B.table_len_ok(n):
        raise InputError(None, "table_len", f"{table_len!r}: needs a power of two in "
                                            f"{B.TABLE_LEN_MIN}..{B.TABLE_LEN_MAX}")
    return n


def _characteristic(f: dict[str, Any], base: int, table_len: int, version: int, motor: MotorParams) -> list[str]:
    """The CHARACTERISTIC of one layout field at bank start ``base`` (byte address)."""
    name, type_ = f["name"], f["type"]
    count = B.field_count(name, table_len, version)
    lower, upper = _limits(f, table_len, version, motor)
    if name == "serial":
        kind, conversion = "ASCII", "NO_COMPU_METHOD"
    else:
        kind = "VALUE" if f.get("count", 1) == 1 else "VAL_BLK"
        conversion = "CM_FLAGS" if name == "flags" else compu_method_name(f.get("unit", ""))
    lines = [
        f"    /begin CHARACTERISTIC {name} {_q(f['meaning'])}",
        f"      {kind} 0x{base + B.field_offset(name, table_len, version):X} {record_layout_name(type_)} 0 {conversion} "
        f"{lower} {upper}",
    ]
    if kind != "VALUE":
        lines.append(f"      MATRIX_DIM {count}")
    if type_ != "f32" and kind != "ASCII" and name != "flags":
        lines.append('      FORMAT "%10.0"')  # an integer: the unit's method shows decimals
    if f.get("unit"):
        lines.append(f"      PHYS_UNIT {_q(f['unit'])}")
    if f["role"] != "field" or name in READ_ONLY_FIELDS:
        lines.append("      READ_ONLY")  # pack derives it, the contract fixes it, or it is the file's layout
    lines.append("    /end CHARACTERISTIC")
    return lines


def _flag_bit_characteristics(base: int) -> list[str]:
    """One CHARACTERISTIC per named bit of ``flags`` (BIT_MASK on the flags word, shown off/on)."""
    addr = base + B.field_offset("flags")
    type_ = B.FIELDS["flags"]["type"]
    out = []
    for name, flag in C.FLAGS.items():
        out += [
            f"    /begin CHARACTERISTIC {flag_characteristic_name(name)} {_q(f'flags bit {flag.bit}: {flag.meaning}')}",
            f"      VALUE 0x{addr:X} {record_layout_name(type_)} 0 CM_FLAG_BIT 0 1",
            f"      BIT_MASK 0x{1 << flag.bit:X}",
            "    /end CHARACTERISTIC",
        ]
    return out


def _flags_compu() -> list[str]:
    """COMPU_METHODs of the flags word (every combination of the named bits by name) and of one bit."""
    bits = [flag.bit for flag in C.FLAGS.values()]
    if len(bits) > _MAX_VERBAL_FLAG_BITS:
        raise ValueError(f"{len(bits)} named flag bits: the flags word's verbal table would have 2**{len(bits)} rows")
    values = sorted({sum(1 << b for i, b in enumerate(bits) if combo >> i & 1) for combo in range(1 << len(bits))})
    rows = [f"      {v} {_q(B.flag_names(v))}" for v in values]
    return [
        f"    /begin COMPU_METHOD CM_FLAGS {_q('flags word: the named bits that are set')}",
        '      TAB_VERB "%10.0" ""',
        "      COMPU_TAB_REF VT_FLAGS",
        "    /end COMPU_METHOD",
        f"    /begin COMPU_VTAB VT_FLAGS {_q('flags by name')} TAB_VERB {len(values)}",
        *rows,
        f"      DEFAULT_VALUE {_q('bits the contract does not name are set')}",
        "    /end COMPU_VTAB",
        f"    /begin COMPU_METHOD CM_FLAG_BIT {_q('one flags bit')}",
        '      TAB_VERB "%1.0" ""',
        "      COMPU_TAB_REF VT_FLAG_BIT",
        "    /end COMPU_METHOD",
        f'    /begin COMPU_VTAB VT_FLAG_BIT {_q("off/on")} TAB_VERB 2',
        '      0 "off"',
        '      1 "on"',
        "    /end COMPU_VTAB",
    ]


def _memory_segments() -> list[str]:
    out = []
    for bank, word_addr in enumerate(B.BANK_WORD_ADDR):
        out += [
            f"      /begin MEMORY_SEGMENT BANK{bank} "
            f"{_q(f'parameter bank {bank}, word address 0x{word_addr:X}, {B.BANK_WORDS:#x} words')}",
            f"        DATA FLASH INTERN 0x{bank_byte_address(bank):X} 0x{B.BANK_BYTES:X} -1 -1 -1 -1 -1",
            "      /end MEMORY_SEGMENT",
        ]
    return out


def render_a2l(bank: int = 0, table_len: int = DEFAULT_TABLE_LEN, version: int = 1,
               motor: MotorParams | None = None) -> str:
    """The A2L text of the layout-``version`` block in ``bank`` with ``table_len`` table entries
    (deterministic).

    Parameters
    ----------
    bank : int
        0 or 1: the bank whose addresses the CHARACTERISTICs carry (both MEMORY_SEGMENTs are
        always described).
    table_len : int
        N, the number of entries of each table (a power of two, 16..1024): the tables and the
        CRC's address depend on it.
    version : int
        The layout (1, or 2 with the mechanical-order extension of revision 1.2).
    motor : MotorParams, optional
        Whose current rating ``i_max`` (A) and encoder pitch bound the tables, ``iqc_limit`` and
        the fingerprint (the contract's bounds depend on them); the paper's motor by default.

    Raises
    ------
    InputError
        ``bank`` not 0 or 1, ``table_len`` not a valid table length, or an unknown layout.
    """
    base = bank_byte_address(bank)
    table_len = check_table_len(table_len)
    motor = load_motor() if motor is None else motor
    if version not in B.LAYOUTS:
        raise InputError(None, "layout", f"{version!r}: known layouts {sorted(B.LAYOUTS)}")
    L = B.LAYOUTS[version]
    units = sorted({f.get("unit", "") for f in L["field"] if f["name"] not in ("flags", "serial")})
    types = sorted({f["type"] for f in L["field"]}, key=list(DATATYPE).index)
    out = [
        f"/* eol_param_block.a2l: calibration parameter block, layout version {L['layout_version']},",
        f" * DESCRIBING bank {bank} (byte address 0x{base:X}) with table_len = {table_len}",
        f" * (block_bytes = {B.block_bytes(table_len, version)}).",
        " *",
        f" * GENERATED by eol_cal.firmware.gen_a2l from eol_cal/firmware/layout_v{version}.toml"
        + (" (on layout_v1.toml)" if version != 1 else "") + " and",
        " * eol_cal/firmware/contract.py (`python -m eol_cal.firmware.gen_header` writes the checked-in",
        " * file, `eol-cal block a2l` one for either bank and any table_len). Do not edit.",
        " *",
        " * Addresses are BYTE addresses = 2 x the F28335 word address (as in eol-cal's Intel HEX);",
        " * the byte image is little-endian. table_const, table_per_amp and crc32 sit where a block",
        f" * of table_len = {table_len} puts them: a block with another table_len needs its own file.",
        " * Changing a value invalidates crc32: the firmware then refuses the block.",
        " * Limits are the contract's bounds (docs/firmware-contract.md section 2, \"Bounds\") for a motor",
        f" * of i_max = {_number(motor.i_max)} A, {motor.poles} poles, {motor.N_enc} PPR (tables, iqc_limit, fingerprint).",
        " */",
        "ASAP2_VERSION 1 71",
        f"/begin PROJECT EOL_CAL {_q('eol-cal end-of-line torque-ripple calibration')}",
        f"  /begin HEADER {_q('F28335 calibration parameter block')}",
        f"    VERSION {_q(f'layout {version} table_len {table_len} bank {bank}')}",
        "  /end HEADER",
        f"  /begin MODULE EOL_PARAM_BLOCK {_q(f'parameter block, layout version {version}')}",
        f"    /begin MOD_PAR {_q('TI TMS320F28335 (C28x), two parameter banks')}",
        f"      SYSTEM_CONSTANT \"table_len\" \"{table_len}\"",
        f"      SYSTEM_CONSTANT \"bank\" \"{bank}\"",
        *_memory_segments(),
        "    /end MOD_PAR",
        f"    /begin MOD_COMMON {_q('byte image of the C28x word memory')}",
        "      BYTE_ORDER MSB_LAST",
        *[f"      ALIGNMENT_{a} {n}" for a, n in (("BYTE", 1), ("WORD", 2), ("LONG", 4), ("FLOAT32_IEEE", 4))],
        "    /end MOD_COMMON",
    ]
    for type_ in types:
        out += [f"    /begin RECORD_LAYOUT {record_layout_name(type_)}",
                f"      FNC_VALUES 1 {DATATYPE[type_]} ROW_DIR DIRECT",
                "    /end RECORD_LAYOUT"]
    for unit in units:
        shown = unit or "no unit"
        out += [f"    /begin COMPU_METHOD {compu_method_name(unit)} {_q(f'identical, {shown}')}",
                f"      IDENTICAL \"%12.6\" {_q(unit)}",
                "    /end COMPU_METHOD"]
    out += _flags_compu()
    for f in L["field"]:
        out += _characteristic(f, base, table_len, version, motor)
    out += _flag_bit_characteristics(base)
    out += ["  /end MODULE", "/end PROJECT", ""]
    return "\n".join(out)
