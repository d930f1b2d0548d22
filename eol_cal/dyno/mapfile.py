"""Read and check a dyno register map file (TOML) into a :class:`~eol_cal.dyno.regmap.RegisterMap`.

Every key is checked on load; a bad one is an :class:`~eol_cal.errors.InputError` naming the
file, the key (``registers.speed_setpoint.scale``) and the reason. The format is in
``docs/dyno.md``, "Writing a register map"; the maps shipped with eol-cal are in
``eol_cal/dyno/maps`` (``default``: the eol-cal reference dyno; ``vendor-b``: a dyno laid out
differently, which the simulator can serve too).
"""

from __future__ import annotations

import functools
import itertools
import math
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any
from collections.abc import Mapping

from eol_cal.dyno import regcodec as rc
from eol_cal.dyno.regmap import Entry, RegisterMap, Window
from eol_cal.dyno.registers import ANALOG_NAMES, DIGITAL_FIELDS, ROLES, Role
from eol_cal.errors import InputError
from eol_cal.infra.inputs import load_toml

DEFAULT_MAP = "default"
TABLES = ("holding", "input")
_TOP_KEYS = ("name", "map_version", "byte_order", "word_order", "shared_tables", "max_read_registers",
             "max_write_registers", "window", "channels", "registers")
_ENTRY_KEYS = ("address", "type", "count", "table", "scale", "offset", "unit", "codes", "bits", "invalid", "meaning")
_WINDOW_KEYS = ("address", "registers", "table", "analog_type", "digital_id", "digital_bits")
#: Modbus PDU limits: 125 registers per read, 123 per write
MAX_READ, MAX_WRITE = 125, 123


def shipped_maps() -> tuple[str, ...]:
    """Names of the maps shipped with eol-cal (``eol_cal/dyno/maps/NAME.toml``)."""
    return tuple(sorted(p.name[:-5] for p in resources.files("eol_cal.dyno.maps").iterdir() if p.name.endswith(".toml")))


def map_path(spec: str | Path | None) -> str | Path:
    """The file of a map given as a file path, a shipped map's name, or None (the default map)."""
    spec = DEFAULT_MAP if spec is None else spec
    text = str(spec)
    if Path(text).is_file() or text.endswith(".toml") or "/" in text:
        return Path(text)
    if text not in shipped_maps():
        raise InputError(None, "register map", f"{text!r} is neither a file nor a shipped map ({', '.join(shipped_maps())})")
    return Path(str(resources.files("eol_cal.dyno.maps").joinpath(f"{text}.toml")))


@functools.lru_cache(maxsize=1)
def default_register_map() -> RegisterMap:
    """The ``default`` map shipped with eol-cal (read once)."""
    return load_register_map(DEFAULT_MAP)


def load_register_map(spec: str | Path | None = None) -> RegisterMap:
    """A register map from a file path or a shipped map's name (default: the ``default`` map).

    Raises
    ------
    InputError
        Unreadable file, bad TOML, or any key that is unknown, missing, of the wrong type or out
        of range, overlapping registers, a writable role in the input table... (file, key, reason).
    """
    path = map_path(spec)
    return parse_register_map(load_toml(path), str(path))


class _Checker:
    """Typed reads of one map file's keys, each refusal naming the file and the dotted key."""

    def __init__(self, file: str) -> None:
        self.file = file

    def fail(self, key: str | None, reason: str) -> InputError:
        return InputError(self.file, key, reason)

    def int_(self, table: Mapping[str, Any], key: str, where: str, lo: int, hi: int, default: int | None = None) -> int:
        if key not in table:
            if default is None:
                raise self.fail(where, "missing")
            return default
        v = table[key]
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(where, f"{v!r} is not an integer")
        if not lo <= v <= hi:
            raise self.fail(where, f"{v} outside {lo} ... {hi}")
        return v

    def number(self, table: Mapping[str, Any], key: str, where: str, default: float) -> float:
        v = table.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.fail(where, f"{v!r} is not a finite number")
        return float(v)

    def choice(self, table: Mapping[str, Any], key: str, where: str, choices: tuple[str, ...], default: str | None = None) -> str:
        v = table.get(key, default)
        if v is None:
            raise self.fail(where, f"missing (one of {', '.join(choices)})")
        if v not in choices:
            raise self.fail(where, f"{v!r} is not one of {', '.join(choices)}")
        return str(v)

    def table(self, doc: Mapping[str, Any], key: str, where: str, known: tuple[str, ...] | None) -> dict[str, Any]:
        v = doc.get(key)
        if not isinstance(v, dict):
            raise self.fail(where, "missing table" if v is None else "must be a table")
        if known is not None:
            for k in v:
                if k not in known:
                    raise self.fail(f"{where}.{k}", f"unknown key; known: {', '.join(known)}")
        return v


def parse_register_map(doc: Mapping[str, Any], file: str) -> RegisterMap:
    """A map file's parsed TOML as a checked :class:`RegisterMap` (see :func:`load_register_map`)."""
    c = _Checker(file)
    for k in doc:
        if k not in _TOP_KEYS:
            raise c.fail(k, f"unknown key; known: {', '.join(_TOP_KEYS)}")
    name = doc.get("name", Path(file).stem)
    if not isinstance(name, str) or not name.strip():
        raise c.fail("name", "must be a non-empty string")
    byte_order = c.choice(doc, "byte_order", "byte_order", rc.ORDERS, "big")
    word_order = c.choice(doc, "word_order", "word_order", rc.ORDERS, "big")
    shared = doc.get("shared_tables", False)
    if not isinstance(shared, bool):
        raise c.fail("shared_tables", f"{shared!r} is not true or false")
    max_read = c.int_(doc, "max_read_registers", "max_read_registers", 1, MAX_READ, MAX_READ)
    max_write = c.int_(doc, "max_write_registers", "max_write_registers", 2, MAX_WRITE, MAX_WRITE)
    window = _window(c, c.table(doc, "window", "window", _WINDOW_KEYS))
    channels = _channels(c, c.table(doc, "channels", "channels", ANALOG_NAMES), window)
    regs = c.table(doc, "registers", "registers", tuple(ROLES))
    entries = {n: _entry(c, ROLES[n], t, f"registers.{n}") for n, t in regs.items()}
    for role in ROLES.values():
        if role.required and role.name not in entries:
            raise c.fail(f"registers.{role.name}", f"missing: the client needs it ({role.meaning})")
    map_version = None
    if "map_version" in entries:
        map_version = c.int_(doc, "map_version", "map_version", 0, 0xFFFF)
    elif "map_version" in doc:
        raise c.fail("map_version", "given, but the map places no registers.map_version to read it from")
    for e in entries.values():
        if e.count > max_write and e.role.writable:
            raise c.fail(f"registers.{e.name}.count", f"{e.count} registers is more than one write ({max_write})")
    _no_overlap(c, list(entries.values()), window, shared)
    return RegisterMap(name=name, source=file, map_version=map_version, byte_order=byte_order, word_order=word_order,
                       shared_tables=shared, max_read_registers=max_read, max_write_registers=max_write,
                       entries=MappingProxyType(entries), window=window, channels=MappingProxyType(channels))


def _window(c: _Checker, w: Mapping[str, Any]) -> Window:
    address = c.int_(w, "address", "window.address", 0, 0xFFFF)
    registers = c.int_(w, "registers", "window.registers", 2, 0x10000 - address)
    table = c.choice(w, "table", "window.table", TABLES)
    analog_type = c.choice(w, "analog_type", "window.analog_type", ("f32",), "f32")
    digital_id = c.int_(w, "digital_id", "window.digital_id", 1, 16)
    bits_doc = w.get("digital_bits", {"enc_a": 0, "enc_b": 1, "hall": 2})
    if not isinstance(bits_doc, dict):
        raise c.fail("window.digital_bits", "must be a table (enc_a, enc_b, hall)")
    used = 0
    bits: dict[str, int] = {}
    for fname, width in DIGITAL_FIELDS.items():
        b = c.int_(bits_doc, fname, f"window.digital_bits.{fname}", 0, 16 - width)
        span = ((1 << width) - 1) << b
        if used & span:
            raise c.fail(f"window.digital_bits.{fname}", f"bit {b} overlaps another field")
        used |= span
        bits[fname] = b
    for k in bits_doc:
        if k not in DIGITAL_FIELDS:
            raise c.fail(f"window.digital_bits.{k}", f"unknown key; known: {', '.join(DIGITAL_FIELDS)}")
    return Window(address, registers, table, analog_type, digital_id, MappingProxyType(bits))


def _channels(c: _Checker, doc: Mapping[str, Any], window: Window) -> dict[str, int]:
    seen: dict[int, str] = {window.digital_id: "window.digital_id"}
    out: dict[str, int] = {}
    for name, _ in doc.items():
        cid = c.int_(doc, name, f"channels.{name}", 1, 16)
        if cid in seen:
            raise c.fail(f"channels.{name}", f"id {cid} is also {seen[cid]}")
        seen[cid] = f"channels.{name}"
        out[name] = cid
    for needed in ("torque", "iq_ref"):
        if needed not in out:
            raise c.fail(f"channels.{needed}", "missing: every capture needs it")
    return out


def _entry(c: _Checker, role: Role, t: Any, where: str) -> Entry:
    if not isinstance(t, dict):
        raise c.fail(where, "must be a table")
    for k in t:
        if k not in _ENTRY_KEYS:
            raise c.fail(f"{where}.{k}", f"unknown key; known: {', '.join(_ENTRY_KEYS)}")
    address = c.int_(t, "address", f"{where}.address", 0, 0xFFFF)
    type_ = c.choice(t, "type", f"{where}.type", rc.TYPES)
    if role.text != (type_ == "str"):
        raise c.fail(f"{where}.type", "must be str (text)" if role.text else "str is only for text registers")
    if type_ == "str":
        count = c.int_(t, "count", f"{where}.count", 1, 64)
    elif "count" in t:
        raise c.fail(f"{where}.count", f"only for str; {type_} takes {rc.TYPE_REGS[type_]} register(s)")
    else:
        count = rc.TYPE_REGS[type_]
    if address + count > 0x10000:
        raise c.fail(f"{where}.address", f"{count} registers from {address} run past 65535")
    table = c.choice(t, "table", f"{where}.table", TABLES)
    if role.writable and table != "holding":
        raise c.fail(f"{where}.table",
                     "the client writes this register: it must be a holding register (input registers are read-only)")
    coded = role.codes is not None or role.bits is not None
    if coded and type_ not in rc.INTEGER_TYPES:
        raise c.fail(f"{where}.type", f"{type_} cannot hold codes or bits; use an integer type")
    for k in ("scale", "offset", "invalid"):
        if k in t and (coded or type_ == "str"):
            raise c.fail(f"{where}.{k}", "only for numeric values (not codes, bits or text)")
    scale = c.number(t, "scale", f"{where}.scale", 1.0)
    if scale == 0.0:
        raise c.fail(f"{where}.scale", "must not be 0")
    offset = c.number(t, "offset", f"{where}.offset", 0.0)
    if "unit" in t and t["unit"] != role.unit:
        raise c.fail(f"{where}.unit", f"{t['unit']!r}: this register's value is in {role.unit or 'no unit'!r}; "
                                      "give the raw unit's conversion as scale and offset")
    invalid = None
    if "invalid" in t:
        if type_ not in rc.INTEGER_TYPES:
            raise c.fail(f"{where}.invalid", f"only for integer types; an {type_} reports NaN itself")
        invalid = c.int_(t, "invalid", f"{where}.invalid", *rc.RANGES[type_])
    codes = _codes(c, role, t.get("codes"), type_, f"{where}.codes") if "codes" in t else {}
    bits = _bits(c, role, t.get("bits"), type_, f"{where}.bits") if "bits" in t else {}
    meaning = t.get("meaning", "")
    if not isinstance(meaning, str):
        raise c.fail(f"{where}.meaning", "must be a string")
    return Entry(role, address, count, type_, table, scale, offset, MappingProxyType(codes), MappingProxyType(bits),
                 invalid, meaning)


def _codes(c: _Checker, role: Role, doc: Any, type_: str, where: str) -> dict[int, int]:
    if role.codes is None:
        raise c.fail(where, "this register carries no codes")
    if not isinstance(doc, dict):
        raise c.fail(where, "must be a table of NAME = raw value")
    names = {m.name.lower(): int(m) for m in role.codes}
    out: dict[int, int] = {}
    for k in doc:
        if k not in names:
            raise c.fail(f"{where}.{k}", f"unknown code; known: {', '.join(names)}")
    for k, semantic in names.items():
        raw = c.int_(doc, k, f"{where}.{k}", *rc.RANGES[type_])
        if raw in out.values():
            raise c.fail(f"{where}.{k}", f"raw value {raw} is also another code")
        out[semantic] = raw
    return out


def _bits(c: _Checker, role: Role, doc: Any, type_: str, where: str) -> dict[int, int]:
    if role.bits is None:
        raise c.fail(where, "this register carries no bits")
    if not isinstance(doc, dict):
        raise c.fail(where, "must be a table of NAME = bit number")
    flags = {m.name.lower(): int(m) for m in role.bits if m.name and bin(int(m)).count("1") == 1}
    width = 16 * rc.TYPE_REGS[type_]
    out: dict[int, int] = {}
    for k in doc:
        if k not in flags:
            raise c.fail(f"{where}.{k}", f"unknown bit; known: {', '.join(flags)}")
    for k, flag in flags.items():
        bit = c.int_(doc, k, f"{where}.{k}", 0, width - 1)
        if bit in out.values():
            raise c.fail(f"{where}.{k}", f"bit {bit} is also another flag")
        out[flag] = bit
    return out


def _no_overlap(c: _Checker, entries: list[Entry], window: Window, shared: bool) -> None:
    # Two values on one register would alias each other; the window is a span too.
    spans = [(e.table, e.address, e.end, f"registers.{e.name}") for e in entries]
    spans.append((window.table, window.address, window.end, "window"))
    if shared:
        spans = [("shared", a, b, n) for _t, a, b, n in spans]
    spans.sort()
    for (t0, _a0, e0, n0), (t1, a1, _e1, n1) in itertools.pairwise(spans):
        if t0 == t1 and a1 < e0:
            raise c.fail(f"{n1}.address" if n1 != "window" else "window.address", f"overlaps {n0}")


if __name__ == "__main__":
    # python -m eol_cal.dyno.mapfile [NAME|FILE]: the map's tables as docs/dyno.md embeds them
    import sys

    print(load_register_map(sys.argv[1] if len(sys.argv) > 1 else None).markdown_table(), end="")
