"""The C port (firmware_params/c/eol_est.c) against the golden vectors, built with the system cc."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from eol_cal.firmware import estimator as est
from eol_cal.firmware import estimator_golden as G

ROOT = Path(__file__).resolve().parents[1]
CDIR = ROOT / "firmware_params" / "c"
GOLDEN = ROOT / "firmware_params" / "golden"
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-O2"]


@pytest.fixture(scope="module")
def harness(tmp_path_factory):
    cc = shutil.which("cc")
    assert cc is not None, "a C compiler (cc) is needed to test the C reference"
    exe = tmp_path_factory.mktemp("est") / "harness"
    srcs = sorted(str(p) for p in CDIR.glob("eol_*.c")) + [str(CDIR / "harness.c")]
    subprocess.run([cc, *CFLAGS, f"-I{CDIR}", f"-I{CDIR.parent}", "-o", str(exe), *srcs, "-lm"],
                   check=True, capture_output=True, text=True)
    return exe


def _estimator_only(dst: Path, names: list[str]) -> None:
    """A golden dir whose manifest lists only ``names`` (the estimator files)."""
    doc = json.loads((GOLDEN / "manifest.json").read_text())
    doc["files"] = [f for f in doc["files"] if f["name"] in names]
    for n in names:
        shutil.copy(GOLDEN / n, dst / n)
    (dst / "manifest.json").write_text(json.dumps(doc))


def test_c_port_matches_every_estimator_scenario_bit_for_bit(harness, tmp_path):
    names = ["estimator_configs.csv", *G.SCENARIOS]
    _estimator_only(tmp_path, names)
    res = subprocess.run([str(harness), str(tmp_path)], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
    for n in names:
        assert f"{n}: " in res.stdout and "rows ok" in res.stdout.split(f"{n}: ")[1].splitlines()[0]
    assert f"PASS: {len(names)} files, 0 failed" in res.stdout


@pytest.mark.parametrize("column", ["theta_hat", "omega_hat", "theta_enc", "status"])
def test_c_harness_detects_one_wrong_output(harness, tmp_path, column):
    name = "estimator_hall_glitch.csv"
    _estimator_only(tmp_path, ["estimator_configs.csv", name])
    lines = (tmp_path / name).read_text().splitlines()
    cols = lines[0].split(",")
    row = lines[1500].split(",")
    i = cols.index(column)
    row[i] = str(int(row[i]) ^ 1) if column == "status" else f"{int(row[i], 16) ^ 1:08x}"
    lines[1500] = ",".join(row)
    (tmp_path / name).write_text("\n".join(lines) + "\n")
    res = subprocess.run([str(harness), str(tmp_path)], capture_output=True, text=True)
    assert res.returncode == 1
    assert f"row 1500: {column}" in res.stderr  # data row 1500 = line 1501


def test_c_harness_checks_the_derived_constants(harness, tmp_path):
    _estimator_only(tmp_path, ["estimator_configs.csv"])
    text = (tmp_path / "estimator_configs.csv").read_text().splitlines()
    cols = text[0].split(",")
    row = text[1].split(",")
    row[cols.index("K_OMEGA")] = "00000000"
    text[1] = ",".join(row)
    (tmp_path / "estimator_configs.csv").write_text("\n".join(text) + "\n")
    res = subprocess.run([str(harness), str(tmp_path)], capture_output=True, text=True)
    assert res.returncode == 1 and "K_OMEGA" in res.stderr


@pytest.mark.parametrize("name", ["estimator_edge_bounce.csv", "estimator_missing_edge.csv"])
def test_checked_in_vectors_are_the_python_reference(name):
    # (every file is regenerated and compared by the golden check; two short ones here)
    text = (GOLDEN / name).read_text()
    columns, rows = G.vector_sets([name])[name]
    assert text == ",".join(columns) + "\n" + "".join(",".join(r) + "\n" for r in rows)


@pytest.mark.slow
def test_fast_numpy_loop_is_the_numpy_step():
    """est.run's scalar fast path computes exactly what step(xp=numpy) computes."""
    cfg = est.EstimatorConfig.all_improvements(standstill_s=0.05)
    a, b, h = (x[:2500] for x in G.SCENARIOS["estimator_standstill_restart.csv"].signals())
    ref = est.run(cfg, a, b, h)
    s = est.init_state(cfg, h[0], a[0], b[0])
    for i in range(len(a)):
        s, o = est.step(cfg, s, a[i], b[i], h[i], xp=np)
        assert (o.theta_hat.view(np.uint32), o.omega_hat.view(np.uint32), int(o.status)) == \
               (ref.theta_hat[i:i + 1].view(np.uint32)[0], ref.omega_hat[i:i + 1].view(np.uint32)[0],
                int(ref.status[i]))


def test_firmware_source_has_no_double_no_heap():
    src = (CDIR / "eol_est.c").read_text() + (CDIR / "eol_est.h").read_text()
    code = "\n".join(line.split("/*")[0] for line in src.splitlines())
    for word in ("double", "malloc", "free(", "printf", "long double"):
        assert word not in code
