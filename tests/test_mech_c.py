"""The C reference of revision 1.2 (firmware_params/c/eol_mech.c, eol_comp_iqc_mech, the block check
of layout 2) against the golden vectors, built with the system cc, bit for bit; and the vectors
against the Python reference."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from eol_cal.firmware import block as B
from eol_cal.firmware import mech_golden as MG
from eol_cal.firmware.mech import EV_EVAL, EV_IDENTIFIED, EV_PASS, EV_RESET_FAULT, EV_RESET_FRACTION
from eol_cal.firmware.vectors import iter_rows

ROOT = Path(__file__).resolve().parents[1]
CDIR = ROOT / "firmware_params" / "c"
GOLDEN = ROOT / "firmware_params" / "golden"
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-O2"]
MECH_FILES = ["blocks_v2.csv", "block_checks_v2.csv", "mech_configs.csv", "mech_compensator.csv", *MG.SCENARIOS]


@pytest.fixture(scope="module")
def harness(tmp_path_factory):
    cc = shutil.which("cc")
    assert cc is not None, "a C compiler (cc) is needed to test the C reference"
    exe = tmp_path_factory.mktemp("mech") / "harness"
    srcs = sorted(str(p) for p in CDIR.glob("eol_*.c")) + [str(CDIR / "harness.c")]
    subprocess.run([cc, *CFLAGS, f"-I{CDIR}", f"-I{CDIR.parent}", "-o", str(exe), *srcs, "-lm"],
                   check=True, capture_output=True, text=True)
    return exe


def _only(dst: Path, names: list[str], edit: dict[str, str] | None = None) -> None:
    """A golden dir whose manifest lists only ``names`` (file texts replaced by ``edit``)."""
    doc = json.loads((GOLDEN / "manifest.json").read_text())
    doc["files"] = [f for f in doc["files"] if f["name"] in names]
    for n in names:
        text = (edit or {}).get(n)
        if text is None:
            shutil.copy(GOLDEN / n, dst / n)
        else:
            (dst / n).write_text(text)
    (dst / "manifest.json").write_text(json.dumps(doc))


def test_c_port_matches_every_layout_2_file_bit_for_bit(harness, tmp_path):
    _only(tmp_path, MECH_FILES)
    res = subprocess.run([str(harness), str(tmp_path)], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
    for n in MECH_FILES:
        assert "rows ok" in res.stdout.split(f"{n}: ")[1].splitlines()[0], n
    assert f"PASS: {len(MECH_FILES)} files, 0 failed" in res.stdout


def test_the_harness_sees_one_changed_bit(harness, tmp_path):
    """A scenario row whose i_qc differs in its last bit, and one whose r differs, fail by name."""
    name = "mech_slip.csv"
    lines = (GOLDEN / name).read_text().splitlines()
    cols = lines[0].split(",")
    k = next(i for i, line in enumerate(lines[1:], 1) if line.split(",")[cols.index("active")] == "1")
    f = lines[k].split(",")
    f[cols.index("i_qc")] = f"{int(f[cols.index('i_qc')], 16) ^ 1:08x}"
    f[cols.index("r")] = str((int(f[cols.index("r")]) + 1) % 64)
    lines[k] = ",".join(f)
    _only(tmp_path, ["blocks_v2.csv", "mech_configs.csv", name], {name: "\n".join(lines) + "\n"})
    res = subprocess.run([str(harness), str(tmp_path)], capture_output=True, text=True)
    assert res.returncode == 1
    assert f"{name}: FAIL" in res.stdout and f"row {k}: i_qc" in res.stderr and f"row {k}: r" in res.stderr


def test_layout_2_blocks_check_and_decode():
    for _bid, blk in MG.golden_blocks_v2():
        data = B.pack(blk)
        assert B.check(data).valid and len(data) == 3248 + 8 * blk.table_len
        assert B.unpack(data) == blk and blk.layout_version == 2
    for cid, image, status in MG.check_cases():
        assert B.check(image).status == status, cid


def test_the_scenarios_show_what_their_descriptions_say():
    """The vectors are worth checking against: each scenario's events as its description says."""
    def events(name):
        rows = list(iter_rows((GOLDEN / name).read_text()))
        return np.array([int(r["events"]) for r in rows]), np.array([int(r["active"]) for r in rows])

    def count(ev, bit):
        return int(((ev & bit) != 0).sum())

    for name in ("mech_pole_pair_0.csv", "mech_pole_pair_1.csv", "mech_pole_pair_2.csv", "mech_reverse.csv",
                 "mech_speed_change.csv"):
        ev, act = events(name)
        assert count(ev, EV_IDENTIFIED) == 1 and act[-1] == 1, name
    ev, act = events("mech_weak.csv")
    assert count(ev, EV_EVAL) >= 2 and count(ev, EV_PASS) == 0 and act.max() == 0
    ev, act = events("mech_reverse_fwd_only.csv")
    assert ev.sum() == 0 and act.max() == 0
    ev, act = events("mech_noise.csv")
    assert count(ev, EV_RESET_FAULT) == 1 and count(ev, EV_IDENTIFIED) == 2 and act[-1] == 1
    ev, act = events("mech_slip.csv")
    assert count(ev, EV_RESET_FRACTION) == 1 and count(ev, EV_IDENTIFIED) == 2 and act[-1] == 1
