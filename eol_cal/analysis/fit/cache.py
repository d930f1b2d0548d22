"""The fit's caches on disk: JAX's persistent compilation cache and serialized one-motor solvers.

Both live in one directory, chosen by the caller (:func:`default_cache_dir` computes the default;
the CLI and the station pass it on). JAX's compilation cache skips XLA compiling; the serialized
(``jax.export``) solvers skip tracing the solver (and importing optimistix), about 2 s of a short
run. Pre-warming a process (imports, one solver trace, matplotlib) sits beside this module:
:func:`eol_cal.analysis.fit.prewarm.prewarm_fit`.
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path
from collections.abc import Callable, Mapping

from eol_cal.analysis.fit.model import FitSpec
from eol_cal.infra.atomic import atomic_write

#: environment variable naming the cache directory (``off``: no cache)
CACHE_ENV = "EOL_CAL_JAX_CACHE"
#: part of every solver file's key: bump it when the solver's program changes
_EXPORT_TAG = "eol-cal-fit-solve-6"


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

    JAX's cache directory is a setting of the whole process (``jax.config``); the serialized
    solvers are not: pass the returned directory to :func:`eol_cal.analysis.fit.fit_many`.

    Returns
    -------
    Path or None
        ``cache_dir`` when it can be used; ``None`` when it is ``None`` or cannot be created (a
        read-only home only costs the compile time).
    """
    if cache_dir is None:
        return None
    path = Path(cache_dir)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    import jax  # a second to import: only for callers that fit or simulate

    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return path


def solver_file(cache_dir: str | os.PathLike[str], spec: FitSpec, S: int, n_grid: int) -> Path:
    """The file of the serialized solver for ``spec``, ``S`` segments and a delay grid of ``n_grid``
    points (the key also holds the jax version: an entry is only read back on this installation)."""
    import jax

    key = repr((_EXPORT_TAG, jax.__version__, spec, S, n_grid))
    return Path(cache_dir) / f"fit-{hashlib.sha256(key.encode()).hexdigest()[:20]}.jaxexport"


#: solvers this process has read, by file: a lot refit fits thousands of motors per process, and
#: reading, deserializing and wrapping one costs more than the solve (~3 ms against ~1 ms)
_LOADED: dict[Path, Callable] = {}


def load_solver(cache_dir: str | os.PathLike[str] | None, spec: FitSpec, S: int, n_grid: int) -> Callable | None:
    """A deserialized one-motor solver ``(compressed, tau_grid) -> outputs`` from ``cache_dir``, or
    ``None`` (no cache, none yet, or unreadable); read once per process and file."""
    if cache_dir is None:
        return None
    path = solver_file(cache_dir, spec, S, n_grid)
    if path in _LOADED:
        return _LOADED[path]
    try:
        blob = path.read_bytes()
        import jax
        from jax import export

        solve = jax.jit(export.deserialize(bytearray(blob)).call)
    except Exception:  # noqa: BLE001 - a missing or stale cache entry only costs the tracing
        return None
    _LOADED[path] = solve
    return solve


def save_solver(cache_dir: str | os.PathLike[str] | None, fn: Callable, spec: FitSpec, S: int, n_grid: int,
                args: tuple) -> None:
    """Serialize the jitted one-motor solver ``fn`` (traced at ``args``) into ``cache_dir`` for the
    next process (best effort, atomic; nothing when ``cache_dir`` is ``None``)."""
    if cache_dir is None:
        return
    try:
        from jax import export

        # The LAPACK custom calls carry no cross-version guarantee; the file name holds the jax
        # version and the entry is only read back on this installation.
        names: set[str] = set()
        for _ in range(20):
            try:
                checks = [export.DisabledSafetyCheck.custom_call(n) for n in sorted(names)]
                exp = export.export(fn, disabled_checks=checks)(*args)
                break
            except ValueError as exc:
                new = set(re.findall(r"custom_call @(\w+)", str(exc))) - names
                if not new:
                    return
                names |= new
        else:
            return
        atomic_write(solver_file(cache_dir, spec, S, n_grid), bytes(exp.serialize()))
    except Exception:  # noqa: BLE001 - the cache is an optimisation, never a failure
        return
