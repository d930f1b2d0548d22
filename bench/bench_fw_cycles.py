"""A cycle budget per tick for the F28335 (150 MHz, C28x + FPU): every operation of the C reference
counted on every tick of every golden scenario, weighed with a cost per operation class
(docs/firmware-contract.md, "Cycle budget").

The counting build: clang compiles each firmware source to LLVM IR (-O2, no vectorisation: the
operations a compiler keeps after optimising), this script puts a counter increment before every
operation of a counted class, and the harness (``-DEOL_COUNT_OPS``) weighs the counts of each call
(estimator, identifier's tick, its background slice, compensator) with :data:`COST` and prints the
worst tick per function and per golden file. The counts are clang's for the host, a stand-in for
TI's cl2000 (not available here); the interrupt's entry and exit are not counted.

    python bench/bench_fw_cycles.py                  # the worst ticks, per file and in all
    python bench/bench_fw_cycles.py --eval-in-tick   # the same with the evaluation's slices run inside the tick
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CDIR = ROOT / "firmware_params" / "c"
SOURCES = ["eol_block.c", "eol_comp.c", "eol_est.c", "eol_mech.c", "eol_fp.c"]
#: cycles of a 20 kHz tick at 150 MHz, and the budget the contract proposes for its ECU side
TICK_CYCLES = 150e6 / 20e3
BUDGET = 0.30 * TICK_CYCLES

#: operation class -> (cycles on the C28x + FPU at 150 MHz, where the figure comes from)
COST: dict[str, tuple[float, str]] = {
    "fadd": (2, "ADDF32/SUBF32, 2 pipeline cycles (TMS320C28x FPU instruction set, SPRUEO2)"),
    "fmul": (2, "MPYF32, 2 pipeline cycles (SPRUEO2)"),
    "fdiv": (24, "no divide instruction: EINVF32 (2) + two Newton steps (3 x 2 each) + MPYF32 (2) + call and "
                 "return (8): the runtime's sequence, eol_cal/firmware/fpu_c28x.py"),
    "fcmp": (2, "CMPF32 (1) + MOVST0 to the CPU's flags (1) (SPRUEO2)"),
    "fneg": (1, "NEGF32 / ABSF32, 1 cycle (SPRUEO2)"),
    "fconv": (2, "I32TOF32 / F32TOI32, 2 pipeline cycles (SPRUEO2)"),
    "floor": (16, "the runtime's floorf: F32TOI32 + I32TOF32 (4), compare and correct (4), call and return (8)"),
    "sqrt": (32, "no square-root instruction: EISQRTF32 (2) + two Newton steps (4 x 2 each) + 2 MPYF32 (4) + a "
                 "test (2) + call and return (8), eol_cal/firmware/fpu_c28x.py"),
    "ialu": (1, "32-bit ADDL/SUBL/AND/OR/XOR/shift, 1 cycle (TMS320C28x CPU, SPRU430)"),
    "imul": (2, "IMPYL, 32 x 32 multiply (SPRU430), 2 cycles with its operand move"),
    "idiv": (59, "i32/i32 division by the runtime on a C28x without the fast integer division unit "
                 "(SPRACN6, table 4)"),
    "irem": (63, "i32/i32 modulo by the runtime on the C28x (SPRACN6, table 4)"),
    "icmp": (1, "CMPL, 1 cycle (SPRU430)"),
    "select": (2, "a conditional move: compare result and MOVL (SPRU430)"),
    "load": (1, "MOVL / MOV32 from zero-wait-state RAM, 1 cycle (SPRU430, SPRUEO2)"),
    "store": (1, "MOVL / MOV32 to RAM, 1 cycle (SPRU430, SPRUEO2)"),
    "branch": (7, "a conditional branch, counted as taken: 7 cycles (4 not taken; SPRU430)"),
    "jump": (4, "an unconditional branch, 4 cycles (SPRU430; a compiler lays many out as fall-throughs)"),
    "call": (8, "LCR (4) + LRETR (4) (SPRU430)"),
}
CLASSES = list(COST)
OPCODES = {"fadd": "fadd", "fsub": "fadd", "fmul": "fmul", "fdiv": "fdiv", "frem": "fdiv", "fcmp": "fcmp",
           "fneg": "fneg", "sitofp": "fconv", "uitofp": "fconv", "fptosi": "fconv", "fptoui": "fconv",
           "add": "ialu", "sub": "ialu", "and": "ialu", "or": "ialu", "xor": "ialu", "shl": "ialu", "lshr": "ialu",
           "ashr": "ialu", "mul": "imul", "sdiv": "idiv", "udiv": "idiv", "srem": "irem", "urem": "irem",
           "icmp": "icmp", "select": "select", "load": "load", "store": "store", "br": "branch",
           "switch": "branch", "call": "call"}
CALLEES = {"llvm.fabs.f32": "fneg", "fabsf": "fneg", "llvm.floor.f32": "floor", "floorf": "floor",
           "llvm.sqrt.f32": "sqrt", "sqrtf": "sqrt", "llvm.smax.i32": "ialu", "llvm.smin.i32": "ialu",
           "llvm.abs.i32": "ialu", "llvm.umin.i32": "ialu", "llvm.umax.i32": "ialu"}
_INSN = re.compile(r"^\s+(?:%[\w.]+ = )?(?:tail |musttail |notail )?(\w+)\b")
_CALLEE = re.compile(r"@([\w.$]+)\(")
N_SLOTS = 24


def instrument(ll: str) -> str:
    """LLVM IR with a counter increment (``eol_ops[class] += 1``) before every counted operation."""
    out, n = [], 0
    in_fn = False
    for line in ll.splitlines():
        if line.startswith("define "):
            in_fn = True
        elif line.startswith("}"):
            in_fn = False
        m = _INSN.match(line) if in_fn else None
        if m and m.group(1) in OPCODES:
            cls = OPCODES[m.group(1)]
            if cls == "branch" and line.strip().startswith("br label"):
                cls = "jump"
            if cls == "call":
                callee = _CALLEE.search(line)
                name = callee.group(1) if callee else ""
                if name.startswith(("llvm.lifetime", "llvm.dbg")):
                    cls = ""
                else:
                    cls = CALLEES.get(name, "call")
            if cls:
                k = CLASSES.index(cls)
                out.append(f"  %__ops{n} = atomicrmw add i64* getelementptr inbounds ([{N_SLOTS} x i64], "
                           f"[{N_SLOTS} x i64]* @eol_ops, i64 0, i64 {k}), i64 1 monotonic")
                n += 1
        out.append(line)
        if line.startswith("target triple"):
            out.append(f"@eol_ops = external global [{N_SLOTS} x i64], align 8")
    return "\n".join(out) + "\n"


def build(work: Path, defines: list[str]) -> Path:
    """The counting harness: instrumented firmware sources, the harness with -DEOL_COUNT_OPS."""
    clang = shutil.which("clang")
    if clang is None:
        raise SystemExit("clang is needed (scripts/test installs it)")
    inc = [f"-I{CDIR}", f"-I{CDIR.parent}"]
    objs = []
    for name in SOURCES:
        ll = work / (name[:-2] + ".ll")
        subprocess.run([clang, "-std=c99", "-O2", "-fno-vectorize", "-fno-slp-vectorize", *inc, "-S", "-emit-llvm",
                        str(CDIR / name), "-o", str(ll)], check=True)
        ll.write_text(instrument(ll.read_text()))
        obj = work / (name[:-2] + ".o")
        subprocess.run([clang, "-O0", "-c", str(ll), "-o", str(obj)], check=True, capture_output=True)
        objs.append(str(obj))
    exe = work / "harness_count"
    subprocess.run([clang, "-std=c99", "-O2", "-DEOL_COUNT_OPS", *defines, *inc, str(CDIR / "harness.c"), *objs,
                    "-o", str(exe), "-lm"], check=True)
    return exe


def worst_ticks(eval_in_tick: bool = False, golden: Path = ROOT / "firmware_params" / "golden") -> dict:
    """Per golden file and in all: the worst modelled cycles of each function and of the tick."""
    with tempfile.TemporaryDirectory() as tmp:
        exe = build(Path(tmp), ["-DEOL_EVAL_IN_TICK"] if eval_in_tick else [])
        env = {**os.environ, "EOL_OPS_WEIGHTS": ",".join(str(COST[c][0]) for c in CLASSES)}
        res = subprocess.run([str(exe), str(golden)], capture_output=True, text=True, env=env)
    files: dict[str, dict[str, tuple[float, int]]] = {}
    for line in res.stdout.splitlines():
        if line.startswith("CYCLES "):
            _, name, *items = line.split()
            files[name] = {k: (float(v.split("@")[0]), int(v.split("@")[1])) for k, v in (i.split("=") for i in items)}
    overall = {f: max(((v[f][0], name, v[f][1]) for name, v in files.items()), default=(0.0, "", 0))
               for f in ("est", "mech_tick", "background", "comp", "tick")}
    return {"files": files, "worst": overall, "budget": BUDGET, "harness_rc": res.returncode}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--eval-in-tick", action="store_true",
                    help="run the evaluation's slices inside the tick (the structure before revision 1.2's background)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()
    r = worst_ticks(args.eval_in_tick)
    print("cost model (cycles per operation, F28335 at 150 MHz):")
    for c in CLASSES:
        print(f"  {c:7s} {COST[c][0]:>4g}  {COST[c][1]}")
    print(f"\nworst modelled tick per function over every golden file (budget {BUDGET:.0f} cycles = 30 % of "
          f"{TICK_CYCLES:.0f}):")
    for f, (c, name, row) in r["worst"].items():
        print(f"  {f:10s} {c:8.0f} cycles  ({name} row {row})")
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=1))


if __name__ == "__main__":
    main()
