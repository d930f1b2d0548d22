"""MISRA C:2012 through cppcheck's addon on the C reference's firmware sources: nothing outside the
documented deviations (firmware_params/MISRA.md, c/misra_suppressions.txt), no function-local
statics, every if/else braced."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CDIR = ROOT / "firmware_params" / "c"
SOURCES = ["eol_block.c", "eol_comp.c", "eol_est.c", "eol_mech.c", "eol_fp.c"]
SUPPRESSIONS = CDIR / "misra_suppressions.txt"


def _cppcheck(cwd: Path, files: list[str], suppressions: Path | None) -> subprocess.CompletedProcess:
    exe = shutil.which("cppcheck")
    assert exe is not None, "cppcheck is needed (scripts/test installs it from the distribution)"
    cmd = [exe, "--addon=misra", "--std=c99", f"-I{CDIR}", f"-I{CDIR.parent}", "--quiet", "--error-exitcode=1",
           "--template={file}:{line}:{id}"]
    if suppressions is not None:
        cmd.append(f"--suppressions-list={suppressions}")
    return subprocess.run([*cmd, *files], cwd=cwd, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_cppcheck_misra_reports_nothing_outside_the_deviations():
    res = _cppcheck(CDIR, SOURCES, SUPPRESSIONS)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "misra-c2012" not in res.stdout + res.stderr


@pytest.mark.slow
def test_the_addon_is_no_rubber_stamp(tmp_path):
    """An unbraced if and else, and an int used as a condition, are reported."""
    bad = tmp_path / "bad.c"
    bad.write_text("#include <stdint.h>\nint32_t f(int32_t x);\nint32_t f(int32_t x)\n{\n    int32_t s = 0;\n"
                   "    if (x)\n        s = x;\n    else\n        s = 1;\n    return s;\n}\n")
    res = _cppcheck(tmp_path, ["bad.c"], None)
    out = res.stdout + res.stderr
    assert res.returncode == 1
    for rule in ("misra-c2012-15.6", "misra-c2012-14.4"):
        assert rule in out, out


def test_every_deviation_is_documented_with_a_reason():
    doc = (ROOT / "firmware_params" / "MISRA.md").read_text("utf-8")
    rows = {}
    for line in doc.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 4 and re.fullmatch(r"\d+\.\d+", cells[0]):
            rows[cells[0]] = (cells[2], cells[3])
    for line in SUPPRESSIONS.read_text().split():
        rule, place = line.removeprefix("misra-c2012-").split(":*")
        assert rule in rows, f"rule {rule} suppressed without a row in MISRA.md"
        assert f"`{place}`" in rows[rule][0], f"{place} not among rule {rule}'s places"
        assert len(rows[rule][1]) > 60, f"rule {rule}: no reason"
    assert not {"14.4", "15.6", "15.7", "10.1", "10.3", "10.4", "10.6", "10.8", "17.7"} & set(rows)


def test_no_function_local_statics_and_every_if_else_braced():
    for name in SOURCES:
        text = (CDIR / name).read_text()
        assert not re.search(r"^[ \t]+static\b", text, re.M), f"{name}: a function-local static"
        code = re.sub(r"^[ \t]*#.*$", "", re.sub(r"/\*.*?\*/", "", text, flags=re.S), flags=re.M)
        for m in re.finditer(r"\b(if|else)\b", code):
            rest = code[m.end():]
            if m.group(1) == "if":
                depth, start = 0, rest.index("(")
                i = start
                for i in range(start, len(rest)):
                    depth += {"(": 1, ")": -1}.get(rest[i], 0)
                    if depth == 0:
                        break
                rest = rest[i + 1:]
            body = rest.lstrip()
            assert body.startswith("{") or (m.group(1) == "else" and body.startswith("if")), \
                f"{name}: an unbraced {m.group(1)} body at offset {m.start()}"
