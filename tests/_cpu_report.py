"""Where the suite's CPU goes: a pytest plugin that writes each test's CPU seconds.

The whole suite on a loaded machine is bounded by its CPU seconds, not its quiet wall time: at load
16 on 2 cores each of the two workers gets about 1/8 of a core. This plugin is off unless asked::

    EOL_CAL_TEST_CPU=DIR python -m pytest -q -n 2     # tests/conftest.py registers it
    python tests/_cpu_report.py DIR [TOP]          # per file, the largest first, and the totals
    python tests/_cpu_report.py DIR --table        # tests/schedule_cpu.txt (tests/_schedule.py)

``EOL_CAL_TEST_CPU_COMPILES=1`` beside it also counts XLA's compilations per program name (JAX's
``jax_log_compiles``, read from its log in the workers): which programs a cold cache compiles, how
often and how long; the summary lists the costliest.

Each worker (or the one process of a serial run) writes ``DIR/<worker>.json``: per test id the
wall seconds and the CPU seconds (user + system) of the worker itself and of its children that
ended meanwhile (``RUSAGE_CHILDREN``: the CLI subprocesses, compilers, Chromium's driver and its
browser, servers stopped within the test), setup and teardown included (a module fixture's cost is
on the file's first test, its teardown on the last), plus the collection's CPU and, at the end,
what the processes still running under the worker had used. Not counted: a daemon that leaves the
tree (the PostgreSQL server ``pg_ctl`` starts, reparented to init); its own figures are small next
to its clients'.

Memory: after each test the worker's peak resident set so far (``ru_maxrss``); the summary names
the tests that raised a worker's peak the most (what a machine with less memory per worker meets).
"""

from __future__ import annotations

import json
import logging
import os
import re
import resource
import sys
import time
from collections import defaultdict
from collections.abc import Generator
from pathlib import Path

import pytest

_ENV = "EOL_CAL_TEST_CPU"
_COMPILES_ENV = "EOL_CAL_TEST_CPU_COMPILES"
#: JAX's log line for one compilation (jax._src.dispatch, with ``jax_log_compiles``)
_COMPILED = re.compile(r"Finished XLA compilation of (.+) in ([0-9.eE+-]+) sec")
_NAME = "eol-cal-cpu-report"


def _cpu() -> tuple[float, float]:
    """(this process's, its ended children's) user + system CPU seconds."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, kids.ru_utime + kids.ru_stime


class _Recorder:
    def __init__(self, out: Path) -> None:
        self.out = out
        self.worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        self.tests: dict[str, list[float]] = {}
        self.collection: tuple[float, float] = (0.0, 0.0)
        self.started = time.monotonic()
        # JAX's own figures (wall seconds of tracing, lowering and compiling; persistent-cache hits)
        self.jax: dict[str, float] = defaultdict(float)
        # per compiled program's name: [compilations, wall seconds] (EOL_CAL_TEST_CPU_COMPILES)
        self.programs: dict[str, list[float]] = defaultdict(lambda: [0, 0.0])

    def _jax_duration(self, event: str, duration: float, **_kw: object) -> None:
        self.jax[event.rsplit("/", 1)[-1]] += duration

    def _jax_event(self, event: str, **_kw: object) -> None:
        if event.endswith(("cache_hits", "cache_misses")):
            self.jax[event.rsplit("/", 1)[-1]] += 1

    @pytest.hookimpl(trylast=True)
    def pytest_collection_finish(self, session: pytest.Session) -> None:
        self.collection = _cpu()
        # registered after tests/conftest.py's configure set JAX's cache variables (JAX reads them
        # when imported)
        import jax.monitoring

        jax.monitoring.register_event_duration_secs_listener(self._jax_duration)
        jax.monitoring.register_event_listener(self._jax_event)
        if os.environ.get(_COMPILES_ENV):
            import jax

            jax.config.update("jax_log_compiles", True)
            logging.getLogger("jax._src.dispatch").addHandler(_ProgramTally(self.programs))

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item: pytest.Item) -> Generator[None, None, None]:
        t0, (own0, kids0), jax0 = time.monotonic(), _cpu(), dict(self.jax)
        yield
        t1, (own1, kids1) = time.monotonic(), _cpu()
        jax = {k: v - jax0.get(k, 0.0) for k, v in self.jax.items() if v != jax0.get(k, 0.0)}
        peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        self.tests[item.nodeid] = [t1 - t0, own1 - own0, kids1 - kids0, jax, peak_kb]

    def pytest_sessionfinish(self, session: pytest.Session) -> None:
        if self.worker == "main" and os.environ.get("PYTEST_XDIST_WORKER") is None and not self.tests:
            return  # the xdist controller: its workers report
        alive = 0.0
        try:
            import psutil

            for proc in psutil.Process().children(recursive=True):
                try:
                    c = proc.cpu_times()
                    alive += c.user + c.system
                except psutil.Error:
                    pass
        except ImportError:
            pass
        own, kids = _cpu()
        self.out.mkdir(parents=True, exist_ok=True)
        report = {
            "worker": self.worker,
            "wall_s": time.monotonic() - self.started,
            "cpu_own_s": own,
            "cpu_children_s": kids,
            "cpu_alive_children_s": alive,
            "collection_cpu_s": sum(self.collection),
            "tests": self.tests,
            "programs": self.programs,
        }
        tmp = self.out / f".{self.worker}.json.tmp"
        tmp.write_text(json.dumps(report))
        tmp.replace(self.out / f"{self.worker}.json")


class _ProgramTally(logging.Handler):
    """Counts JAX's "Finished XLA compilation of NAME in S sec" lines per NAME."""

    def __init__(self, programs: dict[str, list[float]]) -> None:
        super().__init__(logging.DEBUG)
        self.programs = programs

    def emit(self, record: logging.LogRecord) -> None:
        found = _COMPILED.search(record.getMessage())
        if found:
            tally = self.programs[found.group(1)]
            tally[0] += 1
            tally[1] += float(found.group(2))


def pytest_configure(config: pytest.Config) -> None:
    out = os.environ.get(_ENV)
    if out and not config.pluginmanager.has_plugin(_NAME):
        config.pluginmanager.register(_Recorder(Path(out)), _NAME)


def summarise(out: Path, top: int = 40) -> str:
    """Per file: wall, own CPU, children's CPU, JAX's compile wall seconds, tests; the largest CPU first."""
    files: dict[str, list[float]] = defaultdict(lambda: [0.0] * 6)
    tests: list[tuple[float, str]] = []
    lines = []
    total_own = total_kids = total_alive = total_coll = total_jax = 0.0
    programs: dict[str, list[float]] = defaultdict(lambda: [0, 0.0])
    raised: list[tuple[float, str]] = []  # (MiB the worker's peak rose in the test, test)
    for path in sorted(out.glob("*.json")):
        rep = json.loads(path.read_text())
        peak_kb = 0.0
        total_own += rep["cpu_own_s"]
        total_kids += rep["cpu_children_s"]
        total_alive += rep["cpu_alive_children_s"]
        total_coll += rep["collection_cpu_s"]
        for name, (count, seconds) in rep.get("programs", {}).items():
            programs[name][0] += count
            programs[name][1] += seconds
        for nodeid, (wall, own, kids, *more) in rep["tests"].items():
            jax = more[0] if more else {}
            if len(more) > 1:  # the worker's peak resident set after the test (KiB), so far
                raised.append(((more[1] - peak_kb) / 1024, nodeid))
                peak_kb = max(peak_kb, more[1])
            compile_s = sum(v for k, v in jax.items() if k.endswith("_duration"))
            total_jax += compile_s
            f = files[nodeid.split("::")[0]]
            for i, v in enumerate((wall, own, kids, compile_s, jax.get("cache_hits", 0.0), 1)):
                f[i] += v
            tests.append((own + kids, nodeid))
        lines.append(
            f"{rep['worker']}: wall {rep['wall_s']:.0f} s, own {rep['cpu_own_s']:.0f} CPU s "
            f"(collection {rep['collection_cpu_s']:.0f}), children {rep['cpu_children_s']:.0f} CPU s, "
            f"still running at the end {rep['cpu_alive_children_s']:.0f} CPU s"
            + (f", peak resident {peak_kb / 1024:.0f} MiB" if peak_kb else "")
        )
    lines.append(
        f"total: {total_own + total_kids + total_alive:.0f} CPU s (workers {total_own:.0f}, of it collection "
        f"{total_coll:.0f}; children {total_kids + total_alive:.0f}); JAX tracing, lowering and "
        f"compiling in the workers {total_jax:.0f} s wall"
    )
    head = ("file", "wall s", "own", "child", "cpu", "jax s", "hits", "tests")
    lines.append(f"{head[0]:52s}" + "".join(f"{h:>7s}" for h in head[1:]))
    ranked = sorted(files.items(), key=lambda kv: -(kv[1][1] + kv[1][2]))
    for name, (wall, own, kids, jax_s, hits, n) in ranked[:top]:
        figures = (wall, own, kids, own + kids, jax_s)
        lines.append(f"{name:52s}" + "".join(f"{v:7.1f}" for v in figures) + f"{int(hits):7d}{int(n):7d}")
    rest = ranked[top:]
    if rest:
        lines.append(f"{len(rest)} files more: {sum(v[1] + v[2] for _, v in rest):.0f} CPU s")
    if programs:
        lines.append(
            f"XLA compilations in the workers: {sum(c for c, _ in programs.values()):.0f}, "
            f"{sum(t for _, t in programs.values()):.0f} s wall; the costliest programs:"
        )
        for name, (count, seconds) in sorted(programs.items(), key=lambda kv: -kv[1][1])[:10]:
            lines.append(f"{seconds:7.1f} s {int(count):4d}x  {name}")
    if raised:
        lines.append("tests that raised their worker's peak resident set the most (MiB):")
        for mib, nodeid in sorted(raised, reverse=True)[:10]:
            lines.append(f"{mib:7.0f}  {nodeid}")
    lines.append("tests, the largest CPU first:")
    for cpu, nodeid in sorted(tests, reverse=True)[:top]:
        lines.append(f"{cpu:7.1f}  {nodeid}")
    return "\n".join(lines)


def table(out: Path, least_s: float = 5.0) -> str:
    """tests/schedule_cpu.txt from a whole run's figures: each scheduling unit's CPU seconds
    (tests/_schedule.py), those of at least ``least_s``, the costliest first."""
    from _schedule import unit

    units: dict[str, float] = defaultdict(float)
    for path in sorted(out.glob("*.json")):
        for nodeid, (_wall, own, kids, *_more) in json.loads(path.read_text())["tests"].items():
            units[unit(nodeid)] += own + kids
    lines = [
        "# CPU seconds of each scheduling unit of the whole suite (tests/_schedule.py), the costliest first;",
        "# from: EOL_CAL_TEST_CPU=DIR python -m pytest -q -n 2; python tests/_cpu_report.py DIR --table",
    ]
    ranked = sorted(units.items(), key=lambda kv: (-kv[1], kv[0]))
    lines += [f"{seconds:6.0f} {name}" for name, seconds in ranked if seconds >= least_s]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    if "--table" in sys.argv:
        sys.stdout.write(table(Path(sys.argv[1])))
    else:
        print(summarise(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 40))
