"""The fit's caches on disk: JAX's persistent compilation cache and serialized solvers (one motor's,
and a batched fit's per chunk size).

Both live in one directory (the firmware estimator's exported scan too: :mod:`eol_cal.numerics.exported`,
which reads and writes every serialized program), chosen by the caller (:func:`default_cache_dir` computes the default;
the CLI and the station pass it on). JAX's compilation cache skips XLA compiling; the serialized
(``jax.export``) solvers skip tracing the solver (and importing optimistix), about 2 s of a short
run. Pre-warming a process (imports, one solver trace, matplotlib) sits beside this module:
:func:`eol_cal.analysis.fit.prewarm.prewarm_fit`.
"""

from __future__ import annotations

import functools
import importlib.util
import os
from pathlib import Path
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from eol_cal.analysis.fit.compression import COMPRESSED_KEYS
from eol_cal.analysis.fit.model import FitSpec
from eol_cal.numerics.cache_size import MAX_JAX_CACHE_BYTES, time_jax_entries
from eol_cal.numerics.exported import entry_path, key_text, load, save, set_cache_dir, sources_digest
from eol_cal.numerics.xla import start_xla

#: environment variable naming the cache directory (``off``: no cache)
CACHE_ENV = "EOL_CAL_JAX_CACHE"
#: part of every solver file's key (with its modules' sources, :data:`SOLVER_MODULES`): bump it when
#: the solver's program changes in another way (its arguments, what the entry holds)
_EXPORT_TAG = "eol-cal-fit-solve-9"
#: the modules whose code the solver's trace runs: their sources are in its key, so an edited
#: solver or model is traced afresh, never read back from an entry of the code before
SOLVER_MODULES = ("eol_cal.analysis.fit.solver", "eol_cal.analysis.fit.model")


def default_cache_dir(environ: Mapping[str, str] | None = None) -> Path | None:
    """The cache directory a process uses unless told otherwise.

    ``$EOL_CAL_JAX_CACHE``, or ``~/.cache/eol-cal/jax`` when it is unset or empty; ``None`` when it
    is ``off``.

    Parameters
    ----------
    environ : mapping, optional
        The environment to read (default ``os.environ``).
    """
    env = os.environ if environ is None else environ
    value = env.get(CACHE_ENV) or str(Path.home() / ".cache" / "eol-cal" / "jax")
    return None if value == "off" else Path(value)


def enable_compile_cache(cache_dir: str | os.PathLike[str] | None) -> Path | None:
    """Switch on JAX's persistent compilation cache in ``cache_dir`` (created if missing).

    Starts JAX's CPU backend first, on the threads :func:`eol_cal.numerics.xla.start_xla` gives it
    (one unless ``$EOL_CAL_XLA_THREADS`` asks for more), where it has not started yet.

    JAX's cache directory is a setting of the whole process (``jax.config``), and so is the
    directory of the exported programs that are not the fit's (the firmware estimator's scan:
    :func:`eol_cal.numerics.exported.set_cache_dir`, set here too; ``None`` unsets it); the
    serialized solvers are not: pass the returned directory to :func:`eol_cal.analysis.fit.fit_many`.

    Returns
    -------
    Path or None
        ``cache_dir`` when it can be used; ``None`` when it is ``None`` or cannot be created (a
        read-only home only costs the compile time).
    """

    # every entry point that fits or simulates comes through here before computing: XLA's CPU
    # pool of one thread (no spinning second one) unless the user asked for more
    start_xla()
    if cache_dir is None:
        set_cache_dir(None)
        return None
    path = Path(cache_dir)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        set_cache_dir(None)
        return None
    import jax  # a second to import: only for callers that fit or simulate

    jax.config.update("jax_compilation_cache_dir", str(path))
    if "JAX_COMPILATION_CACHE_MAX_SIZE" not in os.environ and importlib.util.find_spec("filelock") is not None:
        # JAX's cache held to a size, the least recently used entries evicted (eol_cal.numerics.cache_size);
        # its eviction needs filelock, without which JAX would refuse the cache at the first compile,
        # and a use time beside every entry, which a cache filled without a bound lacks
        time_jax_entries(path)
        jax.config.update("jax_compilation_cache_max_size", MAX_JAX_CACHE_BYTES)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    set_cache_dir(path)  # the exported programs of eol_cal.numerics.exported (the firmware estimator's)
    return path


#: a batched solver: ``(mode, motors)``, the batch mode of :func:`eol_cal.analysis.fit.fit_many`
#: (``vmap`` or ``map``) and the motors of its chunk; ``None``: the one-motor solver
Batch = tuple[str, int] | None


@functools.cache
def _solver_key(spec: FitSpec, S: int, n_grid: int, batch: Batch = None) -> str:
    """The solver's key (:func:`~eol_cal.numerics.exported.key_text`), made once per process for each
    ``(spec, S, n_grid, batch)``: the JAX version and backend it holds do not change in a process, and
    its ``repr`` of the spec was ~0.1 ms of each fit's call (two a refit's serial, issue 37)."""
    import jax

    parts = (spec, S, n_grid, sources_digest(*SOLVER_MODULES)) + ((batch,) if batch else ())
    with jax.enable_x64(True):  # the solver runs in float64 only (fit_many)
        return key_text(_EXPORT_TAG, parts)


def _entry_name(batch: Batch) -> str:
    return "fit" if batch is None else f"fit-{batch[0]}"


def solver_file(cache_dir: str | os.PathLike[str], spec: FitSpec, S: int, n_grid: int, batch: Batch = None) -> Path:
    """The file of the serialized solver for ``spec``, ``S`` segments and a delay grid of ``n_grid``
    points, of one motor or of a chunk (``batch``: :data:`Batch`)
    (:func:`eol_cal.numerics.exported.entry_path`: the key also holds the JAX version, the backend
    and the float width: an entry is only read back on this installation)."""

    return _solver_path(os.fspath(cache_dir), spec, S, n_grid, batch)


@functools.cache
def _solver_path(cache_dir: str, spec: FitSpec, S: int, n_grid: int, batch: Batch = None) -> Path:
    """:func:`solver_file`, made once per process for each directory and solver (its SHA-256 and path)."""
    return entry_path(cache_dir, _entry_name(batch), _solver_key(spec, S, n_grid, batch))


def solver_args(spec: FitSpec, S: int, n_grid: int, batch: Batch = None) -> tuple[dict[str, Any], Any]:
    """The shapes and dtypes (``jax.ShapeDtypeStruct``) of the solver's arguments
    ``(compressed, tau_grid)``: float64, as :func:`eol_cal.analysis.fit.compression.compressed_dict`
    gives them (a chunk's, ``batch``: each stacked, the motors first)."""
    import jax

    m, nh = spec.n_cols, len(spec.harmonics)
    lead = () if batch is None else (batch[1],)
    shapes = {"R": (S, m, m), "z": (S, m), "n": (S,), "i_qo": (S,), "omega": (S,), "gain_re": (S, nh),
              "gain_im": (S, nh), "cur_re": (S, nh), "cur_im": (S, nh)}
    assert set(shapes) == set(COMPRESSED_KEYS)
    return ({k: jax.ShapeDtypeStruct(lead + v, np.float64) for k, v in shapes.items()},
            jax.ShapeDtypeStruct((n_grid,), np.float64))


#: solvers this process has read, by file: a lot refit fits thousands of motors per process, and
#: reading, deserializing and wrapping one costs more than the solve (~3 ms against ~1 ms)
_LOADED: dict[Path, Callable] = {}


def load_solver(cache_dir: str | os.PathLike[str] | None, spec: FitSpec, S: int, n_grid: int,
                batch: Batch = None) -> Callable | None:
    """A deserialized solver ``(compressed, tau_grid) -> outputs`` (one motor's, or a chunk's:
    ``batch``) from ``cache_dir``, or ``None`` (no cache, none yet, or an entry that is not intact
    and this solver's: :func:`eol_cal.numerics.exported.load`); read once per process and file."""
    if cache_dir is None:
        return None

    path = solver_file(cache_dir, spec, S, n_grid, batch)
    if path in _LOADED:
        return _LOADED[path]
    import jax

    with jax.enable_x64(True):
        solve = load(cache_dir, _entry_name(batch), _solver_key(spec, S, n_grid, batch),
                     solver_args(spec, S, n_grid, batch))
    if solve is not None:
        _LOADED[path] = solve
    return solve


def save_solver(cache_dir: str | os.PathLike[str] | None, fn: Callable, spec: FitSpec, S: int, n_grid: int,
                args: tuple, batch: Batch = None) -> None:
    """Serialize the jitted solver ``fn`` (one motor's, or a chunk's: ``batch``; traced at ``args``)
    into ``cache_dir`` for the next process (best effort, atomic; nothing when ``cache_dir`` is ``None``)."""

    if cache_dir is not None:
        save(cache_dir, _entry_name(batch), _solver_key(spec, S, n_grid, batch), fn, args)
