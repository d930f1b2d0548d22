"""The import structure: no import cycle among eol_cal and cli modules, and every module imports on
its own in a fresh interpreter.

The graph counts every import that runs (module level and inside functions, ``importlib.import_module``
with a literal name), not those under ``if TYPE_CHECKING``: with no cycle in it, any import inside a
function could move to the top of its module. A second graph adds the imports under ``if
TYPE_CHECKING`` (a reader follows those too): no module imports upwards in it, and it holds no cycle
but those of :data:`TYPE_ONLY_CYCLES_LEFT`.
"""

from __future__ import annotations

import ast
import functools
import itertools
import re
import subprocess
import sys
from pathlib import Path
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("eol_cal", "cli")
#: the benchmarks: scripts run from their directory (``python bench/bench_x.py``), so each is a
#: top-level module by its file's name, and one imports another by that name
BENCH = ROOT / "bench"


@functools.cache
def _modules(bench: bool = True) -> dict[str, Path]:
    """module name -> file, of the packages and (``bench``) the benchmark scripts (read, never changed:
    every test here shares it)."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    if bench:
        out.update({path.stem: path for path in sorted(BENCH.glob("*.py"))})
    return out


@functools.cache
def _parsed(path: Path) -> tuple[ast.Module, dict[ast.AST, ast.AST]]:
    """A file's tree and each node's parent, parsed once for all the tests here (they walk every
    module of the project several times)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return tree, {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}


def _dotted(node: ast.AST) -> str:
    """``a.b.c`` for a name or an attribute chain on a name, else ``""`` (cheaper than ``ast.unparse``,
    which the walk would call for every call in the project)."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        base = _dotted(node.value)
        return f"{base}.{node.attr}" if base else ""
    return ""


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
    if (isinstance(node, ast.Call) and _dotted(node.func) in ("importlib.import_module", "import_module")
            and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
        return [(node.args[0].value, True)]
    return []


@functools.cache
def import_graph(type_only: bool = False) -> dict[str, dict[str, int]]:
    """module -> {imported module of this project: first line}, every import that runs (and with
    ``type_only`` those under ``if TYPE_CHECKING``). Shared by the tests here: read it, never change it."""
    mods = _modules()
    graph: dict[str, dict[str, int]] = {m: {} for m in mods}
    for module, path in mods.items():
        tree, parents = _parsed(path)
        for node in ast.walk(tree):
            names = _imported_names(node, module, path.name == "__init__.py", mods)
            if not names or (_under_type_checking(node, parents) and not type_only):
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


def package_of(module: str) -> str:
    """``eol_cal.records`` for ``eol_cal.records.query``; ``eol_cal`` for a module at the root; ``cli``."""
    parts = module.split(".")
    if parts[0] != "eol_cal" or len(parts) < 2 or not (ROOT / "eol_cal" / parts[1]).is_dir():
        return parts[0]
    return ".".join(parts[:2])


def test_no_import_cycle_between_packages():
    """Folder by folder the arrows point one way (a reader follows them down): the graph of the
    packages, every import that runs, has no cycle (records below report, lot and msa; the
    station's cycle above them)."""
    g = import_graph()
    packages: dict[str, dict[str, int]] = {}
    where: dict[tuple[str, str], str] = {}
    for a, deps in g.items():
        for b, line in deps.items():
            pa, pb = package_of(a), package_of(b)
            if pa != pb:
                packages.setdefault(pa, {}).setdefault(pb, line)
                packages.setdefault(pb, {})
                where.setdefault((pa, pb), f"{a} (line {line}) imports {b}")
    cycle = find_cycle(packages)
    assert cycle is None, "package cycle: " + "; ".join(where[(a, b)] for a, b in itertools.pairwise(cycle))
    assert "eol_cal.station" not in packages["eol_cal.records"] and "eol_cal.records" in packages["eol_cal.lot"]


#: Cycles that close only through an import under ``if TYPE_CHECKING``, as sets of modules. The list
#: only shrinks, and is empty: the last (the fit's capture module and its fingerprint angle, both
#: naming ``MotorInput``) went when the type moved below both, into ``eol_cal.analysis.fit.motor_input``.
TYPE_ONLY_CYCLES_LEFT: set[frozenset[str]] = set()


def strongly_connected(graph: dict[str, dict[str, int]]) -> list[frozenset[str]]:
    """The graph's strongly connected parts of more than one module (each holds a cycle)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[frozenset[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = {stack.pop()}
            while v not in part:
                part.add(stack.pop())
            if len(part) > 1:
                out.append(frozenset(part))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph)))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycle_type_only_imports_included():
    """The dyno simulator and its register side imported each other under TYPE_CHECKING until
    2026-11-28; a reader following the imports meets no such loop now but the listed ones."""
    found = set(strongly_connected(import_graph(type_only=True)))
    assert strongly_connected({"a": {"b": 1}, "b": {"a": 2}, "c": {"a": 3}}) == [frozenset({"a", "b"})]
    assert found - TYPE_ONLY_CYCLES_LEFT == set(), "a new cycle through type-only imports"
    assert TYPE_ONLY_CYCLES_LEFT - found == set(), "gone now: drop it from TYPE_ONLY_CYCLES_LEFT"


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
    mods = sorted(_modules(bench=False))  # a benchmark script runs when imported
    assert len(mods) > 100
    r = subprocess.run([sys.executable, "-c", code, *mods], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]


#: The layers docs/architecture.md draws, lowest first: a module imports only from its own layer
#: and the layers below (every import that runs, as in the cycle test). First pattern that matches;
#: ``*`` stands for one part of a dotted name, ``**`` for any number.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    # the root holds only the package, its public errors and how python-can is imported; the shared
    # pieces by kind, each on the ones above
    ("infrastructure", ("eol_cal", "eol_cal.errors", "eol_cal.python_can", "eol_cal.infra", "eol_cal.infra.**")),
    ("numerics", ("eol_cal.numerics", "eol_cal.numerics.**")),
    ("rendering", ("eol_cal.rendering", "eol_cal.rendering.**")),
    # the hardware under test (motor data sheet, bench mechanics); the data packages (TOML files) with it
    ("domain", ("eol_cal.domain", "eol_cal.domain.**", "eol_cal.schemas", "eol_cal.benches", "eol_cal.motors",
                "eol_cal.profiles", "eol_cal.spreads")),
    ("firmware twin", ("eol_cal.firmware", "eol_cal.firmware.**")),
    ("capture", ("eol_cal.capture", "eol_cal.capture.**")),
    ("analysis and plant", ("eol_cal.analysis", "eol_cal.analysis.**", "eol_cal.plant", "eol_cal.plant.**")),
    ("instruments", ("eol_cal.dyno", "eol_cal.dyno.**", "eol_cal.ecu", "eol_cal.ecu.**")),
    # what stands in for the plant floor: the rig, loopback stations, the ECU test rig, hostile inputs
    ("simulators", ("eol_cal.sim", "eol_cal.sim.rig", "eol_cal.sim.loopback", "eol_cal.sim.remote_ecu",
                    "eol_cal.sim.virtual_rig", "eol_cal.sim.postgres", "eol_cal.sim.mech_motors", "eol_cal.sim.fuzz",
                    "eol_cal.sim.fuzz.campaign", "eol_cal.sim.fuzz.hostile", "eol_cal.sim.fuzz.mutate")),
    ("records", ("eol_cal.records", "eol_cal.records.**")),
    # realistic run records and lots of them (the records a line would have written)
    ("simulated records", ("eol_cal.sim.run_records", "eol_cal.sim.lot_records")),
    ("pages and statistics", ("eol_cal.report", "eol_cal.report.**", "eol_cal.msa", "eol_cal.msa.**", "eol_cal.lot",
                              "eol_cal.lot.**")),
    ("station", ("eol_cal.station", "eol_cal.station.**")),
    # the station's instruments on the plant in-process (a what-if lot's motors): the seam's other side
    ("what-if instruments", ("eol_cal.sim.plant_instruments",)),
    # the operator panel and the line view: the station's cycle and the records, served to a browser
    ("operator panel", ("eol_cal.panel", "eol_cal.panel.**")),
    # a fault scenario builds a station's files (limits, a records database) to attack
    ("fault scenarios", ("eol_cal.sim.fuzz.scenarios", "eol_cal.sim.fuzz.scenarios_gate", "eol_cal.sim.fuzz.scenarios_harden")),
    ("command line", ("cli", "cli.**")),
    # bench/: the scripts use the library and the CLI as a user would, and nothing imports them
    ("benchmarks", ("bench_*", "check_*", "trace_*")),
]


@functools.cache
def _pattern(p: str) -> re.Pattern[str]:
    return re.compile(re.escape(p).replace(r"\*\*", ".*").replace(r"\*", "[^.]*") + "$")


@functools.cache
def layer_of(module: str) -> int:
    packages = {f"eol_cal.{d.name}" for d in (ROOT / "eol_cal").iterdir() if (d / "__init__.py").exists()}
    for i, (_, patterns) in enumerate(LAYERS):
        if any(p == module or ("*" in p and module not in packages and _pattern(p).match(module)) for p in patterns):
            return i
    raise LookupError(f"{module}: in no layer of tests/test_imports.py LAYERS (and docs/architecture.md)")


def test_every_module_has_a_layer():
    assert [m for m in _modules() if not _has_layer(m)] == []
    assert layer_of("eol_cal.errors") == 0 and layer_of("eol_cal.station.cycle") > layer_of("eol_cal.records.record")


def test_the_architecture_page_draws_these_layers():
    """docs/architecture.md draws the layers top first, one line each, as :data:`LAYERS` holds them."""
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    block = text[text.index("\n## Layers"):text.index("\n## Shared pieces")]
    names = [name for name, _ in LAYERS]
    drawn = [line[4:25].strip() for line in block.splitlines() if line.startswith("    ") and line[4:25].strip()]
    assert drawn == names[::-1]


def _has_layer(module: str) -> bool:
    try:
        layer_of(module)
    except LookupError:
        return False
    return True


def test_imports_follow_the_layers():
    """No module imports from a layer above its own (the order docs/architecture.md draws), the
    imports under ``if TYPE_CHECKING`` included."""
    g = import_graph(type_only=True)
    upward = [f"{a} ({LAYERS[layer_of(a)][0]}, line {line}) imports {b} ({LAYERS[layer_of(b)][0]})"
              for a, deps in sorted(g.items()) for b, line in sorted(deps.items()) if layer_of(b) > layer_of(a)]
    assert upward == []


def test_the_library_does_not_import_its_simulators():
    """What stands in for the plant floor (``eol_cal.sim``) is scaffolding: the library outside it
    never imports it, type-only imports included; the CLI's simulator commands and bench/ do."""
    g = import_graph(type_only=True)
    found = [f"{a} (line {line}) imports {b}" for a, deps in sorted(g.items()) if a.startswith("eol_cal.")
             and not (a + ".").startswith("eol_cal.sim.") for b, line in sorted(deps.items())
             if (b + ".").startswith("eol_cal.sim.")]
    assert found == []


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_uses(module: str, path: Path) -> list[str]:
    """``from x import _name`` of the project's modules, and ``alias._name`` on a module of the
    project bound by an import (``from eol_cal.a import b as m; m._f()``)."""
    tree, _ = _parsed(path)
    mods = _modules()
    found, aliases = [], set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in PACKAGES + ("bench",):
            found += [f"{module} (line {node.lineno}): from {node.module} import {a.name}" for a in node.names
                      if _private(a.name)]
            aliases |= {a.asname or a.name for a in node.names if f"{node.module}.{a.name}" in mods}
        elif isinstance(node, ast.Import):
            aliases |= {a.asname or a.name for a in node.names if a.name in mods and (a.asname or "." not in a.name)}
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and _private(node.attr) and isinstance(node.value, ast.Name)
                and node.value.id in aliases):
            found.append(f"{module} (line {node.lineno}): {node.value.id}.{node.attr}")
    return found


def test_no_private_name_imported_across_modules():
    """A private name (``_x``) is its module's own: no other module of the project, and no
    benchmark, imports it or reaches it through the module."""
    found = [use for module, path in _modules().items() for use in private_uses(module, path)]
    assert found == []


def test_private_uses_are_found():
    """The check above is not empty by mistake: an import and an attribute of a module alias."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        probe = Path(tmp, "probe.py")
        probe.write_text("from eol_cal.analysis import fingerprint as fpr\nfrom eol_cal.errors import _x\n"
                         "import eol_cal.ecu.session as session\nfpr._f(); session._g; fpr.public\n")
        assert sorted(u.split(": ")[1] for u in private_uses("probe", probe)) == [
            "fpr._f", "from eol_cal.errors import _x", "session._g"]


def _sys_path_edits(path: Path) -> list[str]:
    if "sys.path" not in path.read_text(encoding="utf-8"):
        return []
    tree, _ = _parsed(path)
    return [f"{path.relative_to(ROOT)} (line {node.lineno}): {ast.unparse(node)[:80]}" for node in ast.walk(tree)
            if isinstance(node, (ast.Call, ast.Assign, ast.AugAssign))
            and "sys.path" in ast.unparse(node.func if isinstance(node, ast.Call) else node)
            and not (isinstance(node, ast.Call) and ast.unparse(node.func) in ("os.pathsep.join",))]


def test_no_sys_path_edits_in_bench_or_tests():
    """bench/ and tests/ import the library as a user would (``eol_cal.sim`` for what stands in for
    the plant floor): nothing puts a directory on ``sys.path``."""
    files = sorted(BENCH.glob("*.py")) + sorted((ROOT / "tests").glob("*.py"))
    assert [e for f in files for e in _sys_path_edits(f)] == []


#: Imported inside functions on purpose: each costs a second or more, or brings a server's client
#: (and what imports them at module level is heavy in turn). scipy: its signal, interpolate and
#: linalg modules, which the analysis uses, cost as much as asammdf together (`python -X importtime`,
#: docs/benchmarks.md "Takt time"), and `eol-cal run` paid them before its cycle started. psycopg (the
#: PostgreSQL driver, 1.4 s): only eol_cal.sim.postgres names it, SQLAlchemy loads it for a postgresql:// URL.
#: pint (1.3 s, `python -X importtime -c "import pint"`): the units of a capture file's columns.
HEAVY = ("jax", "jaxlib", "matplotlib", "distributed", "dask", "asammdf", "optimistix", "equinox", "lineax",
         "sqlalchemy", "psycopg", "pint", "scipy")

#: Library modules that still import light modules inside functions. The branches in flight
#: (station cycle and dyno; inputs and UDS) edit them: their imports move to the top after those
#: merges. The list only shrinks (the test fails on a module listed here that is already clean).
LAZY_ON_PURPOSE = {
    "eol_cal.numerics.blas": "numpy's BLAS loaded and limited only when no thread variable is set, at the CLI's start",
}

LAZY_LEFT = frozenset({
    "eol_cal.analysis.analyze", "eol_cal.analysis.fit.capture", "eol_cal.analysis.fit.motors",
    "eol_cal.analysis.fit.plot", "eol_cal.analysis.fit.prewarm", "eol_cal.analysis.fit.table",
    "eol_cal.analysis.result", "eol_cal.capture.ecu_state", "eol_cal.capture.io", "eol_cal.dyno.client",
    "eol_cal.dyno.sim_modbus", "eol_cal.dyno.transfer", "eol_cal.lot.cluster", "eol_cal.lot.runs",
    "eol_cal.lot.lot_page", "eol_cal.lot.refit", "eol_cal.records.limits", "eol_cal.report.motor_page", "eol_cal.schemas",
    "eol_cal.station.configure", "eol_cal.station.early", "eol_cal.station.preflight", "eol_cal.station.restore",
    "eol_cal.station.run", "eol_cal.station.settings", "eol_cal.station.whatif",
})


#: how many modules LAZY_LEFT holds. It only goes down: lower it with the list (the test below
#: fails until you do); a module that would join the list imports at its top instead.
LAZY_LEFT_COUNT = 26


def test_lazy_left_only_shrinks():
    assert len(LAZY_LEFT) <= LAZY_LEFT_COUNT, "LAZY_LEFT may only shrink: import at the module's top instead"
    assert len(LAZY_LEFT) == LAZY_LEFT_COUNT, f"LAZY_LEFT shrank to {len(LAZY_LEFT)}: lower LAZY_LEFT_COUNT with it"


def _in_function(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> bool:
    while node in parents:
        node = parents[node]
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            return True
    return False


def lazy_light_imports() -> dict[str, list[str]]:
    """library module -> its imports inside functions of modules that are not heavy (:data:`HEAVY`,
    or a module of this project that imports one at its top, directly or through others)."""
    mods = _modules()
    top_ours: dict[str, set[str]] = {}
    top_theirs: dict[str, set[str]] = {}
    inside: dict[str, list[tuple[int, str]]] = {}
    for module, path in mods.items():
        tree, parents = _parsed(path)
        top_ours[module], top_theirs[module], inside[module] = set(), set(), []
        for node in ast.walk(tree):
            names = _imported_names(node, module, path.name == "__init__.py", mods)
            if not names or _under_type_checking(node, parents):
                continue
            for name, _ in names:
                ours = name.split(".")[0] in PACKAGES
                target = next((".".join(name.split(".")[:i]) for i in range(name.count(".") + 1, 0, -1)
                               if ".".join(name.split(".")[:i]) in mods), None) if ours else name.split(".")[0]
                if target is None or target == module:  # a package importing its own modules
                    continue
                if _in_function(node, parents):
                    inside[module].append((node.lineno, target))
                else:
                    (top_ours if ours else top_theirs)[module].add(target)

    @functools.cache
    def heavy(module: str) -> bool:
        return bool(top_theirs.get(module, set()) & set(HEAVY)) or any(heavy(m) for m in top_ours.get(module, ()))

    out: dict[str, list[str]] = {}
    for module, found in inside.items():
        light = [f"line {line}: {t}" for line, t in found if not (heavy(t) if t in mods else t in HEAVY)]
        if module.startswith("eol_cal") and light:
            out[module] = light
    return out


def test_library_imports_at_module_top():
    """A library module imports at its top, but for the heavy ones: the real dependency graph is
    the one a reader sees (the CLI's commands keep importing lazily: ``eol-cal --help`` stays quick)."""
    found = lazy_light_imports()
    assert {m: v for m, v in found.items() if m not in LAZY_LEFT and m not in LAZY_ON_PURPOSE} == {}
    assert sorted(LAZY_LEFT - set(found)) == [], "clean now: drop from LAZY_LEFT"
