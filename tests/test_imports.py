"""The import structure: no import cycle among eol_cal and cli modules, and every module imports on
its own in a fresh interpreter.

The graph counts every import that runs (module level and inside functions, ``importlib.import_module``
with a literal name), not those under ``if TYPE_CHECKING``: with no cycle in it, any import inside a
function could move to the top of its module.
"""

from __future__ import annotations

import ast
import itertools
import subprocess
import sys
from pathlib import Path
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("eol_cal", "cli")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _under_type_checking(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> bool:
    while node in parents:
        node = parents[node]
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            return True
    return False


def _imported_names(node: ast.AST, module: str, is_pkg: bool, mods: dict[str, Path]) -> list[tuple[str, bool]]:
    """(module name, whether its parent packages are loaded too) for one import statement."""
    if isinstance(node, ast.Import):
        return [(a.name, True) for a in node.names]
    if isinstance(node, ast.ImportFrom):
        base = node.module or ""
        if node.level:
            pkg = module.split(".") if is_pkg else module.split(".")[:-1]
            pkg = pkg[: len(pkg) - (node.level - 1)]
            base = ".".join(pkg + ([base] if base else []))
        return [(base, True)] + [(f"{base}.{a.name}", True) for a in node.names if f"{base}.{a.name}" in mods]
    if (isinstance(node, ast.Call) and ast.unparse(node.func) in ("importlib.import_module", "import_module")
            and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
        return [(node.args[0].value, True)]
    return []


def import_graph() -> dict[str, dict[str, int]]:
    """module -> {imported module of this project: first line}, every import that runs."""
    mods = _modules()
    graph: dict[str, dict[str, int]] = {m: {} for m in mods}
    for module, path in mods.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
        for node in ast.walk(tree):
            names = _imported_names(node, module, path.name == "__init__.py", mods)
            if not names or _under_type_checking(node, parents):
                continue
            for name, _ in names:
                chain = name.split(".")
                for i in range(1, len(chain) + 1):
                    target = ".".join(chain[:i])
                    # a parent package of the importer is already being loaded: no edge to it
                    # unless it is the module named (``from pkg import name`` needs pkg/__init__)
                    own_parent = module.startswith(target + ".") and i < len(chain)
                    if target in mods and target != module and not own_parent:
                        graph[module].setdefault(target, node.lineno)
    return graph


def find_cycle(graph: dict[str, dict[str, int]]) -> list[str] | None:
    """One cycle as a list of modules (first == last), or None."""
    state: dict[str, int] = {}  # 1 on the current path, 2 done
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state:
                found = visit(n)
                if found:
                    return found
        stack.pop()
        state[m] = 2
        return None

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph)))
    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return None


def test_the_graph_sees_imports_at_every_level():
    """The graph is not empty by mistake: a module-level, a function-level and an importlib edge."""
    g = import_graph()
    assert "eol_cal.analysis.steady" in g["eol_cal.analysis.metrics"]  # module level
    assert "eol_cal.analysis.fit.motors" in g["eol_cal.station.run"]  # inside fit_motor
    assert find_cycle({"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b": 1}, "b": {}}) is None


def test_no_import_cycle():
    g = import_graph()
    cycle = find_cycle(g)
    assert cycle is None, "import cycle: " + " -> ".join(
        f"{a} (line {g[a][b]})" for a, b in itertools.pairwise(cycle)) + f" -> {cycle[-1]}"


@pytest.mark.slow
def test_every_module_imports_first_in_a_fresh_interpreter():
    """Each module imported as the first of the project's modules (the others dropped from
    ``sys.modules`` in between; third-party packages stay loaded, so this takes seconds)."""
    code = (
        "import importlib, sys\n"
        "bad = []\n"
        "for m in sys.argv[1:]:\n"
        "    for k in [k for k in sys.modules if k.split('.')[0] in ('eol_cal', 'cli')]:\n"
        "        del sys.modules[k]\n"
        "    try:\n"
        "        importlib.import_module(m)\n"
        "    except Exception as exc:\n"
        "        bad.append(f'{m}: {type(exc).__name__}: {exc}')\n"
        "print('\\n'.join(bad))\n"
        "sys.exit(1 if bad else 0)\n"
    )
    mods = sorted(_modules())
    assert len(mods) > 100
    r = subprocess.run([sys.executable, "-c", code, *mods], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]
