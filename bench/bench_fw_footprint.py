"""Memory of the firmware's C reference: RAM per motor (its state structs), code size and stack per
function, from the build (docs/firmware-contract.md, "Memory").

Builds every firmware source (``firmware_params/c/eol_*.c``) with the host gcc at -O2 and -Os,
``-fstack-usage``, and reads ``size`` (text, data, bss per object), ``nm -S`` (code bytes per
function) and the ``.su`` files (stack bytes per function). The RAM of the state is ``sizeof`` of
each struct, printed by a small program built against the same headers; on the C28x every member
is 32 bits (float, int32_t, uint32_t), so its size in 16-bit words is half the host's bytes.
The code sizes are x86-64's: a proxy for the C28x's (TI's cl2000 is not available here), stated
as such.

    python bench/bench_fw_footprint.py
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CDIR = ROOT / "firmware_params" / "c"
SOURCES = ["eol_block.c", "eol_comp.c", "eol_est.c", "eol_mech.c", "eol_fp.c"]
STRUCTS = ["eol_est_t", "eol_est_out_t", "eol_mech_t", "eol_mech_out_t"]


def _run(cmd: list[str], cwd: Path) -> str:
    return subprocess.run(cmd, cwd=cwd, check=True, capture_output=True, text=True).stdout


def struct_sizes(work: Path) -> dict[str, int]:
    """sizeof of each state struct (bytes, host)."""
    src = work / "sizes.c"
    body = "".join(f'    printf("{s} %zu\\n", sizeof({s}));\n' for s in STRUCTS)
    head = '#include <stdio.h>\n#include "eol_est.h"\n#include "eol_mech.h"\n'
    src.write_text(f"{head}int main(void)\n{{\n{body}    return 0;\n}}\n")
    exe = work / "sizes"
    _run(["gcc", "-std=c99", f"-I{CDIR}", f"-I{CDIR.parent}", "-o", str(exe), str(src)], work)
    return {k: int(v) for k, v in (line.split() for line in _run([str(exe)], work).splitlines())}


def functions(work: Path, opt: str) -> list[tuple[str, str, int, int]]:
    """(file, function, code bytes, stack bytes) of every function at ``opt``."""
    out = []
    for name in SOURCES:
        obj = work / f"{name[:-2]}{opt}.o"
        _run(["gcc", "-std=c99", opt, "-fstack-usage", f"-I{CDIR}", f"-I{CDIR.parent}", "-c", str(CDIR / name),
              "-o", str(obj)], work)
        stack = {}
        for line in obj.with_suffix(".su").read_text().splitlines():
            m = re.match(r".*:\d+:\d+:(\w+)\s+(\d+)", line)
            if m:
                stack[m.group(1)] = int(m.group(2))
        for line in _run(["nm", "-S", "--size-sort", str(obj)], work).splitlines():
            addr, size, kind, sym = line.split()
            if kind.lower() == "t":
                out.append((name, sym, int(size, 16), stack.get(sym, 0)))
    return out


def object_sizes(work: Path, opt: str) -> list[tuple[str, int, int, int]]:
    """(file, text, data, bss) from ``size`` at ``opt``."""
    rows = []
    for name in SOURCES:
        text, data, bss = _run(["size", str(work / f"{name[:-2]}{opt}.o")], work).splitlines()[1].split()[:3]
        rows.append((name, int(text), int(data), int(bss)))
    return rows


def main() -> None:
    for tool in ("gcc", "nm", "size"):
        if shutil.which(tool) is None:
            raise SystemExit(f"{tool} is needed")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        sizes = struct_sizes(work)
        print("RAM per motor (state structs): host bytes, C28x 16-bit words")
        for s, b in sizes.items():
            print(f"  {s:16s} {b:6d} B  {b // 2:6d} words")
        total = sizes["eol_est_t"] + sizes["eol_mech_t"]
        print(f"  estimator + identifier: {total} B = {total // 2} words (F28335: 34 K words of RAM)")
        for opt in ("-O2", "-Os"):
            fns = functions(work, opt)
            print(f"\ngcc 12 x86-64 {opt}: code and stack per function (bytes)")
            for file, sym, size, stack in sorted(fns, key=lambda r: (r[0], -r[2])):
                print(f"  {file:12s} {sym:28s} {size:6d}  stack {stack:5d}")
            print(f"size {opt}: file text data bss")
            for file, text, data, bss in object_sizes(work, opt):
                print(f"  {file:12s} {text:6d} {data:6d} {bss:6d}")


if __name__ == "__main__":
    main()
