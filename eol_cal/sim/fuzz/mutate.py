"""Hostile inputs: seeded mutations of valid files the tool writes itself (see :mod:`eol_cal.sim.fuzz`)."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import struct
import tempfile
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eol_cal.capture.data import Capture
from eol_cal.capture.io import write_capture
from eol_cal.capture.synthetic import synthetic_capture
from eol_cal.firmware import block as B
from eol_cal.firmware.block_layout import FIELDS_BY_VERSION
from eol_cal.firmware.example import example_block
from eol_cal.firmware.mech_params import make_mech_tables, unused_mech
from eol_cal.sim import FIXTURES

#: ``block2`` and ``fitjson2``: a layout-2 block and a fit result with its ``mech`` object (contract
#: revision 1.2), mutated the same ways plus their mechanical fields
KINDS = ("csv", "mdf4", "block", "fitjson", "block2", "fitjson2")

#: bound on every child's address space (bytes): a decoder that believes a hostile size dies of it
CHILD_MEMORY_BYTES = 2 * 1024**3

_HOSTILE_CELLS = ("nan", "inf", "-inf", "1e308", "-1e308", "1e999", "", "abc", "0x10", "1,5", "--1", "1e-320",
                  "3e38", "9" * 400)
_HOSTILE_UNITS = ("degC", "kg", "V", "", "[", "m/s", "1/0", "rpm**rpm", "N*m*" * 50, "degF", "A/s", "\u00b5A")
_HOSTILE_META = {"poles": ("0", "-6", "7", "1e9", "x", "6.5", "99999999999999999999"),
                 "encoder_ppr": ("0", "-1", "1e12", "y", "64.0"),
                 "kt": ("0", "-1", "nan", "inf", "1e308"),
                 "serial": ("", "\x00", "x" * 5000)}
_HOSTILE_F32 = (float("nan"), float("inf"), float("-inf"), 3e38, -3e38, 0.0, -1.0, 1e-45, 1e30)
_HOSTILE_JSON: tuple[object, ...] = (1e30, -5, True, False, "0.0006", None, [], {}, "NaN", 10**30, -1e-300, "")
_HOSTILE_JSON_TEXT = ("NaN", "Infinity", "-Infinity", "1e400", "-1e400", "9" * 5000, "1" + "0" * 100000)


@dataclass
class Case:
    """One hostile input: its files (name -> bytes) and how it was made."""

    kind: str
    name: str
    how: str
    data: bytes



# --------------------------------------------------------------------------------------------
# valid base files


def base_files(fit_result: Path | None = None) -> BaseFiles:
    """The valid files every mutation starts from: kind (:data:`KINDS`) -> bytes, written by the tool
    itself, each when first read (:class:`BaseFiles`)."""
    return BaseFiles(fit_result or FIXTURES / "fit_paper.json")


class BaseFiles(Mapping[str, bytes]):
    """:func:`base_files`: each kind's file made when first read, then kept. The MDF4 one imports
    asammdf (~1 s), and a test suite collects the scenarios, which read the CSV alone, in every worker."""

    def __init__(self, fit_result: Path) -> None:
        self._fit_result = fit_result
        self._made: dict[str, bytes] = {}

    def __getitem__(self, kind: str) -> bytes:
        if kind not in KINDS:
            raise KeyError(kind)
        if kind not in self._made:
            self._made[kind] = self._make(kind)
        return self._made[kind]

    def __iter__(self) -> Iterator[str]:
        return iter(KINDS)

    def __len__(self) -> int:
        return len(KINDS)

    @functools.cached_property
    def _capture(self) -> Capture:
        return synthetic_capture(rpm=60.0, seconds=0.5, fs=5000.0, serial="F-0001", seed=7)

    def _make(self, kind: str) -> bytes:
        if kind in ("csv", "mdf4"):
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / f"base{SUFFIX[kind]}"
                write_capture(self._capture, path)
                return path.read_bytes()
        if kind == "block":
            return example_block(serial="F-0001")
        if kind == "block2":
            return layout2_block(self["block"])
        if kind == "fitjson":
            return self._fit_result.read_bytes()
        return fit_result_with_mech(self["fitjson"])  # fitjson2


def layout2_block(base: bytes) -> bytes:
    """``base`` as a layout-2 block with a measured fingerprint and mechanical orders."""

    blk = B.unpack(base)
    c, ph, zeros = (0.004, 0.001, 0.0005), (0.3, -1.0, 2.0), (0.0, 0.0, 0.0)
    tc, tp = make_mech_tables(c, ph, zeros, zeros, blk.kt)
    j = np.arange(2 * blk.encoder_ppr)
    mech = unused_mech(blk.encoder_ppr).replace(
        fp_dirs=3, grid_phase=0.7, mech_c=c, mech_phase_c=ph, mech_table_const=tc, mech_table_per_amp=tp,
        fingerprint=(0.01 * np.sin(2 * np.pi * j / j.size)).astype(np.float32))
    return B.pack(dataclasses.replace(blk, mech=mech, layout_version=None,
                                      flags=blk.flags | B.FLAG_MECH_COMP_ENABLE))


def fit_result_with_mech(base: bytes) -> bytes:
    """``base`` (a fit result) with a ``mech`` object of status ok on every motor."""
    doc = json.loads(base)
    for m in doc["motors"]:
        n = 2 * int(m["encoder_ppr"])
        m["mech"] = {
            "status": "ok", "reasons": [], "dirs": 3, "grid_phase": 0.7,
            "margin": {"predicted": 0.6, "score": 0.9, "threshold": 0.25, "ref_rpm": 60.0},
            "orders": [{"order": h, "c": {"value": c, "ci95": 1e-4}, "phase_c": {"value": p, "ci95": 0.05}}
                       for h, c, p in ((1, 0.004, 0.3), (2, 0.001, -1.0), (3, 0.0005, 2.0))],
            "windows": [0], "fingerprint": [round(0.01 * math.sin(2 * math.pi * i / n), 6) for i in range(n)],
            "sigma": [1e-3] * n,
        }
    return json.dumps(doc).encode()


# --------------------------------------------------------------------------------------------
# byte-level mutations


def _bitflip(rng: np.random.Generator, data: bytes, lo: int = 0, hi: int | None = None) -> tuple[bytes, str]:
    buf = bytearray(data)
    hi = len(buf) if hi is None else hi
    flips = int(rng.integers(1, 9))
    for _ in range(flips):
        pos = int(rng.integers(lo, hi))
        buf[pos] ^= 1 << int(rng.integers(0, 8))
    return bytes(buf), f"{flips} bit flips in bytes {lo}..{hi}"


def _truncate(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    n = int(rng.integers(0, len(data)))
    return data[:n], f"truncated to {n} of {len(data)} bytes"


def _splice(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    a, b = sorted(int(x) for x in rng.integers(0, len(data), 2))
    at = int(rng.integers(0, len(data)))
    return data[:at] + data[a:b] + data[at:], f"bytes {a}..{b} copied in at {at}"


# --------------------------------------------------------------------------------------------
# CSV


def _csv_cell(rng: np.random.Generator, text: str) -> tuple[str, str]:
    lines = text.split("\n")
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    row = int(rng.integers(first + 1, len(lines) - 1))
    cells = lines[row].split(",")
    col = int(rng.integers(0, len(cells)))
    cell = str(rng.choice(_HOSTILE_CELLS))
    cells[col] = cell
    lines[row] = ",".join(cells)
    return "\n".join(lines), f"cell row {row} column {col} = {cell[:20]!r}"


def _csv_unit(rng: np.random.Generator, text: str) -> tuple[str, str]:
    lines = text.split("\n")
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    cells = lines[first].split(",")
    col = int(rng.integers(0, len(cells)))
    name = cells[col].split("[")[0].strip()
    unit = str(rng.choice(_HOSTILE_UNITS))
    cells[col] = f"{name} [{unit}]"
    lines[first] = ",".join(cells)
    return "\n".join(lines), f"unit of {name} = {unit[:20]!r}"


def _csv_meta(rng: np.random.Generator, text: str) -> tuple[str, str]:
    key = str(rng.choice(list(_HOSTILE_META)))
    value = str(rng.choice(_HOSTILE_META[key]))
    lines = [line for line in text.split("\n") if not line.startswith(f"# {key}:")]
    return "\n".join([f"# {key}: {value}", *lines]), f"metadata {key} = {value[:20]!r}"


def _csv_wide(rng: np.random.Generator, text: str) -> tuple[str, str]:
    n = int(rng.choice((1000, 20000, 100000)))
    header = ",".join(f"c{i} [A]" for i in range(n))
    return f"# serial: W\n{header}\n" + ",".join("0" for _ in range(n)) + "\n", f"{n}-column header"


def _csv_rows(rng: np.random.Generator, text: str) -> tuple[str, str]:
    lines = text.split("\n")
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    keep = int(rng.choice((0, 1, 2, 3)))
    return "\n".join(lines[: first + 1 + keep]) + "\n", f"{keep} data rows"


def _csv_bytes(rng: np.random.Generator, text: str) -> tuple[bytes, str]:
    raw = text.encode()
    at = int(rng.integers(0, len(raw)))
    junk = bytes(rng.choice([0xFF, 0xFE, 0x00, 0xC3, 0x80], int(rng.integers(1, 4))).tolist())
    return raw[:at] + junk + raw[at:], f"bytes {junk!r} inserted at {at}"


def mutate_csv(rng: np.random.Generator, base: bytes) -> tuple[bytes, str]:
    """One hostile CSV from a valid one."""
    text = base.decode()
    op = int(rng.integers(0, 9))
    if op == 0:
        return _bitflip(rng, base)
    if op == 1:
        return _truncate(rng, base)
    if op == 2:
        return _splice(rng, base)
    if op == 7:
        return _csv_bytes(rng, text)
    mutated, how = (_csv_cell, _csv_unit, _csv_meta, _csv_wide, _csv_rows, _csv_cell)[op - 3](rng, text)
    return mutated.encode(), how


# --------------------------------------------------------------------------------------------
# MDF4


def mdf4_blocks(data: bytes) -> dict[int, tuple[bytes, int, tuple[int, ...]]]:
    """Every block reachable from the header: offset -> (id, length, links) (for mutations only)."""
    blocks: dict[int, tuple[bytes, int, tuple[int, ...]]] = {}
    stack = [64]
    while stack:
        offset = stack.pop()
        if offset in blocks or offset + 24 > len(data):
            continue
        block_id, _, length, count = struct.unpack_from("<4sIQQ", data, offset)
        if count > 10000 or offset + 24 + 8 * count > len(data):
            continue
        links = struct.unpack_from(f"<{count}Q", data, offset + 24)
        blocks[offset] = (block_id, length, links)
        stack.extend(link for link in links if link)
    return blocks


def _patch_u64(data: bytes, at: int, value: int) -> bytes:
    buf = bytearray(data)
    struct.pack_into("<Q", buf, at, value & 0xFFFFFFFFFFFFFFFF)
    return bytes(buf)


def mutate_mdf4(rng: np.random.Generator, base: bytes) -> tuple[bytes, str]:
    """One hostile MDF4 file from a valid one."""
    blocks = mdf4_blocks(base)
    offsets = sorted(blocks)
    op = int(rng.integers(0, 10))
    if op == 0:
        return _bitflip(rng, base)
    if op == 1:
        dz = [o for o in offsets if blocks[o][0] == b"##DZ"]
        if dz:
            o = dz[0]
            return _bitflip(rng, base, o + 48, o + blocks[o][1])
        return _bitflip(rng, base)
    if op == 2:
        return _truncate(rng, base)
    if op == 3:  # a link to its own block, outside the file, to another block, or to garbage
        with_links = [o for o in offsets if blocks[o][2]]
        o = int(rng.choice(with_links))
        k = int(rng.integers(0, len(blocks[o][2])))
        target = int(rng.choice([o, len(base) + 8, 2**63, int(rng.choice(offsets)), int(rng.integers(0, len(base))),
                                 blocks[o][2][k] + 8, 64]))
        return _patch_u64(base, o + 24 + 8 * k, target), f"link {k} of {blocks[o][0].decode()} at {o} -> {target}"
    if op == 4:  # block length
        o = int(rng.choice(offsets))
        value = int(rng.choice([0, 1, 23, 24, 2**31, 2**62, 2**64 - 1, blocks[o][1] + 8, blocks[o][1] - 8,
                                len(base)]))
        return _patch_u64(base, o + 8, value), f"length of {blocks[o][0].decode()} at {o} = {value}"
    if op == 5:  # link count
        o = int(rng.choice(offsets))
        value = int(rng.choice([0, 1, 2**20, 2**40, 2**64 - 1, len(blocks[o][2]) + 1]))
        return _patch_u64(base, o + 16, value), f"link count of {blocks[o][0].decode()} at {o} = {value}"
    if op == 6:  # compressed data sizes
        dz = [o for o in offsets if blocks[o][0] == b"##DZ"]
        if not dz:
            return _bitflip(rng, base)
        o = dz[0]
        field_at, label = [(o + 32, "original length"), (o + 40, "compressed length")][int(rng.integers(0, 2))]
        value = int(rng.choice([0, 1, 2**31, 2**62, 2**64 - 1, 7]))
        return _patch_u64(base, field_at, value), f"DZ {label} = {value}"
    if op == 7:  # cycle count, record size
        cg = [o for o in offsets if blocks[o][0] == b"##CG"]
        o = int(rng.choice(cg))
        data_at = o + 24 + 8 * len(blocks[o][2])
        value = int(rng.choice([0, 1, 2, 2**31, 2**62, 2**64 - 1]))
        return _patch_u64(base, data_at + 8, value), f"CG cycle count = {value}"
    if op == 8:  # channel byte offset / bit count / data type
        cn = [o for o in offsets if blocks[o][0] == b"##CN"]
        o = int(rng.choice(cn))
        data_at = o + 24 + 8 * len(blocks[o][2])
        buf = bytearray(base)
        which = int(rng.integers(0, 3))
        if which == 0:
            value = int(rng.choice([2**31, 2**32 - 1, 1000, 9]))
            struct.pack_into("<I", buf, data_at + 4, value)
            return bytes(buf), f"CN byte offset = {value}"
        if which == 1:
            value = int(rng.choice([0, 65, 2**31, 2**32 - 1, 1000]))
            struct.pack_into("<I", buf, data_at + 8, value)
            return bytes(buf), f"CN bit count = {value}"
        value = int(rng.choice([6, 7, 9, 13, 15, 200, 255]))
        buf[data_at + 2] = value
        return bytes(buf), f"CN data type = {value}"
    return _splice(rng, base)


# --------------------------------------------------------------------------------------------
# parameter blocks


#: layout 2's float fields (contract revision 1.2)
_MECH_F32 = ("grid_phase", "id_min_score", "id_margin", "id_frac_tol", "mech_c", "mech_phase_c", "mech_k",
             "mech_phase_k", "mech_table_const", "mech_table_per_amp", "fingerprint")


def mutate_block(rng: np.random.Generator, base: bytes) -> tuple[bytes, str]:
    """One hostile parameter block; most keep a right CRC so that only a sanity check refuses them."""

    op = int(rng.integers(0, 5))
    if op == 0:
        return _bitflip(rng, base)
    if op == 1:
        return _truncate(rng, base)
    head = B.unpack(base)
    n, v = head.table_len, head.layout_version
    assert v is not None  # a ParamBlock's layout is never None once made (__post_init__ sets the default)
    buf = bytearray(base)
    if op == 2:  # a float field
        floats = ["tick_hz", "kt", "c6", "phase_c6", "k6", "phase_k6", "lead_s", "iqc_limit", "hall_angle",
                  "table_const", "table_per_amp"]
        name = str(rng.choice(floats + (list(_MECH_F32) if v == 2 else [])))
        value = float(rng.choice(_HOSTILE_F32))
        count = B.field_count(name, n, v)
        at = B.field_offset(name, n, v) + 4 * int(rng.integers(0, count))
        with np.errstate(over="ignore"):
            struct.pack_into("<f", buf, at, np.float32(value))
        how = f"{name} = {value}"
    elif op == 3:  # an integer field
        ints = ["poles", "encoder_ppr", "table_len", "block_bytes", "flags", "sequence"]
        name = str(rng.choice(ints + (["layout_version", "mech_table_len", "fp_len", "fp_dirs", "reserved2"]
                                      if v == 2 else [])))
        size = {"u16": 2, "u32": 4}[FIELDS_BY_VERSION[v][name]["type"]]
        value = int(rng.choice([0, 1, 2, 3, 8, 7, 0xFFFF, 2**31]))
        at = B.field_offset(name, n, v)
        buf[at:at + size] = (value & (256**size - 1)).to_bytes(size, "little")
        how = f"{name} = {value}"
    else:
        return _bitflip(rng, base, 0, B.field_offset("crc32", n, v))
    try:
        return B.with_crc(bytes(buf)), how + " (CRC made right)"
    except Exception:  # noqa: BLE001 - a table_len the CRC cannot be placed for: keep the bytes as they are
        return bytes(buf), how


# --------------------------------------------------------------------------------------------
# fit result JSON


def _leaves(doc: object, path: tuple = ()) -> Iterator[tuple]:
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _leaves(v, (*path, i))
    else:
        yield path


def _set(doc: object, path: tuple, value: object) -> None:
    for k in path[:-1]:
        doc = doc[k]  # type: ignore[index]
    doc[path[-1]] = value  # type: ignore[index]


def mutate_fitjson(rng: np.random.Generator, base: bytes) -> tuple[bytes, str]:
    """One hostile fit result."""
    doc = json.loads(base)
    leaves = [p for p in _leaves(doc) if p and p[0] == "motors"]
    op = int(rng.integers(0, 7))
    if op in (0, 1):  # a value of the wrong type or out of bounds
        path = leaves[int(rng.integers(0, len(leaves)))]
        value = _HOSTILE_JSON[int(rng.integers(0, len(_HOSTILE_JSON)))]
        _set(doc, path, value)
        return json.dumps(doc).encode(), f"{'.'.join(map(str, path))} = {value!r}"
    if op == 2:  # a number as text JSON allows (or Python's json writes)
        path = leaves[int(rng.integers(0, len(leaves)))]
        token = str(rng.choice(_HOSTILE_JSON_TEXT))
        _set(doc, path, "@@TOKEN@@")
        return json.dumps(doc).replace('"@@TOKEN@@"', token).encode(), f"{'.'.join(map(str, path))} = {token[:20]}"
    if op == 3:  # deep nesting
        depth = int(rng.choice((1000, 100000, 1000000)))
        path = leaves[int(rng.integers(0, len(leaves)))]
        _set(doc, path, "@@TOKEN@@")
        return json.dumps(doc).replace('"@@TOKEN@@"', "[" * depth + "]" * depth).encode(), f"nesting depth {depth}"
    if op == 4:
        return _truncate(rng, base)
    if op == 5:
        return _bitflip(rng, base)
    path = leaves[int(rng.integers(0, len(leaves)))]
    parent = doc
    for k in path[:-2]:
        parent = parent[k]
    if isinstance(parent, dict) and path[-2] in parent and isinstance(parent[path[-2]], dict):
        del parent[path[-2]]
        return json.dumps(doc).encode(), f"{'.'.join(map(str, path[:-1]))} removed"
    return _bitflip(rng, base)


MUTATORS: dict[str, Callable[[np.random.Generator, bytes], tuple[bytes, str]]] = {
    "csv": mutate_csv, "mdf4": mutate_mdf4, "block": mutate_block, "fitjson": mutate_fitjson,
    "block2": mutate_block, "fitjson2": mutate_fitjson,
}
SUFFIX = {"csv": ".csv", "mdf4": ".mf4", "block": ".bin", "fitjson": ".json", "block2": ".bin", "fitjson2": ".json"}


def cases(seed: int, per_kind: int, bases: Mapping[str, bytes], kinds: tuple[str, ...] = KINDS) -> list[Case]:
    """``per_kind`` hostile inputs of each kind, the same for the same seed."""
    out = []
    for k, kind in enumerate(kinds):
        rng = np.random.default_rng([seed, k])
        for i in range(per_kind):
            data, how = MUTATORS[kind](rng, bases[kind])
            out.append(Case(kind, f"{kind}-{seed}-{i:04d}{SUFFIX[kind]}", how, data))
    return out


