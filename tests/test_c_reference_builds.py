"""The C reference built as a firmware team builds it: gcc and clang, -O0 and -O2, with and without
fused multiply-add, and with the C28x's division and square root (``-DEOL_FPU_C28X``), each against
every golden file within its tolerance class (firmware contract section 4, "Floating point"); and
the harness's own accounting (rows, per column, every difference
in a file).

The sources state their floating-point contract (``firmware_params/c/eol_fp.h``), so no build
flag is needed for bit-exactness: with FMA available (``-mfma``) and gcc told to contract
everything (``-ffp-contract=fast``, its default outside ISO C mode) the results are the same.
clang's ``-ffp-contract=fast`` disregards pragmas by definition; the contract forbids it.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CDIR = ROOT / "firmware_params" / "c"
GOLDEN = ROOT / "firmware_params" / "golden"
WARN = ["-Wall", "-Wextra", "-Werror"]
#: (compiler, flags) of each build; "fma": FMA instructions available and contraction allowed by the build
BUILDS = {
    f"{cc}-{opt}-{fma}": (cc, [std, opt, *extra, *WARN])
    for cc in ("gcc", "clang")
    for opt in ("-O0", "-O2")
    for fma, std, extra in (
        ("nofma", "-std=c99", []),
        # gcc: GNU C mode contracts by default, -ffp-contract=fast says so; clang: its default (on)
        ("fma", "-std=gnu99", ["-mfma", "-ffp-contract=fast"] if cc == "gcc" else ["-mfma", "-ffp-contract=on"]),
    )
}
#: the division and square root of the identification as the C28x computes them (eol_fp.c's model)
BUILDS["gcc-O2-c28x-division"] = ("gcc", ["-std=c99", "-O2", "-DEOL_FPU_C28X", *WARN])


def _build(cc: str, flags: list[str], out: Path) -> Path:
    exe = shutil.which(cc)
    assert exe is not None, f"{cc} is needed (scripts/test installs it from the distribution)"
    srcs = sorted(str(p) for p in CDIR.glob("eol_*.c")) + [str(CDIR / "harness.c")]
    res = subprocess.run([exe, *flags, f"-I{CDIR}", f"-I{CDIR.parent}", "-o", str(out), *srcs, "-lm"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    return out


@pytest.mark.slow
@pytest.mark.parametrize("build", sorted(BUILDS))
def test_every_build_passes_every_golden_file_within_its_class(build, tmp_path):
    cc, flags = BUILDS[build]
    exe = _build(cc, flags, tmp_path / "harness")
    diff = tmp_path / "diff.csv"
    res = subprocess.run([str(exe), str(GOLDEN), str(diff)], capture_output=True, text=True, timeout=600)
    n_files = len(json.loads((GOLDEN / "manifest.json").read_text())["files"])
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert f"PASS: {n_files} files, 0 failed" in res.stdout
    recorded = diff.read_text().splitlines()[1:]
    assert not [line for line in recorded if line.endswith("beyond")]
    if "c28x" in build:
        # the model does make the cosine and margin differ (within their class), nothing else
        assert recorded and {line.split(",")[2] for line in recorded} <= {"score", "margin"}
    else:
        assert recorded == []


def _only(dst: Path, names: list[str], edit: dict[str, str]) -> None:
    doc = json.loads((GOLDEN / "manifest.json").read_text())
    doc["files"] = [f for f in doc["files"] if f["name"] in names]
    for n in names:
        (dst / n).write_text(edit[n]) if n in edit else shutil.copy(GOLDEN / n, dst / n)
    (dst / "manifest.json").write_text(json.dumps(doc))


@pytest.fixture(scope="module")
def harness(tmp_path_factory):
    return _build("cc", ["-std=c99", "-O2", *WARN], tmp_path_factory.mktemp("h") / "harness")


def test_rows_are_counted_once_and_every_difference_is_in_the_file(harness, tmp_path):
    """30 rows with two changed columns each: 30 rows differ (not 60), each column counted with its
    largest ulp, and all 60 differences in the file although stderr shows only a few."""
    name = "estimator_const_60rpm.csv"
    lines = (GOLDEN / name).read_text().splitlines()
    cols = lines[0].split(",")
    rows = list(range(100, 3100, 100))
    for k in rows:
        f = lines[k].split(",")
        f[cols.index("theta_hat")] = f"{int(f[cols.index('theta_hat')], 16) + 3:08x}"
        f[cols.index("status")] = str(int(f[cols.index("status")]) ^ 64)
        lines[k] = ",".join(f)
    _only(tmp_path, ["estimator_configs.csv", name], {name: "\n".join(lines) + "\n"})
    diff = tmp_path / "diff.csv"
    res = subprocess.run([str(harness), str(tmp_path), str(diff)], capture_output=True, text=True)
    assert res.returncode == 1
    assert f"{name}: FAIL: 30 of 6000 rows differ beyond their class" in res.stdout
    summary = res.stdout.split(f"{name}: FAIL")[1]
    assert "theta_hat          30 rows differ, 30 beyond its class (exact); largest 3 ulp" in summary
    assert "status             30 rows differ, 30 beyond its class (exact)" in summary
    recorded = diff.read_text().splitlines()
    assert recorded[0] == "file,row,column,expected,got,ulp,bound,class"
    assert len(recorded) == 1 + 60
    assert sorted({int(line.split(",")[1]) for line in recorded[1:]}) == rows
    assert res.stderr.count(": row ") < 60


def test_a_column_with_an_ulp_class_passes_within_and_fails_beyond(harness, tmp_path):
    """The manifest's per-file ``ulp`` object is what the harness checks: 2 ulp off passes a bound of
    2 (reported as within), 3 ulp fails it."""
    name = "estimator_const_60rpm.csv"
    lines = (GOLDEN / name).read_text().splitlines()
    cols = lines[0].split(",")

    def run(delta: int) -> subprocess.CompletedProcess:
        edited = list(lines)
        f = edited[500].split(",")
        f[cols.index("omega_hat")] = f"{int(f[cols.index('omega_hat')], 16) + delta:08x}"
        edited[500] = ",".join(f)
        _only(tmp_path, ["estimator_configs.csv", name], {name: "\n".join(edited) + "\n"})
        doc = json.loads((tmp_path / "manifest.json").read_text())
        for entry in doc["files"]:
            if entry["name"] == name:
                entry["ulp"] = {"theta_hat": 1, "omega_hat": 2}
        (tmp_path / "manifest.json").write_text(json.dumps(doc, indent=2))
        return subprocess.run([str(harness), str(tmp_path), str(tmp_path / "d.csv")], capture_output=True, text=True)

    ok = run(2)
    assert ok.returncode == 0, ok.stdout
    assert f"{name}: 6000 rows ok, 1 of them within their class" in ok.stdout
    bad = run(3)
    assert bad.returncode == 1
    assert "omega_hat           1 rows differ, 1 beyond its class (ulp <= 2); largest 3 ulp" in bad.stdout
