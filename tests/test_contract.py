"""The firmware contract's constants are spelled once (eol_cal/firmware/contract.py) and the C side
takes them from the generated header."""

from __future__ import annotations

import ast
import math
import re
from pathlib import Path

import numpy as np

from eol_cal.firmware import contract as C

ROOT = Path(__file__).resolve().parents[1]

#: literals that belong to the contract module only (an int or a tuple of ints)
CONTRACT_LITERALS = {
    C.MAGIC: "MAGIC",
    C.DID_SERIAL: "DID_SERIAL",
    C.DID_SW_VERSION: "DID_SW_VERSION",
    C.DID_LAYOUTS: "DID_LAYOUTS",
    C.DID_ACTIVE_BLOCK: "DID_ACTIVE_BLOCK",
    C.RID_ERASE: "RID_ERASE",
    C.HALL_FORWARD_SEQUENCE: "HALL_FORWARD_SEQUENCE",
    C.HALL_NEXT: "HALL_NEXT",
}


def _literal(node: ast.AST) -> int | tuple | None:
    if isinstance(node, ast.Constant) and type(node.value) is int:
        return node.value
    if isinstance(node, ast.Tuple) and all(isinstance(e, ast.Constant) and type(e.value) is int for e in node.elts):
        return tuple(e.value for e in node.elts)
    return None


def test_the_contract_as_the_documents_state_it():
    assert C.HALL_NEXT == (0, 3, 6, 2, 5, 1, 4, 0)
    assert [round(math.degrees(a)) for a in C.NOMINAL_HALL_ANGLE] == [60, 180, 120, 300, 0, 240]
    assert (C.FLAG_COMP_ENABLE, C.FLAG_INTERP_ENABLE) == (1, 2)
    assert (C.STATUS_VALID, C.STATUS_CRC_MISMATCH, C.STATUS_HEADER_INVALID) == (0, 1, 2)


def test_contract_literals_are_spelled_only_in_the_contract_module():
    found = []
    for pkg in ("eol_cal", "cli"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            if path == ROOT / "eol_cal" / "firmware" / "contract.py":
                continue
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                value = _literal(node)
                if value in CONTRACT_LITERALS:
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {CONTRACT_LITERALS[value]}")
    assert found == []


def test_the_c_code_takes_the_hall_convention_and_codes_from_the_header():
    header = (ROOT / "firmware_params" / "eol_param_block.h").read_text("utf-8")
    nxt = re.search(r"#define EOL_PB_HALL_NEXT \{([^}]*)\}", header)
    assert nxt and tuple(int(x) for x in nxt.group(1).split(",")) == C.HALL_NEXT
    nominal = re.search(r"#define EOL_PB_HALL_ANGLE_NOMINAL \{([^}]*)\}", header)
    assert nominal, "no EOL_PB_HALL_ANGLE_NOMINAL"
    # the C literals round to the binary32 of the contract's angles
    got = np.array([float(x.strip().rstrip("f")) for x in nominal.group(1).split(",")], dtype=np.float32)
    np.testing.assert_array_equal(got, np.array(C.NOMINAL_HALL_ANGLE, dtype=np.float32))
    for name, status in C.CHECK_STATUS.items():
        assert re.search(rf"#define EOL_PB_STATUS_{name}\s+{status.code}u", header), name
    sources = {p.name: p.read_text("utf-8") for p in (ROOT / "firmware_params" / "c").glob("*.c")}
    assert "EOL_PB_HALL_NEXT" in sources["eol_est.c"]
    seq_c = "{" + ", ".join(map(str, C.HALL_NEXT)) + "}"
    assert all(seq_c not in text for text in sources.values())


def test_every_flag_bit_is_in_the_header_and_the_estimator_reads_the_contract_bits():
    header = (ROOT / "firmware_params" / "eol_param_block.h").read_text("utf-8")
    for name, flag in C.FLAGS.items():
        assert re.search(rf"#define EOL_PB_FLAG_{name}\s+\(UINT32_C\(1\) << {flag.bit}\)", header), name
    assert re.search(rf"#define EOL_PB_FLAGS_ESTIMATOR\s+UINT32_C\(0x{C.FLAGS_ESTIMATOR:02X}\)", header)
    assert {n for n in C.FLAGS if n.startswith("EST_")} == set(C.ESTIMATOR_OPTIONS)
    # the C estimator has no option mask of its own: it tests the block's bits
    est_h = (ROOT / "firmware_params" / "c" / "eol_est.h").read_text("utf-8")
    est_c = (ROOT / "firmware_params" / "c" / "eol_est.c").read_text("utf-8")
    assert not re.search(r"#define EOL_EST_(CLAMP|LEARN|ACCEL)", est_h + est_c)
    for name in C.ESTIMATOR_OPTIONS:
        assert f"EOL_PB_FLAG_{name}" in est_c, name
