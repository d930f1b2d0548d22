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


#: a file of the repository named in a document: ``eol_cal/dyno/client.py``, ``cli/fit.py``,
#: ``eol_cal/motors/paper.toml``; placeholders (``cli/NAME.py``, ``tests/test_x.py``) are left out
PATH = re.compile(r"(?<![\w/.])((?:eol_cal|cli|bench|tests|scripts|firmware_params)/[\w/.-]*\w\.(?:py|toml|md|h|c))(?![\w.])")
#: in docs/architecture.md also a module named from inside the library (``station/steps/check_ready.py``)
SHORT = re.compile(r"`((?:[a-z_]+/)+[a-z_0-9]+\.py)`")


def _placeholder(path: str) -> bool:
    return any(part.isupper() for part in re.split(r"[/.]", path)) or "test_x." in path


def test_the_docs_name_files_that_exist():
    """A module moved or renamed takes the documents with it (the history under docs/history/ keeps
    the names of its day): every file path a document names is there."""
    missing = []
    for p in _tracked():
        rel = p.relative_to(ROOT).as_posix()
        if p.suffix != ".md" or rel.startswith("docs/history/"):
            continue
        text = p.read_text()
        for path in set(PATH.findall(text)) - {x for x in PATH.findall(text) if _placeholder(x)}:
            if not (ROOT / path).exists():
                missing.append(f"{rel}: {path}")
        if rel == "docs/architecture.md":
            missing += [f"{rel}: {s}" for s in set(SHORT.findall(text)) if not (ROOT / s).exists()
                        and not (ROOT / "eol_cal" / s).exists() and not _placeholder(s)]
    assert sorted(missing) == []
