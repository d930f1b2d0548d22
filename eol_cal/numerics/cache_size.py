"""The cache directory held to a size: the kept programs and their executables
(:mod:`eol_cal.numerics.exported`) over :data:`MAX_KEPT_BYTES` lose the least recently used first,
and JAX's own compilation cache beside them evicts its entries past :data:`MAX_JAX_CACHE_BYTES`
(JAX's ``jax_compilation_cache_max_size``, set by ``eol_cal.analysis.fit.cache.enable_compile_cache``
unless ``JAX_COMPILATION_CACHE_MAX_SIZE`` sets it).

Without a bound the directory only grows: every release keys the plant's programs afresh (their key
holds the package's sources, :func:`eol_cal.numerics.exported.code_digest`) and every new capture
shape or fit option adds a solver; each program is 0.1-0.3 MB and its executable 0.2-1.2 MB (a cold
run of the test suite writes ~60 MB of them), so a line PC that takes every release would fill its
disk. "Used" is a file's modification time, set when it is read back (:func:`used`): most mounts do
not keep access times.
"""

from __future__ import annotations

import contextlib
import os
import stat
from pathlib import Path

#: the kept programs' and executables' share of the cache directory (bytes)
MAX_KEPT_BYTES = 512 << 20
#: JAX's compilation cache's share (bytes), unless ``JAX_COMPILATION_CACHE_MAX_SIZE`` says otherwise
MAX_JAX_CACHE_BYTES = 1 << 30
#: a prune goes down to this fraction of the bound, so that the next few writes do not prune again
KEEP_FRACTION = 0.75
#: the names of JAX's cache entries and of their use times (jax 0.10's ``lru_cache``)
_JAX_ENTRY, _JAX_USED = "-cache", "-atime"
#: the kept files' suffixes (:func:`eol_cal.numerics.exported.entry_path`, ``executable_path``)
KEPT_SUFFIXES = (".jaxexport", ".xlaexec")


def lock_of(path: Path) -> Path:
    """The lock file of the kept file ``path`` (:func:`eol_cal.numerics.exported.one_at_a_time`):
    held while it is traced or compiled, removed with it (:func:`prune`)."""
    return Path(path).with_suffix(".lock")


def used(path: Path) -> None:
    """Mark the kept file ``path`` used now (best effort: a read-only directory keeps its times)."""
    with contextlib.suppress(OSError):
        os.utime(path)


def prune(directory: Path, max_bytes: int | None = None, keep: Path | None = None) -> list[Path]:
    """Remove the least recently used kept files of ``directory`` (and each one's lock file) while
    they hold more than ``max_bytes`` (default :data:`MAX_KEPT_BYTES`), down to :data:`KEEP_FRACTION`
    of it; ``keep`` (the file just
    written) stays. Only regular files with :data:`KEPT_SUFFIXES` directly in ``directory`` count
    and go: a link, a folder or any other file is left alone. Returns what was removed. Never
    raises: a file that cannot be removed is passed over.

    A process may still want a program removed here: it traces and compiles it again (the cost of
    a cold cache, nothing wrong)."""
    files: list[tuple[int, str, int]] = []
    try:
        with os.scandir(directory) as it:
            for e in it:
                if not e.name.endswith(KEPT_SUFFIXES):
                    continue
                with contextlib.suppress(OSError):
                    st = e.stat(follow_symlinks=False)
                    if stat.S_ISREG(st.st_mode):
                        files.append((st.st_mtime_ns, e.name, st.st_size))
    except OSError:
        return []
    bound = MAX_KEPT_BYTES if max_bytes is None else max_bytes
    total = sum(size for _, _, size in files)
    if total <= bound:
        return []
    removed: list[Path] = []
    for _, name, size in sorted(files):  # the least recently used first
        if total <= KEEP_FRACTION * bound:
            break
        path = Path(directory) / name
        if keep is not None and path == Path(keep):
            continue
        try:
            path.unlink()
        except OSError:
            continue
        with contextlib.suppress(OSError):
            lock_of(path).unlink()
        total -= size
        removed.append(path)
    return removed


def time_jax_entries(directory: Path) -> int:
    """Give every entry of JAX's compilation cache in ``directory`` that has no use time its file's
    modification time as one; returns how many were given one. Needed once before the cache gets a
    bound: JAX writes a use time beside each entry only while its cache has one (jax 0.10's
    ``lru_cache``: ``KEY-cache`` and ``KEY-atime``, nanoseconds, 8 bytes little-endian), and its
    eviction reads every entry's, so a cache filled before without them failed every later write
    ("Error writing persistent compilation cache entry ... FileNotFoundError"). Best effort."""
    try:
        with os.scandir(directory) as it:
            names = {e.name: e for e in it}
    except OSError:
        return 0
    given = 0
    for name, e in names.items():
        used_name = name.removesuffix(_JAX_ENTRY) + _JAX_USED
        if not name.endswith(_JAX_ENTRY) or used_name in names:
            continue
        with contextlib.suppress(OSError):
            st = e.stat(follow_symlinks=False)
            if stat.S_ISREG(st.st_mode):
                (Path(directory) / used_name).write_bytes(st.st_mtime_ns.to_bytes(8, "little"))
                given += 1
    return given
