"""The fit's on-disk cache of serialized (``jax.export``) one-motor solvers.

JAX's persistent compilation cache skips XLA compiling; this cache skips tracing the solver
(and importing optimistix), about 2 s of a short run.
"""

from __future__ import annotations

from eol_cal.analysis.fit.model import FitSpec

#: Where :func:`fit_many` keeps serialized (``jax.export``) one-motor solvers; ``None`` = off.
#: The CLI sets it next to JAX's persistent compilation cache: the compilation cache skips XLA
#: compiling, this skips tracing the solver (and importing optimistix), about 2 s of a short run.
EXPORT_DIR: str | None = None
_EXPORT_TAG = "eol-cal-fit-solve-2"


def _export_file(spec: FitSpec, S: int, n_grid: int) -> str | None:
    import hashlib
    import os

    import jax

    if not EXPORT_DIR:
        return None
    key = repr((_EXPORT_TAG, jax.__version__, spec, S, n_grid))
    return os.path.join(EXPORT_DIR, f"fit-{hashlib.sha256(key.encode()).hexdigest()[:20]}.jaxexport")


def _exported_solver(spec: FitSpec, S: int, n_grid: int):
    """A deserialized one-motor solver from EXPORT_DIR, or None (none yet, or unreadable)."""
    path = _export_file(spec, S, n_grid)
    if path is None:
        return None
    try:
        with open(path, "rb") as fh:
            blob = fh.read()
        from jax import export

        return export.deserialize(bytearray(blob)).call
    except Exception:  # noqa: BLE001 - a missing or stale cache entry only costs the tracing
        return None


def _save_exported(fn, spec: FitSpec, S: int, n_grid: int, args: tuple) -> None:
    """Serialize the jitted one-motor solver for the next process (best effort, atomic)."""
    import re

    path = _export_file(spec, S, n_grid)
    if path is None:
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
        blob = exp.serialize()
        from eol_cal.atomic import atomic_write

        atomic_write(path, bytes(blob))
    except Exception:  # noqa: BLE001 - the cache is an optimisation, never a failure
        return
