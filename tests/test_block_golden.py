"""Golden vectors: checked-in set = Python reference; C reference built with cc matches bit for bit."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.firmware import block as B
from eol_cal.firmware import compensator as comp
from eol_cal.firmware import golden, vectors

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "firmware_params" / "golden"
CDIR = ROOT / "firmware_params" / "c"
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror"]


@pytest.fixture(scope="module")
def sets():
    return golden.vector_sets()


@pytest.mark.slow  # regenerates every golden vector set (the C harness tests check the files in the fast loop)
def test_checked_in_golden_matches_reference(sets):
    assert golden.check_golden(GOLDEN, sets) == []


@pytest.mark.slow  # regenerates every golden vector set (the C harness tests check the files in the fast loop)
def test_manifest_format(sets):
    doc = json.loads((GOLDEN / "manifest.json").read_text())
    assert doc["layout_version"] == 1 and doc["float_encoding"] == "ieee754-binary32-hex"
    assert doc["generator"] == golden.GENERATOR
    names = [f["name"] for f in doc["files"]]
    assert {"blocks.csv", "block_checks.csv", "compensator.csv"} <= set(names)
    for f in doc["files"]:
        text = (GOLDEN / f["name"]).read_bytes()
        assert hashlib.sha256(text).hexdigest() == f["sha256"]
        assert text.count(b"\n") == f["rows"] + 1
        assert f["name"] in doc["tolerance"]
    comp_rows = list(vectors.iter_rows((GOLDEN / "compensator.csv").read_text()))
    for r in comp_rows[:50]:
        assert all(re.fullmatch(r"[0-9a-f]{8}", r[c]) for c in ("theta_hat", "omega_hat", "i_qo", "i_qc"))


@pytest.mark.slow  # regenerates every golden vector set (the C harness tests check the files in the fast loop)
def test_golden_sets_cover_what_the_brief_asks(sets):
    blocks = golden.golden_blocks()
    assert len(blocks) >= 3 and len({b.table_len for _, b in blocks}) >= 3
    theta, omega, i_qo = golden.compensator_inputs()
    assert theta.min() < 0 and theta.max() > 2 * np.pi and np.any(theta == 0)
    assert omega.min() < 0 < omega.max() and i_qo.min() < 0 < i_qo.max()
    clamped = 0
    for _, b in blocks:
        y = comp.i_qc(theta, omega, i_qo, b.table_const, b.table_per_amp, b.lead_s, b.iqc_limit)
        clamped += int(np.sum(np.abs(y) == np.float32(b.iqc_limit)))
    assert clamped > 0
    statuses = {r[2] for r in sets["block_checks.csv"].rows}
    assert statuses == {"0", "1", "2"}


@pytest.mark.slow  # regenerates every golden vector set (the C harness tests check the files in the fast loop)
def test_check_reports_file_and_row(tmp_path, sets):
    mine = {k: v for k, v in sets.items() if k in ("blocks.csv", "block_checks.csv", "compensator.csv")}
    golden.write_golden(tmp_path, mine)
    assert golden.check_golden(tmp_path, mine) == []
    path = tmp_path / "compensator.csv"
    lines = path.read_text().splitlines(keepends=True)
    cols = lines[0].rstrip().split(",")
    fields = lines[42].rstrip().split(",")
    fields[cols.index("i_qc")] = vectors.f32hex(vectors.hex_f32(fields[cols.index("i_qc")]) + np.float32(1e-3))
    lines[42] = ",".join(fields) + "\n"
    path.write_text("".join(lines))
    problems = golden.check_golden(tmp_path, mine)
    assert any("compensator.csv: row 42 differs in i_qc" in p for p in problems)
    assert any("SHA-256" in p for p in problems)


def _build_harness(tmp_path: Path) -> Path:
    cc = shutil.which("cc")
    if cc is None:
        pytest.fail("no C compiler `cc` on PATH: the C reference cannot be checked")
    exe = tmp_path / "harness"
    srcs = sorted(str(p) for p in CDIR.glob("eol_*.c")) + [str(CDIR / "harness.c")]
    subprocess.run([cc, *CFLAGS, "-O2", f"-I{CDIR}", f"-I{CDIR.parent}", "-o", str(exe), *srcs, "-lm"],
                   check=True, capture_output=True, text=True)
    return exe


@pytest.fixture(scope="module")
def harness(tmp_path_factory):
    return _build_harness(tmp_path_factory.mktemp("cbuild"))


def test_c_harness_passes_every_vector(harness):
    res = subprocess.run([str(harness), str(GOLDEN)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    doc = json.loads((GOLDEN / "manifest.json").read_text())
    for f in doc["files"]:
        assert f"{f['name']}: {f['rows']} rows ok" in res.stdout


@pytest.mark.parametrize("target, column", [("compensator.csv", "i_qc"), ("block_checks.csv", "status"),
                                            ("blocks.csv", "kt")])
def test_c_harness_detects_a_wrong_vector(harness, tmp_path, target, column):
    for f in ("manifest.json", "blocks.csv", "block_checks.csv", "compensator.csv"):
        shutil.copy(GOLDEN / f, tmp_path / f)
    doc = json.loads((tmp_path / "manifest.json").read_text())
    doc["files"] = [f for f in doc["files"] if f["name"] in ("blocks.csv", "block_checks.csv", "compensator.csv")]
    (tmp_path / "manifest.json").write_text(json.dumps(doc, indent=2))
    ok = subprocess.run([str(harness), str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0, ok.stderr
    path = tmp_path / target
    lines = path.read_text().splitlines(keepends=True)
    cols = lines[0].rstrip().split(",")
    fields = lines[2].rstrip().split(",")
    i = cols.index(column)
    fields[i] = "1" if column == "status" and fields[i] != "1" else (
        "2" if column == "status" else f"{int(fields[i], 16) ^ 1:08x}")
    lines[2] = ",".join(fields) + "\n"
    path.write_text("".join(lines))
    bad = subprocess.run([str(harness), str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1
    assert f"{target}: row 2" in bad.stderr and f"{target}: FAIL" in bad.stdout


def test_c_harness_fails_on_a_file_without_checker(harness, tmp_path):
    shutil.copy(GOLDEN / "blocks.csv", tmp_path / "blocks.csv")
    (tmp_path / "mystery.csv").write_text("a\n1\n")
    (tmp_path / "manifest.json").write_text(json.dumps({"files": [{"name": "blocks.csv"}, {"name": "mystery.csv"}]},
                                                       indent=2))
    res = subprocess.run([str(harness), str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 1 and "mystery.csv: FAIL: no checker" in res.stderr


def test_firmware_sources_avoid_double_and_heap():
    cc = shutil.which("cc")
    assert cc is not None
    for src in ("eol_block.c", "eol_comp.c"):
        text = (CDIR / src).read_text()
        code = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
        assert not re.search(r"\bdouble\b|\bmalloc\b|\bfree\b|\bcalloc\b|\buint8_t\b", code), src
        # -Wdouble-promotion: no float silently widened to double (C28x: double is 32-bit anyway)
        subprocess.run([cc, *CFLAGS, "-pedantic", "-Wdouble-promotion", "-Wconversion", f"-I{CDIR}",
                        f"-I{CDIR.parent}", "-c", str(CDIR / src), "-o", "/dev/null"],
                       check=True, capture_output=True, text=True)


def test_c_crc_table_is_iso_hdlc():
    text = (CDIR / "eol_block.c").read_text()
    table = [int(x, 16) for x in re.findall(r"\b0x([0-9A-F]{8})u\b", text.split("eol_crc32_table[256]")[1].split("};")[0])]
    assert len(table) == 256
    for i, v in enumerate(table):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0xEDB88320 if c & 1 else c >> 1
        assert v == c
    assert B.crc32(b"123456789") == 0xCBF43926


@pytest.mark.slow  # every other vector set computed: 105 s in the fast loop at load 7
def test_estimator_sets_are_taken_from_their_module(monkeypatch, tmp_path):
    import types

    fake = types.ModuleType("eol_cal.firmware.estimator_golden")
    fake.vector_sets = lambda: {"estimator_const_60rpm.csv": (["tick", "theta_hat"], [[0, "3f800000"], [1, "40000000"]])}
    fake.TOLERANCE = {"estimator_const_60rpm.csv": {"theta_hat": {"abs": 1e-6, "unit": "rad"}}}
    fake.DESCRIPTIONS = {}
    monkeypatch.setattr(golden, "estimator_golden", fake)
    monkeypatch.setattr(golden, "_estimator_sets", golden._estimator_sets.__wrapped__)
    sets = golden.vector_sets()
    est = sets["estimator_const_60rpm.csv"]
    assert est.rows == [["0", "3f800000"], ["1", "40000000"]]
    doc = golden.write_golden(tmp_path, sets)
    assert doc["tolerance"]["estimator_const_60rpm.csv"] == {"theta_hat": {"abs": 1e-6, "unit": "rad"}}
    assert (tmp_path / "estimator_const_60rpm.csv").read_text() == "tick,theta_hat\n0,3f800000\n1,40000000\n"
    assert golden.check_golden(tmp_path, sets) == []
    fake.vector_sets = lambda: {"blocks.csv": (["x"], [])}
    with pytest.raises(ValueError, match="clashes"):
        golden.vector_sets()


def test_makefile_builds_and_checks(tmp_path):
    make = shutil.which("make")
    if make is None:
        pytest.fail("no make on PATH: the documented `make -C firmware_params/c check` cannot run")
    res = subprocess.run([make, "-s", "-C", str(CDIR), f"BUILD={tmp_path}", "check"], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "PASS" in res.stdout and (tmp_path / "harness").exists()


@pytest.mark.parametrize("files", [[{"size": 1}, {"name": "x.csv"}], 7, [3, None, {"name": 5}]])
def test_a_malformed_manifest_is_reported_not_a_crash(tmp_path, files):
    (tmp_path / "manifest.json").write_text(json.dumps({"files": files}))
    problems = golden.check_golden(tmp_path, {})
    if isinstance(files, list):
        assert sum("a files entry without a name" in p for p in problems) == len(files) - (files[-1] == {"name": "x.csv"})
    else:
        assert any("files is not a list" in p for p in problems)
    assert all(p.startswith(str(tmp_path / "manifest.json")) for p in problems)


def _golden_cli(*args: str):
    # in this module's process, where the sets fixture computed the vector sets once (golden's cache)
    return CliRunner().invoke(cli, ["golden", *args], catch_exceptions=False)


@pytest.mark.slow
def test_golden_out_and_check(sets, tmp_path):
    out = tmp_path / "g"
    res = _golden_cli("--out", str(out))
    assert res.exit_code == 0, res.output
    assert _golden_cli("--check", str(out)).exit_code == 0
    (out / "blocks.csv").write_text((out / "blocks.csv").read_text().replace("EPS-0001", "EPS-0009"))
    res = _golden_cli("--check", str(out))
    assert res.exit_code == 1 and "blocks.csv: row 1 differs in serial" in res.output
    assert _golden_cli().exit_code == 2


@pytest.mark.slow
def test_golden_check_default_dir(sets, monkeypatch):
    monkeypatch.chdir(ROOT)
    res = _golden_cli("--check")
    assert res.exit_code == 0, res.output
    n = len(sets)
    assert f"{n} files" in res.output
