"""A dyno's register map as one typed object, shared by the client and the simulator.

Loaded from a map file by :func:`eol_cal.dyno.mapfile.load_register_map` (format:
``docs/dyno.md``, "Writing a register map"). It places every role of
:mod:`eol_cal.dyno.registers` (address, holding or input table, type, scaling, raw codes) and the
capture window, and encodes and decodes values: the client and the simulator speak roles and
physical or semantic values (rpm, N*m, ``DriveState.AT_SPEED``) and never an address.

Scaling: ``physical = raw * scale + offset``. A raw value equal to an entry's ``invalid`` reads
as NaN (a transducer that reports no measurement).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from eol_cal.capture.data import CANONICAL_CHANNELS
from eol_cal.dyno import regcodec as rc
from eol_cal.dyno.registers import GROUPS, Role, channel_bit, pack_digital, unpack_digital

Value = float | int | str
#: Modbus function code that reads each table
READ_FC: Mapping[str, int] = MappingProxyType({"holding": 3, "input": 4})


@dataclass(frozen=True)
class Entry:
    """Where and how one role lives on a dyno.

    Attributes
    ----------
    role : Role
        What the register means (name, group, physical unit).
    address : int
        First register (0-based PDU address).
    count : int
        Registers occupied.
    type : str
        ``u16``, ``i16``, ``u32``, ``i32``, ``f32`` or ``str``.
    table : str
        ``holding`` (FC 3 read, FC 6/16 write) or ``input`` (FC 4, read-only).
    scale, offset : float
        ``physical = raw * scale + offset``.
    codes : mapping
        Semantic value (the role's enum) -> raw value; empty: raw = semantic.
    bits : mapping
        Semantic flag value -> raw bit number; empty: the same bit.
    invalid : int or None
        Raw value that means "no valid measurement" (decodes to NaN).
    meaning : str
        The map's own note on the register (the role's meaning when the map gives none).
    """

    role: Role
    address: int
    count: int
    type: str
    table: str
    scale: float = 1.0
    offset: float = 0.0
    codes: Mapping[int, int] = field(default_factory=dict)
    bits: Mapping[int, int] = field(default_factory=dict)
    invalid: int | None = None
    meaning: str = ""

    @property
    def name(self) -> str:
        return self.role.name

    @property
    def end(self) -> int:
        return self.address + self.count


@dataclass(frozen=True)
class Window:
    """The capture window: one page of a channel's samples.

    Attributes
    ----------
    address, registers : int
        First register and size of the page (registers).
    table : str
        ``holding`` or ``input``.
    analog_type : str
        Value type of one analog sample (``f32``).
    digital_id : int
        Channel id of the packed digital channel.
    digital_bits : mapping
        Bit of ``enc_a``, ``enc_b`` and the lowest bit of the 3-bit ``hall`` in a digital sample.
    """

    address: int
    registers: int
    table: str
    analog_type: str
    digital_id: int
    digital_bits: Mapping[str, int]

    @property
    def end(self) -> int:
        return self.address + self.registers


@dataclass(frozen=True)
class RegisterMap:
    """A dyno's register map (see the module doc); build it with :func:`eol_cal.dyno.mapfile.load_register_map`."""

    name: str
    source: str
    map_version: int | None
    byte_order: str
    word_order: str
    shared_tables: bool
    max_read_registers: int
    max_write_registers: int
    entries: Mapping[str, Entry]
    window: Window
    channels: Mapping[str, int]  # analog channel name -> channel id

    # ------------------------------------------------------------------ lookup
    def __getitem__(self, name: str) -> Entry:
        return self.entries[name]

    def __contains__(self, name: object) -> bool:
        return name in self.entries

    @property
    def analog_channels(self) -> Mapping[int, str]:
        """Channel id -> canonical channel name of every analog channel."""
        return MappingProxyType({cid: name for name, cid in self.channels.items()})

    def group(self, group: str) -> tuple[str, ...]:
        """Names of the placed registers of ``group``, by address."""
        return tuple(e.name for e in sorted(self.entries.values(), key=lambda e: (e.table, e.address))
                     if e.role.group == group)

    def channel_mask(self, ids: Sequence[int]) -> int:
        mask = 0
        for cid in ids:
            mask |= channel_bit(cid)
        return mask

    def samples_per_page(self, channel_id: int) -> int:
        return self.window.registers // self.regs_per_sample(channel_id)

    def regs_per_sample(self, channel_id: int) -> int:
        return 1 if channel_id == self.window.digital_id else rc.TYPE_REGS[self.window.analog_type]

    # ------------------------------------------------------------------ values
    def encode(self, name: str, value: Value) -> list[int]:
        """Register words of one physical or semantic value of register ``name``.

        Raises ValueError for a value the map cannot carry (out of range, no code, not finite).
        """
        e = self.entries[name]
        if e.type == "str":
            try:
                return rc.text_to_words(str(value), e.count, self.byte_order)
            except UnicodeEncodeError:
                raise ValueError(f"{name}: {value!r} is not ASCII") from None
        raw = self._raw(e, value)
        return rc.value_words(raw, e.type, self.byte_order, self.word_order)

    def _raw(self, e: Entry, value: Value) -> float | int:
        if e.role.codes is not None:
            v = int(value)
            if e.codes:
                if v not in e.codes:
                    raise ValueError(f"{e.name}: {value} has no code in the register map")
                return self._check_int(e, e.codes[v], value)
            return self._check_int(e, v, value)
        if e.role.bits is not None:
            v = int(value)
            if not e.bits:
                return self._check_int(e, v, value)
            raw = 0
            for flag, bit in e.bits.items():
                if v & flag:
                    raw |= 1 << bit
            if v & ~sum(e.bits):
                raise ValueError(f"{e.name}: bits 0x{v & ~sum(e.bits):x} have no place in the register map")
            return self._check_int(e, raw, value)
        x = float(value)
        if not math.isfinite(x):
            if e.invalid is not None:
                return e.invalid
            if e.type == "f32":
                return x
            raise ValueError(f"{e.name}: {value} is not finite")
        raw_f = (x - e.offset) / e.scale
        if e.type == "f32":
            return raw_f
        return self._check_int(e, int(round(raw_f)), value)

    @staticmethod
    def _check_int(e: Entry, raw: int, value: Value) -> int:
        lo, hi = rc.RANGES[e.type]
        if not lo <= raw <= hi:
            raise ValueError(f"{e.name}: {value} out of {e.type} range")
        return raw

    def decode(self, name: str, words: Sequence[int]) -> Value:
        """The physical or semantic value of register ``name`` from its words.

        Raises ValueError for a raw code the map does not list.
        """
        e = self.entries[name]
        if len(words) != e.count:
            raise ValueError(f"{name}: expected {e.count} registers, got {len(words)}")
        if e.type == "str":
            return rc.words_to_text(list(words), self.byte_order)
        raw = rc.words_value(words, e.type, self.byte_order, self.word_order)
        if e.type in rc.INTEGER_TYPES and e.invalid is not None and raw == e.invalid:
            return math.nan
        if e.role.codes is not None and e.codes:
            for semantic, code in e.codes.items():
                if code == raw:
                    return semantic
            raise ValueError(f"{name}: raw value {raw} is not one of the map's codes")
        if e.role.bits is not None and e.bits:
            return sum(flag for flag, bit in e.bits.items() if int(raw) >> bit & 1)  # an integer type (mapfile)
        if e.type in rc.INTEGER_TYPES and e.scale == 1.0 and e.offset == 0.0:
            return raw
        return float(raw) * e.scale + e.offset

    def unpack(self, address: int, words: Sequence[int], names: Sequence[str]) -> dict[str, Value]:
        """Decode registers ``names`` out of one block read that started at ``address``."""
        out: dict[str, Value] = {}
        for n in names:
            e = self.entries[n]
            i = e.address - address
            out[n] = self.decode(n, list(words[i: i + e.count]))
        return out

    # ------------------------------------------------------------------ requests
    def read_runs(self, names: Sequence[str]) -> list[tuple[str, int, int, tuple[str, ...]]]:
        """The fewest block reads covering registers ``names``: ``(table, address, count, names)``.

        Only registers that touch join one read (a gap may be an illegal address), up to
        ``max_read_registers`` each.
        """
        return self._runs([self.entries[n] for n in names], self.max_read_registers)

    def write_runs(self, values: Mapping[str, Value]) -> list[tuple[int, list[int], tuple[str, ...]]]:
        """Writes of ``values`` (name -> value) as FC 16 requests: ``(address, words, names)``."""
        out = []
        for _table, address, _count, names in self._runs([self.entries[n] for n in values], self.max_write_registers):
            words = [w for n in names for w in self.encode(n, values[n])]
            out.append((address, words, names))
        return out

    @staticmethod
    def _runs(entries: list[Entry], limit: int) -> list[tuple[str, int, int, tuple[str, ...]]]:
        runs: list[tuple[str, int, int, tuple[str, ...]]] = []
        for e in sorted(entries, key=lambda e: (e.table, e.address)):
            if runs:
                table, address, count, names = runs[-1]
                if table == e.table and address + count == e.address and count + e.count <= limit:
                    runs[-1] = (table, address, count + e.count, names + (e.name,))
                    continue
            runs.append((e.table, e.address, e.count, (e.name,)))
        return runs

    def page_blocks(self, n_regs: int) -> list[tuple[int, int]]:
        """``(address, count)`` reads of the first ``n_regs`` registers of the window."""
        step = self.max_read_registers
        return [(self.window.address + a, min(step, n_regs - a)) for a in range(0, n_regs, step)]

    # ------------------------------------------------------------------ samples
    def analog_to_words(self, values: np.ndarray) -> np.ndarray:
        """Samples (physical) -> window words (uint16)."""
        return rc.to_words(np.asarray(values), self.window.analog_type, self.byte_order, self.word_order)

    def words_to_analog(self, words: np.ndarray) -> np.ndarray:
        """Window words -> samples (float64)."""
        return rc.from_words(words, self.window.analog_type, self.byte_order, self.word_order).astype(np.float64)

    def pack_digital(self, enc_a: np.ndarray, enc_b: np.ndarray | None, hall: np.ndarray) -> np.ndarray:
        """Digital levels -> one window word per sample (before the byte order)."""
        words = pack_digital(enc_a, enc_b, hall, self.window.digital_bits)
        return rc.to_words(words, "u16", self.byte_order, self.word_order)

    def unpack_digital(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Window words of the digital channel -> (enc_a, enc_b, hall)."""
        return unpack_digital(rc.from_words(words, "u16", self.byte_order, self.word_order), self.window.digital_bits)

    # ------------------------------------------------------------------ docs
    def markdown_table(self) -> str:
        """The map as Markdown tables, one per group, and the channel table (docs/dyno.md embeds
        the default map's)."""
        titles = {"identification": "Identification (read-only)", "control": "Control (read/write)",
                  "status": "Status (read-only)", "transfer": "Capture data transfer",
                  "sim": "Simulator only (fault injection)"}
        lines: list[str] = []
        for group in GROUPS:
            names = self.group(group)
            if not names and group != "transfer":
                continue
            lines += [f"### {titles[group]}", "",
                      "| address | table | name | type | regs | unit | scaling | meaning |",
                      "|---|---|---|---|---|---|---|---|"]
            for n in names:
                lines.append(self._row(self.entries[n]))
            if group == "transfer":
                w = self.window
                lines.append(f"| {w.address}-{w.end - 1} | {w.table} | window | {w.analog_type} / u16 | {w.registers} | | "
                             f"| capture window page: one {w.analog_type} per analog sample, one u16 per digital sample; "
                             f"read in blocks of <= {self.max_read_registers} |")
            lines.append("")
        lines += ["### Capture channels (`buf_channel`)", "", "| id | channel | window type | unit |", "|---|---|---|---|"]
        for cid, name in sorted(self.analog_channels.items()):
            lines.append(f"| {cid} | `{name}` | {self.window.analog_type} | {CANONICAL_CHANNELS[name]} |")
        bits = self.window.digital_bits
        lines.append(f"| {self.window.digital_id} | `enc_a` bit {bits['enc_a']}, `enc_b` bit {bits['enc_b']}, "
                     f"`hall` bits {bits['hall']}-{bits['hall'] + 2} | u16 | 1 |")
        return "\n".join(lines) + "\n"

    def _row(self, e: Entry) -> str:
        addr = f"{e.address}" if e.count == 1 else f"{e.address}-{e.end - 1}"
        scaling = "" if (e.scale, e.offset) == (1.0, 0.0) else f"x {e.scale:g}" + (f" + {e.offset:g}" if e.offset else "")
        meaning = e.meaning or e.role.meaning
        if e.role.codes is not None:
            meaning += ": " + ", ".join(f"{m.name.lower()} = {e.codes.get(int(m), int(m))}" for m in e.role.codes)
        if e.role.bits is not None:
            flags: list[str] = []
            for m in e.role.bits:  # the named single-bit flags (a Flag member's name is None for an unnamed combination)
                if m.name and bin(int(m)).count("1") == 1:
                    flags.append(f"bit {e.bits.get(int(m), int(m).bit_length() - 1)} {m.name.lower()}")
            meaning += ": " + ", ".join(flags)
        if e.invalid is not None:
            meaning += f"; raw {e.invalid} = no measurement (NaN)"
        return f"| {addr} | {e.table} | `{e.name}` | {e.type} | {e.count} | {e.role.unit} | {scaling} | {meaning} |"
