"""scipy's LAPACK, for this package and for JAX, without the import of the package ``scipy.linalg``.

Importing any module of ``scipy.linalg`` first runs the package's ``__init__``: the whole of
``scipy.linalg`` with scipy's array-API layer and numpy's f2py, about 0.2 s of a warm
`eol-cal fit`'s 1.2-1.4 s (2026-12-02) and more CPU beside a station's stream. What is used of it
is three extension modules, each of which loads alone:

- ``scipy.linalg._flapack``: the f2py LAPACK wrappers (``scipy.linalg.lapack.dpotrf`` *is*
  ``_flapack.dpotrf``), used by the fingerprint's and the segment noise's Cholesky factors
  (:func:`flapack`);
- ``scipy.linalg.cython_blas`` and ``scipy.linalg.cython_lapack``: jaxlib takes its CPU LAPACK
  kernels from their ``__pyx_capi__`` function pointers, importing them by name the first time it
  needs LAPACK; every call of a deserialized ``jax.export`` program needs it (jax initialises LAPACK
  for any CPU export, whether the program calls LAPACK or not) (:func:`preload_for_jax`).

They are loaded from their files under their full names, so a later import finds them in
``sys.modules``. A later ``import scipy.linalg`` runs as it would have and finds them there too;
only the package's attributes of those names stay unset (``from scipy.linalg import _flapack``
still works: Python falls back to ``sys.modules``).
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

#: scipy's f2py LAPACK wrappers (what ``scipy.linalg.lapack`` re-exports)
FLAPACK = "scipy.linalg._flapack"
#: the modules jaxlib's LAPACK initialisation imports (jaxlib/cpu/lapack_kernels)
JAX_POINTERS = ("scipy.linalg.cython_blas", "scipy.linalg.cython_lapack")


def flapack() -> ModuleType:
    """scipy's LAPACK wrappers (``dpotrf``, ``dtrtrs``, ``dpotrs``, ``dtrtri``, ...: the functions
    of ``scipy.linalg.lapack``), loaded without ``scipy.linalg``'s package import.

    Raises
    ------
    ImportError
        scipy is not installed or has no such module.
    """
    module = sys.modules.get(FLAPACK)
    if module is not None:
        return module
    if "scipy.linalg" in sys.modules:  # the package is paid for: its own import
        import scipy.linalg._flapack

        return scipy.linalg._flapack
    return _load(FLAPACK)


def preload_for_jax() -> bool:
    """Load :data:`JAX_POINTERS` without ``scipy.linalg``'s package import, before jaxlib asks for
    them; True when both are loaded.

    Does nothing (False) once ``scipy.linalg`` is imported: it has paid its import and loads them
    itself. Never raises: where a module does not load here, jaxlib imports it the usual way.
    """
    if "scipy.linalg" in sys.modules:
        return False
    try:
        for name in JAX_POINTERS:
            if name not in sys.modules:
                _load(name)
    except Exception:  # noqa: BLE001 - an optimisation: the usual import still follows
        return False
    return True


def _load(name: str) -> ModuleType:
    """The extension module ``name`` of scipy, executed from its file without its package's import."""
    import scipy

    stem = Path(scipy.__file__).parent.joinpath(*name.split(".")[1:])
    path = next((p for suffix in importlib.machinery.EXTENSION_SUFFIXES
                 if (p := stem.with_name(stem.name + suffix)).is_file()), None)
    spec = None if path is None else importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"no extension module {name} under {stem.parent}", name=name)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module
