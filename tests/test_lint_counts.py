"""Counts of the linters' exemptions that only go down: the mypy error codes the modules' own headers
disable (``# mypy: disable-error-code=...``), against the number recorded in pyproject.toml
(scripts/lint_baseline.py counts them and names a code a header no longer needs). ``LAZY_LEFT``'s
count is held in tests/test_imports.py."""

from __future__ import annotations

import runpy
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _baseline_tool() -> dict:
    """scripts/lint_baseline.py's functions (a script, not a module of the package)."""
    return runpy.run_path(str(ROOT / "scripts" / "lint_baseline.py"))


def test_the_header_exemptions_only_shrink():
    tool = _baseline_tool()
    headers = tool["header_exemptions"]()
    n = sum(len(codes) for codes in headers.values())
    recorded = tool["recorded_header_count"]((ROOT / "pyproject.toml").read_text("utf-8"))
    assert recorded is not None, "pyproject.toml records no count of the header exemptions"
    assert n <= recorded, (f"module headers disable {n} mypy error codes, {recorded} recorded: a module's header "
                           f"may only lose codes ({ {m: sorted(c) for m, c in headers.items()} })")
    assert n == recorded, f"module headers disable {n} error codes now: record it (scripts/lint_baseline.py --write)"


def test_the_header_exemptions_are_found():
    """The count is not zero by mistake: the firmware twin's array-generic modules hold them."""
    headers = _baseline_tool()["header_exemptions"]()
    assert "eol_cal.firmware.estimator_step" in headers and "index" in headers["eol_cal.firmware.estimator_step"]


#: modules of the library and the CLI longer than :data:`MAX_LINES`, each to be split along a concept
#: (not by line count); the list only shrinks, and is empty: a module that grows past the limit is split
LONG_LEFT: frozenset[str] = frozenset()
MAX_LINES = 500


def test_no_module_grows_over_500_lines():
    long = {p.relative_to(ROOT).as_posix() for d in ("eol_cal", "cli") for p in (ROOT / d).rglob("*.py")
            if len(p.read_text("utf-8").splitlines()) > MAX_LINES}
    assert long - LONG_LEFT == set(), f"over {MAX_LINES} lines: split it along a concept"
    assert LONG_LEFT - long == set(), "short enough now: drop it from LONG_LEFT"
