"""Nothing in the repository points outside it; the docs' relative links resolve."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TEXT = (".py", ".md", ".toml", ".h", ".c", ".j2", ".txt", ".cfg", ".ini", ".json")
OUTSIDE = re.compile(r"\.\./shared|(?<![\w.])shared/(capture-format|firmware-contract|design)\.md|/work/")


def _tracked() -> list[Path]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return [ROOT / line for line in out.splitlines() if line.endswith(TEXT) and (ROOT / line).is_file()]


def test_no_reference_outside_the_repository():
    hits = [f"{p.relative_to(ROOT)}:{n}" for p in _tracked() if p.name != "test_docs_links.py"
            for n, line in enumerate(p.read_text(errors="replace").splitlines(), 1) if OUTSIDE.search(line)]
    assert hits == []


def test_markdown_links_resolve():
    broken = []
    for p in _tracked():
        if p.suffix != ".md":
            continue
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", p.read_text()):
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (p.parent / target).resolve().exists():
                broken.append(f"{p.relative_to(ROOT)} -> {target}")
    assert broken == []
