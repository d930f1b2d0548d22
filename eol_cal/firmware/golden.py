"""Golden vectors for the firmware's unit tests (``docs/firmware-contract.md`` section 4).

``firmware_params/golden/`` holds ``manifest.json`` and one CSV per vector set; floats are
binary32 bit patterns as 8 lower-case hex digits, integers decimal. Sets:

- ``blocks.csv``: valid parameter blocks, every field value and the exact byte image (hex);
- ``block_checks.csv``: images (valid, deliberately broken, erased) and the check routine's status;
- ``compensator.csv``: i_qc for a grid of angle, speed and i_qo over each block of ``blocks.csv``;
- the estimator scenarios, from ``eol_cal.firmware.estimator_golden.vector_sets()``;
- layout 2 (revision 1.2): ``blocks_v2.csv``, ``block_checks_v2.csv``, the identifier's scenarios
  and the mechanical compensation, from ``eol_cal.firmware.mech_golden.vector_sets()``.

Everything is generated from the Python reference; ``check_golden`` regenerates and compares.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import struct
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any
from collections.abc import Sequence

import numpy as np

from eol_cal import __version__
from eol_cal.infra.atomic import atomic_write
from eol_cal.errors import InputError
from eol_cal.firmware import block as B
from eol_cal.firmware import estimator_golden, mech_golden
from eol_cal.firmware.compensator import i_qc, make_tables
from eol_cal.firmware.estimator import NOMINAL_HALL_ANGLE
from eol_cal.firmware.vectors import VectorSet, csv_text, f32hex
from eol_cal.infra.inputs import loads_json, read_text
from eol_cal.domain.motor_params import load_motor
from eol_cal.numerics.wrap import wrap_2pi

GOLDEN_FORMAT = 1
GENERATOR = f"eol_cal.firmware.golden format {GOLDEN_FORMAT}"
FLOAT_ENCODING = "ieee754-binary32-hex"
DEFAULT_DIR = Path("firmware_params") / "golden"

#: Tolerance for targets whose FPU rounds differently (e.g. a fused multiply-add); a host build
#: of the C reference with -ffp-contract=off must match exactly.
COMPENSATOR_TOLERANCE = {"i_qc": {"abs": 1e-3, "unit": "A"}}


_HALL_NOMINAL = NOMINAL_HALL_ANGLE


def golden_blocks() -> list[tuple[str, B.ParamBlock]]:
    """The valid blocks of the golden set: three table lengths, harmonics, clamp limits that bite."""
    motor = load_motor("paper")  # seed paper Table I: P, N_enc, PWM tick, kt = 3P/4 * psi_f
    kt = motor.kt
    specs = [
        # id, N, c6, phase_c6, k6, phase_k6, harmonics, lead_s, iqc_limit, flags, serial, sequence
        ("paper_n256", 256, 0.012, 0.35, 0.0015, -0.6, (), 1.0 / (2 * math.pi * motor.current_bw_hz), 8.0, 3,
         "EPS-0001", 1),
        ("clamp_n16", 16, 0.030, -2.9, 0.0040, 1.2, ((12, 0.004, 0.5, 0.0006, -1.0),), 0.0, 0.25, 1, "EPS-0002-A",
         7),
        ("fine_n1024", 1024, 0.008, 3.0, 0.0021, 2.2,
         ((12, 0.002, -0.4, 0.0004, 0.8), (18, 0.0007, 1.9, 0.0001, -2.5)), 2.5e-4, 3.0,
         B.FLAG_INTERP_ENABLE | B.FLAGS_ESTIMATOR, "MOTOR-1024-XYZ-9",
         0xFFFFFFFE),
    ]
    hall_skewed = tuple(a + math.radians(d) for a, d in zip(_HALL_NOMINAL, (1.5, -0.7, 0.3, -1.9, 0.0, 1.1), strict=True))
    hall_skewed = tuple(float(wrap_2pi(a)) for a in hall_skewed)
    out = []
    for k, (bid, n, c6, pc6, k6, pk6, harm, lead, lim, flags, serial, seq) in enumerate(specs):
        tc, tp = make_tables(c6, pc6, k6, pk6, kt, n, harmonics=harm)
        out.append((bid, B.ParamBlock(
            sequence=seq, flags=flags, serial=serial, calibrated_at=1_767_225_600 + 86_400 * k,
            poles=motor.poles, encoder_ppr=motor.N_enc, tick_hz=motor.f_pwm, kt=kt,
            hall_angle=_HALL_NOMINAL if k != 1 else hall_skewed,
            c6=c6, phase_c6=pc6, k6=k6, phase_k6=pk6, lead_s=lead, iqc_limit=lim,
            table_const=tc, table_per_amp=tp)))
    return out


_BLOCK_COLUMNS = ("id", "sequence", "flags", "serial", "calibrated_at", "poles", "encoder_ppr", "tick_hz",
                  "kt", *(f"hall_angle_{s}" for s in range(1, 7)), "c6", "phase_c6", "k6", "phase_k6",
                  "lead_s", "iqc_limit", "table_len", "block_bytes", "crc32", "image")


def paper_block() -> B.ParamBlock:
    """The example block of ``fixtures/block_paper.bin``: paper motor, N = 256, both flags set."""
    return golden_blocks()[0][1]


def _blocks_set(blocks: Sequence[tuple[str, B.ParamBlock]]) -> VectorSet:
    rows = []
    for bid, b in blocks:
        image = B.pack(b)
        crc = B.check(image).crc_stored
        rows.append([bid, str(b.sequence), str(b.flags), b.serial, str(b.calibrated_at), str(b.poles),
                     str(b.encoder_ppr), f32hex(b.tick_hz), f32hex(b.kt), *(f32hex(a) for a in b.hall_angle),
                     f32hex(b.c6), f32hex(b.phase_c6), f32hex(b.k6), f32hex(b.phase_k6), f32hex(b.lead_s),
                     f32hex(b.iqc_limit), str(b.table_len), str(b.block_bytes), str(crc), image.hex()])
    return VectorSet(_BLOCK_COLUMNS, rows,
                     "valid blocks: field values (floats as binary32 hex, serial as ASCII, crc32 decimal) "
                     "and the exact byte image as hex; the tables are in the image")


def _patch(image: bytes, name: str, value: int, n: int = 0, fix_crc: bool = True) -> bytes:
    buf = bytearray(image)
    fmt = {"u16": "<H", "u32": "<I"}[B.FIELDS[name]["type"]]
    struct.pack_into(fmt, buf, B.field_offset(name, n), value)
    return B.with_crc(bytes(buf)) if fix_crc else bytes(buf)


def check_cases(blocks: Sequence[tuple[str, B.ParamBlock]]) -> list[tuple[str, bytes, int]]:
    """(id, image, expected status) for the check routine: one case per validity rule and more.

    Header faults are made with the CRC recomputed, so each case breaks exactly one rule.
    """
    _, b0 = blocks[0]
    img = B.pack(b0)
    n = b0.table_len
    _, b1 = blocks[1]
    small = B.pack(b1)
    crc_at = B.field_offset("crc32", n)
    flipped_table = bytearray(img)
    flipped_table[B.field_offset("table_per_amp", n) + 5] ^= 0x10
    flipped_crc = bytearray(img)
    flipped_crc[crc_at + 3] ^= 0x80
    V, C, H = B.STATUS_VALID, B.STATUS_CRC_MISMATCH, B.STATUS_HEADER_INVALID
    cases = [(f"valid_{bid}", B.pack(b), V) for bid, b in blocks]
    cases += [
        ("valid_in_erased_bank_tail", small + b"\xff" * 512, V),
        ("valid_reserved_nonzero", _patch(small, "reserved", 0x1234), V),
        ("valid_unknown_flag_bit", _patch(small, "flags", 0x80000001), V),
        ("valid_option_without_interp", _patch(small, "flags", B.FLAG_COMP_ENABLE | B.FLAGS_ESTIMATOR), V),
        ("erased", b"\xff" * 256, H),
        ("all_zero", b"\x00" * 256, H),
        ("header_truncated", small[:60], H),
        ("bad_magic", _patch(small, "magic", 0xEC6B), H),
        ("layout_version_0", _patch(small, "layout_version", 0), H),
        ("layout_version_2", _patch(small, "layout_version", 2), H),
        ("table_len_8", _patch(small, "table_len", 8), H),
        ("table_len_2048", _patch(img + b"\xff" * (8 * 2048), "table_len", 2048), H),
        ("table_len_not_pow2", _patch(img, "table_len", 192), H),
        ("table_len_0", _patch(small, "table_len", 0), H),
        ("block_bytes_mismatch", _patch(small, "block_bytes", B.block_bytes(16) + 8), H),
        ("block_bytes_zero", _patch(small, "block_bytes", 0), H),
        ("sequence_0", _patch(small, "sequence", 0), H),
        ("sequence_erased", _patch(small, "sequence", 0xFFFFFFFF), H),
        ("block_truncated", img[:-2], H),
        ("crc_table_bit_flipped", bytes(flipped_table), C),
        ("crc_field_bit_flipped", bytes(flipped_crc), C),
        ("crc_header_edited", _patch(img, "sequence", 2, fix_crc=False), C),
        ("crc_erased_field", img[:crc_at] + b"\xff" * 4, C),
    ]
    return cases


def _checks_set(blocks: Sequence[tuple[str, B.ParamBlock]]) -> VectorSet:
    rows = []
    for cid, image, status in check_cases(blocks):
        got = B.check(image).status
        if got != status:  # the case list documents intent; the reference must agree with it
            raise AssertionError(f"check case {cid}: reference gives status {got}, case expects {status}")
        rows.append([cid, str(len(image)), str(status), image.hex()])
    return VectorSet(("id", "image_bytes", "status", "image"), rows,
                     "check routine: bank image (hex, may continue past the block) and the expected status "
                     "0 valid, 1 CRC mismatch, 2 header invalid; avail_bytes = image_bytes")


def compensator_inputs(seed: int = 20100) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angle (rad), speed (rad/s) and i_qo (A) grid plus seeded random points, all binary32."""
    two_pi = 2 * math.pi
    thetas = list(np.linspace(-2 * two_pi, 3 * two_pi, 31))
    # exact zero, tiny negatives whose reduction rounds to N, a table node, beyond 2*pi, large
    thetas += [0.0, -0.0, -1e-9, -1e-30, -3e-7, two_pi / 6 / 256 * 3, two_pi, two_pi + 1e-3, 1000.0, -777.7]
    omegas = [-2500.0, -90.0, 0.0, 90.0, 2500.0]
    i_qos = [-60.0, -3.5, 0.0, 3.5, 60.0]
    grid = np.array([(t, w, i) for t in thetas for w in omegas for i in i_qos], dtype=np.float32)
    rng = np.random.default_rng(seed)
    rand = np.stack([rng.uniform(-50, 50, 300), rng.uniform(-3000, 3000, 300), rng.uniform(-80, 80, 300)],
                    axis=1).astype(np.float32)
    allv = np.concatenate([grid, rand])
    return allv[:, 0], allv[:, 1], allv[:, 2]


def _compensator_set(blocks: Sequence[tuple[str, B.ParamBlock]]) -> VectorSet:
    theta, omega, iq = compensator_inputs()
    rows = []
    for bid, b in blocks:
        out = i_qc(theta, omega, iq, b.table_const, b.table_per_amp, b.lead_s, b.iqc_limit)
        for t, w, i, y in zip(theta, omega, iq, out, strict=True):
            rows.append([bid, f32hex(t), f32hex(w), f32hex(i), f32hex(y)])
    return VectorSet(("block_id", "theta_hat", "omega_hat", "i_qo", "i_qc"), rows,
                     "i_qc = eol_comp_iqc(theta_hat, omega_hat, i_qo, tables, table_len, lead_s, iqc_limit) "
                     "with the tables, lead_s and iqc_limit of blocks.csv row block_id (COMP_ENABLE not applied)",
                     COMPENSATOR_TOLERANCE)


@functools.cache
def _estimator_sets() -> dict[str, VectorSet]:
    # Cached: the tick-by-tick numpy reference takes seconds, and its output never changes
    # within a process (golden --out, --check and the tests all ask for it).
    mod = estimator_golden

    out = {}
    for name, (columns, rows) in mod.vector_sets().items():
        # TOLERANCE: one spec for every estimator file, or a dict of specs keyed by file name
        per_file = isinstance(mod.TOLERANCE, dict) and all(str(k).endswith(".csv") for k in mod.TOLERANCE)
        tol = mod.TOLERANCE.get(name, "exact") if per_file else mod.TOLERANCE
        out[name] = VectorSet(tuple(columns), [list(map(str, r)) for r in rows], mod.DESCRIPTIONS.get(name, ""),
                              tol)
    return out


@functools.cache
def _mech_sets() -> dict[str, VectorSet]:
    # Cached like the estimator's: the identifier's scenarios run tick by tick in numpy.
    return mech_golden.vector_sets()


def vector_sets(include_estimator: bool = True) -> dict[str, VectorSet]:
    """Every golden vector set, by file name (``include_estimator=False``: the block and
    compensator sets of layout 1 only, the quick ones)."""
    blocks = golden_blocks()
    sets = {"blocks.csv": _blocks_set(blocks), "block_checks.csv": _checks_set(blocks),
            "compensator.csv": _compensator_set(blocks)}
    if include_estimator:
        with ThreadPoolExecutor(1) as side:  # both references' processes share the cores: no idle tail
            mech = side.submit(_mech_sets)
            heavy = {**_estimator_sets(), **mech.result()}
        for name, vs in heavy.items():
            if name in sets or name == "manifest.json":
                raise ValueError(f"vector set {name!r} clashes with another set")
            sets[name] = vs
    return sets


def manifest(sets: dict[str, VectorSet], texts: dict[str, str]) -> dict[str, Any]:
    """The manifest document for the sets and their CSV texts."""
    return {
        "format": "eol-cal golden vectors",
        "layout_version": B.LAYOUT_VERSION,
        "layout_versions": list(B.SUPPORTED_LAYOUTS),
        "generator": GENERATOR,
        "generator_package_version": __version__,
        "float_encoding": FLOAT_ENCODING,
        "integer_encoding": "decimal",
        "tolerance": {name: vs.tolerance for name, vs in sets.items()},
        "files": [{"name": name, "rows": len(vs.rows), "sha256": hashlib.sha256(texts[name].encode()).hexdigest(),
                   "columns": list(vs.columns), "description": vs.description,
                   **({"ulp": dict(vs.ulp)} if vs.ulp else {})} for name, vs in sets.items()],
    }


def write_golden(out_dir: str | Path, sets: dict[str, VectorSet] | None = None) -> dict[str, Any]:
    """Write every CSV and ``manifest.json`` (each atomically) into ``out_dir``; returns the manifest."""
    sets = vector_sets() if sets is None else sets
    out_dir = Path(out_dir)
    texts = {name: csv_text(vs) for name, vs in sets.items()}
    for name, text in texts.items():
        atomic_write(out_dir / name, text.encode("ascii"))
    doc = manifest(sets, texts)
    atomic_write(out_dir / "manifest.json", (json.dumps(doc, indent=2) + "\n").encode("ascii"))
    return doc


# Manifest keys that identify the vectors; the rest (package version) is informational.
_MANIFEST_KEYS = ("format", "layout_version", "layout_versions", "generator", "float_encoding", "integer_encoding", "tolerance")


def check_golden(golden_dir: str | Path, sets: dict[str, VectorSet] | None = None,
                 max_per_file: int = 5) -> list[str]:
    """Differences between the vectors in ``golden_dir`` and the Python reference (empty: identical).

    Each difference names the file and, for CSVs, the row (1 = first data row) and column.
    """
    sets = vector_sets() if sets is None else sets
    golden_dir = Path(golden_dir)
    texts = {name: csv_text(vs) for name, vs in sets.items()}
    problems: list[str] = []
    mpath = golden_dir / "manifest.json"
    try:
        on_disk = loads_json(read_text(mpath), str(mpath))
    except InputError as exc:
        return [f"{mpath}: cannot read the manifest ({exc.reason})"]
    if not isinstance(on_disk, dict):
        return [f"{mpath}: the manifest is not a JSON object"]
    expected = manifest(sets, texts)
    for key in _MANIFEST_KEYS:
        if on_disk.get(key) != expected[key]:
            problems.append(f"{mpath}: {key} is {on_disk.get(key)!r}, the reference gives {expected[key]!r}")
    files = on_disk.get("files", [])
    if not isinstance(files, list):
        problems.append(f"{mpath}: files is not a list")
        files = []
    disk_files: dict[str, dict] = {}
    for f in files:
        name = f.get("name") if isinstance(f, dict) else None
        if not isinstance(name, str):
            problems.append(f"{mpath}: a files entry without a name: {str(f)[:60]}")
            continue
        disk_files[name] = f
    for extra in sorted(set(disk_files) - set(sets)):
        problems.append(f"{mpath}: lists {extra}, which the reference does not generate")
    for name in sets:
        path = golden_dir / name
        entry = disk_files.get(name)
        exp_entry = next(f for f in expected["files"] if f["name"] == name)
        if entry is None:
            problems.append(f"{mpath}: {name} missing from the manifest")
        elif entry != exp_entry:
            diff = [k for k in exp_entry if entry.get(k) != exp_entry[k]]
            problems.append(f"{mpath}: entry of {name} differs in {', '.join(diff)}")
        try:
            text = read_text(path, encoding="ascii")
        except InputError as exc:
            problems.append(f"{path}: cannot read ({exc.reason})")
            continue
        if entry is not None and hashlib.sha256(text.encode()).hexdigest() != entry.get("sha256"):
            problems.append(f"{path}: SHA-256 differs from the manifest's")
        problems += _diff_csv(path, text, texts[name], max_per_file)
    return problems


def _diff_csv(path: Path, got: str, want: str, max_diffs: int) -> list[str]:
    if got == want:
        return []
    g_lines, w_lines = got.splitlines(), want.splitlines()
    out = []
    if g_lines[:1] != w_lines[:1]:
        out.append(f"{path}: header is {g_lines[:1]}, the reference gives {w_lines[:1]}")
        return out
    cols = w_lines[0].split(",")
    for k, (g, w) in enumerate(zip(g_lines[1:], w_lines[1:], strict=False), start=1):
        if g != w:
            gf, wf = g.split(","), w.split(",")
            bad = [c for c, a, b in zip(cols, gf, wf, strict=False) if a != b] or ["(field count)"]
            out.append(f"{path}: row {k} differs in {', '.join(bad)}"
                       + (f" (file {_short(gf, cols, bad[0])}, reference {_short(wf, cols, bad[0])})"
                          if bad[0] in cols else ""))
            if len(out) >= max_diffs:
                out.append(f"{path}: ... further rows not listed")
                return out
    if len(g_lines) != len(w_lines):
        out.append(f"{path}: {len(g_lines) - 1} rows, the reference gives {len(w_lines) - 1}")
    return out


def _short(fields: list[str], cols: list[str], col: str) -> str:
    i = cols.index(col)
    v = fields[i] if i < len(fields) else "<missing>"
    return v if len(v) <= 24 else v[:21] + "..."


