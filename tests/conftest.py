"""Shared fixtures: a real PostgreSQL server (session-scoped, started only when a test asks), and
the suite's own JAX cache directory.

The suite runs in parallel (pytest-xdist, ``scripts/test``): each worker is its own process, so
whatever a test writes goes under ``tmp_path`` or into a directory of its worker, never into the
repository, the working directory or the user's home. The PostgreSQL server is one per worker
(session scope), on a free port, each test in a database of its own.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import _cpu_report
import _schedule
import pytest

from eol_cal.numerics.blas import limit_blas_threads
from eol_cal.numerics.xla import configure_xla, start_xla
from eol_cal.sim.postgres import PostgresServer

# pytest-xdist gives its workers COLUMNS=80 (the controller's terminal): the CLI would print its
# tables 80 wide there and LOG_WIDTH wide in a serial run, and a test reading a table would pass in
# one and not the other. The workers see what a serial run sees; a test that wants a width sets it.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.pop("COLUMNS", None)

# PYTHONDONTWRITEBYTECODE (some CI images and this project's dev machines set it) would make every
# worker rewrite every test module's asserts and every CLI subprocess compile the project from its
# source, on every run: ~5.5 CPU s a worker's collection and ~0.1 s a subprocess (2026-11-29). The
# suite keeps Python's bytecode caches (``__pycache__``, ignored by git) whatever the environment says.
sys.dont_write_bytecode = False
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

# The CLI runs the library on one BLAS thread (eol_cal.numerics.blas, at its start); a test that
# calls the library in its own process does too. Two workers each with a multi-threaded OpenBLAS on
# two cores wait for each other's threads: a small solve costs 100x its time on a loaded machine
# (the fit's zero-phase filter 90 ms instead of 2 ms, 2026-11-29). A count the caller set stands.
limit_blas_threads()

# XLA's loop kernel (eol_cal.numerics.xla.configure_xla), as every entry point that simulates or
# fits turns it on (the CLI, the station, the refit's workers): the tests run the plant's and the
# estimator's tick loops as the product runs them, not XLA's defaults, which only the library
# called from a user's own script gets. Before, a worker had it only where a CLI test happened to
# run in it first. The plant-heavy files took 24 % less CPU with it (289 -> 220 CPU s, 8 files,
# cold caches, 2026-11-30); tests that need the defaults run them in a process of their own
# (tests/test_plant_identifying_loop.py).
configure_xla()

# The station tests run the dyno simulator and its plant in the test's process (or beside it): on
# a loaded machine (the hog runs of docs/history/benchmarks-journal.md, "Test suite") the station's client can be
# quiet for more than the dyno's 2 s communication watchdog while the plant computes a capture, and
# the dyno stops the run. The watchdog is not what they test: they get 30 s (a test of the setting
# itself passes its own environment; the dyno's own tests set DynoConfig.watchdog_ms).
os.environ.setdefault("EOL_CAL_DYNO_WATCHDOG_MS", "30000")

_JAX_CACHE = "EOL_CAL_JAX_CACHE"
_jax_cache_key = pytest.StashKey[str]()


def pytest_configure(config: pytest.Config) -> None:
    """Point JAX's compilation cache and the fit's serialized solvers at the suite's own directory
    unless the caller chose one (``EOL_CAL_JAX_CACHE``: a directory, both caches there; ``off``:
    none): the tests stay out of the user's home. The processes a test starts inherit it.

    The directory is kept between runs (``.pytest_cache/eol-cal-jax/shared``), so the fast loop
    run again compiles only what changed (about 25 s less on 2 cores), and it is one for every
    worker: pytest-xdist hands a test file to whichever worker is free, so a cache per worker
    missed about half of it the next run. JAX writes its entries in place unless its cache has a
    size limit, and then it reads and writes under a file lock (``filelock``): the limit set here
    makes the workers' sharing safe. ``EOL_CAL_TEST_JAX_CACHE=fresh`` takes a new directory per
    worker, removed at the end."""
    # EOL_CAL_TEST_CPU=DIR: each test's CPU seconds, children's included (tests/_cpu_report.py)
    _cpu_report.pytest_configure(config)
    chosen = os.environ.get(_JAX_CACHE)
    if chosen == "off":
        _start_xla(config)
        return
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    if chosen:
        # the caller's (a CI cache kept between clones; the workers inherit the controller's): JAX's
        # programs too, not only the fit's solvers. JAX's cache key is the program without its
        # source locations, so a directory kept across checkouts is hit (test_fit_core.py and
        # test_plant_sim.py: 67 CPU s with a cold cache, 21 warm; 2026-11-29)
        path = chosen
        os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(4 << 30))
    elif os.environ.get("EOL_CAL_TEST_JAX_CACHE") == "fresh":
        path = tempfile.mkdtemp(prefix=f"eol-cal-test-jax-{worker}-")
        config.stash[_jax_cache_key] = path
    else:
        keep = Path(config.rootpath) / ".pytest_cache" / "eol-cal-jax" / "shared"
        keep.mkdir(parents=True, exist_ok=True)
        path = str(keep)
        os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(4 << 30))
    os.environ[_JAX_CACHE] = path
    # every compilation of the worker (the plant's, the estimator's), not only the fit's, which
    # enables the cache itself: JAX reads these when it starts
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", path)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    _start_xla(config)
    # the programs the product keeps between processes (the fit's solvers, the plant's tick loops:
    # eol_cal.numerics.exported), kept there too, as the CLI keeps them in its cache directory: a
    # worker reads what another traced, a run what the last one traced (the fast loop a few per cent
    # less CPU, docs/benchmarks.md). Their keys hold the code they were traced from, so an edit is traced
    # afresh; the export's own tests give it a directory of their own.
    from eol_cal.numerics.exported import set_cache_dir

    set_cache_dir(path)


def _start_xla(config: pytest.Config) -> None:
    """XLA's CPU pool of one thread, as the product's entry points start it
    (:func:`eol_cal.numerics.xla.start_xla`): with XLA's default every tick loop's second thread
    spun beside the first, twice the CPU for no less wall, and three workers on two cores took it
    from each other (the identifier's 10 000 power-ups: 229 -> 150 CPU s, 2026-11-30). After the
    cache's variables: JAX reads them when it is imported, which this does. Not in
    pytest-xdist's controller, which runs no test (and would import JAX for nothing)."""
    if getattr(config.option, "numprocesses", None) and not hasattr(config, "workerinput"):
        return
    start_xla()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Also ``slow``, so that the fast loop (``-m "not slow"``) leaves them out: a test on the
    PostgreSQL server (``records_db``'s ``postgresql`` parameter; SQLite stays in the fast loop),
    and a test marked ``long`` (minutes: the mech branch's marker). Then the costliest files first."""
    for item in items:
        callspec = getattr(item, "callspec", None)
        on_postgres = callspec is not None and callspec.params.get("records_db") == "postgresql"
        if (on_postgres or item.get_closest_marker("long") is not None) and item.get_closest_marker("slow") is None:
            item.add_marker(pytest.mark.slow)
    # the costliest files first, so the two workers end together (tests/_schedule.py says why)
    _schedule.costliest_first(items)


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's hook: absent without it (-p no:xdist)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """``--dist loadfile`` (pyproject's addopts), with the 10 000 power-ups' parts on both workers."""
    if config.getoption("dist") == "loadfile":
        return _schedule.make_scheduler(config, log)
    return None


def pytest_unconfigure(config: pytest.Config) -> None:
    path = config.stash.get(_jax_cache_key, None)
    if path is not None:
        shutil.rmtree(path, ignore_errors=True)
        for name in (_JAX_CACHE, "JAX_COMPILATION_CACHE_DIR"):
            if os.environ.get(name) == path:
                del os.environ[name]



@pytest.fixture(autouse=True)
def _exported_dir_kept() -> Iterator[None]:
    """The worker's directory of exported programs as it was before each test: a test that runs an
    entry point in its process (the station's, a refit worker's: ``enable_compile_cache``) moves it
    for the tests after it otherwise."""
    from eol_cal.numerics import exported

    before = exported.cache_dir()
    yield
    exported.set_cache_dir(before)


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    server = PostgresServer().start()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def records_db(request, tmp_path: Path) -> str | Path:
    """A new, empty records database of each backend: a SQLite file path or a PostgreSQL URL."""
    if request.param == "sqlite":
        return tmp_path / "records.sqlite"
    server: PostgresServer = request.getfixturevalue("postgres_server")
    return server.create_db("r" + uuid.uuid4().hex[:12])
