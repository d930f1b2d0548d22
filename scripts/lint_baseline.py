"""The linters' baseline: which files (ruff) and modules (mypy) still hold findings from before
the linters were configured, by rule.

New code is checked in full; a file or module listed here is excused only the rules it broke on
the day it was listed. The lists live in ``pyproject.toml`` between the ``# lint-baseline``
markers and are meant to shrink: fix a file, then run ``--write`` and commit the shorter list.

    python scripts/lint_baseline.py            # counts: findings per rule, excused and not
    python scripts/lint_baseline.py --check    # exit 1 when an entry excuses what is no longer there
    python scripts/lint_baseline.py --write    # rewrite both lists from today's findings

A module may also disable mypy error codes in its own header (``# mypy: disable-error-code=...``,
with the reason above it: the firmware twin's array-generic modules). Those are counted here too
(:func:`header_exemptions`), ``--check`` names a code a header disables that the module no longer
needs, and the number they add up to is recorded in ``pyproject.toml`` (``HEADER_MARK``), which
``tests/test_lint_counts.py`` holds it to: it only goes down.

``--write`` on code that gained findings silences them: use it only to shrink the lists, or for a
merge of work written before the linters, and say so in the commit.
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = ROOT / "pyproject.toml"
RUFF_BEGIN, RUFF_END = "# lint-baseline: ruff begin", "# lint-baseline: ruff end"
MYPY_BEGIN, MYPY_END = "# lint-baseline: mypy begin", "# lint-baseline: mypy end"
MYPY_LINE = re.compile(r"^(?P<path>[^:]+\.py):\d+: error: .*\[(?P<code>[a-z-]+)\]$")
#: a module's own exemption, in its header
HEADER = re.compile(r'^# mypy: disable-error-code="(?P<codes>[^"]*)"$', re.M)
#: the line of pyproject.toml that records how many error codes module headers disable
HEADER_MARK = re.compile(r"^# lint-baseline: mypy headers disable (?P<n>\d+) error codes$", re.M)


def _ruff(baseline: dict[str, set[str]]) -> dict[str, set[str]]:
    """Ruff's findings with the listed baseline replaced by ``baseline``."""
    table = "{" + ", ".join(f"{json.dumps(str(ROOT / p))} = {json.dumps(sorted(c))}"
                            for p, c in baseline.items()) + "}"
    with tempfile.TemporaryDirectory() as tmp:  # an override merges with the table: drop it from a copy
        cfg = Path(tmp) / "pyproject.toml"
        cfg.write_text(_replace(PYPROJECT.read_text("utf-8"), RUFF_BEGIN, RUFF_END, ""), "utf-8")
        out = subprocess.run(
            [sys.executable, "-m", "ruff", "check", "--output-format", "json", "--exit-zero", "--no-cache",
             "--config", str(cfg), "--config", f"lint.extend-per-file-ignores = {table}", "."],
            cwd=ROOT, capture_output=True, text=True, check=True).stdout
    found: dict[str, set[str]] = collections.defaultdict(set)
    for f in json.loads(out):
        found[Path(f["filename"]).resolve().relative_to(ROOT).as_posix()].add(f["code"])
    return dict(found)


def ruff_findings() -> dict[str, set[str]]:
    """file (relative, posix) -> the rule codes ruff finds in it with the configured rule set and
    no baseline (and the RUF100 that excusing a rule gives a ``noqa`` of that rule)."""
    found = _ruff({})
    for _ in range(3):
        more = _ruff(found)
        if not more:
            break
        for path, codes in more.items():
            found.setdefault(path, set()).update(codes)
    return found


def _module(path: str) -> str:
    parts = list(Path(path).with_suffix("").parts)
    if parts[0] == "bench":  # a script: a top-level module of its directory
        return parts[-1]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _mypy(baseline: dict[str, set[str]], tmp: Path) -> dict[str, set[str]]:
    """mypy's findings with the listed baseline replaced by ``baseline``."""
    cfg = tmp / "pyproject.toml"  # mypy reads one config file: a copy with ``baseline`` as the list
    cfg.write_text(_replace(PYPROJECT.read_text("utf-8"), MYPY_BEGIN, MYPY_END, render_mypy(baseline)), "utf-8")
    r = subprocess.run([sys.executable, "-m", "mypy", "--config-file", str(cfg), "--cache-dir", str(tmp / "cache")],
                       cwd=ROOT, capture_output=True, text=True)  # the files the configuration names
    found: dict[str, set[str]] = collections.defaultdict(set)
    for line in r.stdout.splitlines():
        m = MYPY_LINE.match(line)
        if m:
            found[_module(m["path"])].add(m["code"])
    if r.returncode not in (0, 1) or (r.returncode == 1 and not found):
        raise SystemExit(f"mypy did not run: {r.stdout[-2000:]}{r.stderr[-2000:]}")
    return dict(found)


def mypy_findings() -> dict[str, set[str]]:
    """module -> the error codes mypy finds in it with the configured settings and no baseline (and
    the unused-ignore that excusing a code gives a ``type: ignore`` of that code)."""
    with tempfile.TemporaryDirectory() as tmp:
        found = _mypy({}, Path(tmp))
        for _ in range(3):
            more = _mypy(found, Path(tmp))
            if not more:
                break
            for module, codes in more.items():
                found.setdefault(module, set()).update(codes)
    return found


def mypy_files() -> list[Path]:
    """The Python files mypy checks (``[tool.mypy] files`` of pyproject.toml)."""
    files = tomllib.loads(PYPROJECT.read_text("utf-8"))["tool"]["mypy"]["files"]
    return sorted(p for f in files for p in ((ROOT / f).rglob("*.py") if (ROOT / f).is_dir() else [ROOT / f]))


def header_exemptions() -> dict[str, set[str]]:
    """module -> the error codes its header disables (``# mypy: disable-error-code="..."``)."""
    out = {}
    for path in mypy_files():
        m = HEADER.search(path.read_text("utf-8"))
        if m:
            out[_module(path.relative_to(ROOT).as_posix())] = {c.strip() for c in m["codes"].split(",") if c.strip()}
    return out


def header_findings() -> dict[str, set[str]]:
    """module -> the error codes mypy finds in the modules with a header exemption when their
    headers are left out (one run, each such file replaced by a copy without its header through
    mypy's ``--shadow-file``): what the headers still have to disable."""
    with tempfile.TemporaryDirectory() as tmp:
        shadows = []
        for path in mypy_files():
            text = path.read_text("utf-8")
            if HEADER.search(text):
                shadow = Path(tmp) / f"{len(shadows)}.py"
                shadow.write_text(HEADER.sub("", text), "utf-8")
                shadows += ["--shadow-file", str(path), str(shadow)]
        r = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(Path(tmp) / "cache"), *shadows],
                           cwd=ROOT, capture_output=True, text=True)
    found: dict[str, set[str]] = collections.defaultdict(set)
    for line in r.stdout.splitlines():
        m = MYPY_LINE.match(line)
        if m:
            found[_module(m["path"])].add(m["code"])
    if r.returncode not in (0, 1):
        raise SystemExit(f"mypy did not run: {r.stdout[-2000:]}{r.stderr[-2000:]}")
    return dict(found)


def recorded_header_count(text: str) -> int | None:
    m = HEADER_MARK.search(text)
    return int(m["n"]) if m else None


def _replace(text: str, begin: str, end: str, body: str) -> str:
    i, j = text.index(begin), text.index(end)
    return text[: i + len(begin)] + "\n" + body + text[j:]


def _section(text: str, begin: str, end: str) -> str:
    return text[text.index(begin) + len(begin): text.index(end)]


def render_ruff(found: dict[str, set[str]]) -> str:
    return "".join(f'"{path}" = [{", ".join(json.dumps(c) for c in sorted(codes))}]\n'
                   for path, codes in sorted(found.items()))


def render_mypy(found: dict[str, set[str]]) -> str:
    groups: dict[tuple[str, ...], list[str]] = collections.defaultdict(list)
    for module, codes in found.items():
        groups[tuple(sorted(codes))].append(module)
    out = []
    for codes, modules in sorted(groups.items(), key=lambda kv: sorted(kv[1])[0]):
        out.append("[[tool.mypy.overrides]]\n"
                   f"module = [{', '.join(json.dumps(m) for m in sorted(modules))}]\n"
                   f"disable_error_code = [{', '.join(json.dumps(c) for c in codes)}]\n")
    return "\n".join(out)


def listed_ruff(text: str) -> dict[str, set[str]]:
    out = {}
    for line in _section(text, RUFF_BEGIN, RUFF_END).splitlines():
        if "=" in line and not line.lstrip().startswith("#"):
            path, codes = line.split("=", 1)
            out[json.loads(path.strip())] = set(json.loads(codes))
    return out


def listed_mypy(text: str) -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    modules: list[str] = []
    for line in _section(text, MYPY_BEGIN, MYPY_END).splitlines():
        if line.startswith("module ="):
            modules = json.loads(line.split("=", 1)[1])
        elif line.startswith("disable_error_code ="):
            for m in modules:
                out[m] = set(json.loads(line.split("=", 1)[1]))
    return out


def stale(listed: dict[str, set[str]], found: dict[str, set[str]]) -> list[str]:
    """Entries that excuse a rule the file or module no longer breaks."""
    return [f"{name}: {', '.join(sorted(codes - found.get(name, set())))}"
            for name, codes in sorted(listed.items()) if codes - found.get(name, set())]


def counts(found: dict[str, set[str]], tool: str) -> str:
    per_rule = collections.Counter(c for codes in found.values() for c in codes)
    return f"{tool}: {len(found)} files excused; per rule (files): " + ", ".join(
        f"{c} {n}" for c, n in per_rule.most_common())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when the lists excuse more than is found")
    ap.add_argument("--write", action="store_true", help="rewrite both lists from today's findings")
    ap.add_argument("--ruff-only", action="store_true", help="skip mypy (seconds instead of a minute)")
    args = ap.parse_args(argv)
    text = PYPROJECT.read_text("utf-8")
    rf = ruff_findings()
    mf = {} if args.ruff_only else mypy_findings()
    headers = header_exemptions()
    n_headers = sum(len(c) for c in headers.values())
    if args.write:
        text = _replace(text, RUFF_BEGIN, RUFF_END, render_ruff(rf))
        if not args.ruff_only:
            text = _replace(text, MYPY_BEGIN, MYPY_END, render_mypy(mf))
        text = HEADER_MARK.sub(f"# lint-baseline: mypy headers disable {n_headers} error codes", text)
        PYPROJECT.write_text(text, "utf-8")
    print(counts(rf, "ruff"))
    if not args.ruff_only:
        print(counts(mf, "mypy"))
    print(counts(headers, "mypy module headers").replace("files excused", "modules disable")
          + f"; {n_headers} error codes in all (recorded: {recorded_header_count(text)})")
    if args.check:
        bad = stale(listed_ruff(text), rf) + ([] if args.ruff_only else stale(listed_mypy(text), mf))
        if not args.ruff_only:
            bad += [f"header of {s}" for s in stale(headers, header_findings())]
        if bad:
            print("baseline excuses what is fixed (run python scripts/lint_baseline.py --write):\n  "
                  + "\n  ".join(bad))
            return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
