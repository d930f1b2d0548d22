"""Jitted programs kept between processes: ``jax.export`` files in the product's cache directory.

Tracing a JAX program costs a short run more than computing with it (the fit's solver ~2 s with
optimistix, the firmware estimator's scan ~0.1 s); JAX's persistent compilation cache skips only
the compiling after it. A program exported here is read back by the next process instead of
traced: :func:`load` returns it, :func:`save` writes it after the first trace. Beside it the
program's compiled executable is kept (:func:`executable`): the next process runs that without
lowering the program again, which JAX's compilation cache needs before it can answer.

Every entry is untrusted input: it is read back only when its header says it is this program
(the full key text: the caller's tag and options, the argument shapes and dtypes, the JAX version,
the backend, the float width), its SHA-256 matches the key and the payload (a torn or corrupt
file), it is not over :data:`MAX_ENTRY_BYTES`, and the deserialized program takes exactly the
arguments the caller is about to pass. Anything else is ignored (the caller traces and the entry
is written again); reading never raises. The digest guards against corruption and mix-ups, not
against someone who can write the user's cache directory (they can write its Python too).

The directory is a setting of the process, as JAX's own compilation cache directory is
(:func:`set_cache_dir`; ``eol_cal.analysis.fit.cache.enable_compile_cache`` sets both). Processes
that share it trace and compile a program once between them (:func:`one_at_a_time`); its kept files
are held to a size, the least recently used removed first (:mod:`eol_cal.numerics.cache_size`).
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import hashlib
import importlib.util
import os
import platform
import re
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from eol_cal.infra.atomic import atomic_write
from eol_cal.infra.inputs import read_bytes
from eol_cal.infra.lockfile import open_lock_file
from eol_cal.numerics.cache_size import lock_of, prune, used

#: the first bytes of every entry (bump the number when the layout below changes)
MAGIC = b"eol-cal-exported/1\n"
#: an entry larger than this is not read (the largest, the fit's solver, is ~0.3 MB)
MAX_ENTRY_BYTES = 64 << 20
#: the longest a process waits for another one tracing or compiling the same program (s); then it
#: does the work itself (a duplicate costs only time)
LOCK_WAIT_S = 300.0

_DIR: Path | None = None
#: the programs this process has read or traced (:func:`kept`), by directory, name and key
_KEPT: dict[tuple[Path, str, str], Callable] = {}


def set_cache_dir(path: str | os.PathLike[str] | None) -> None:
    """Keep this process's exported programs in ``path`` (``None``: trace every program afresh)."""
    global _DIR
    _DIR = None if path is None else Path(path)


def cache_dir() -> Path | None:
    """The directory :func:`set_cache_dir` set (``None``: none)."""
    return _DIR


def key_text(tag: str, parts: object) -> str:
    """The full key of a program: ``tag`` (the caller's name and version of its code), ``parts``
    (everything else that changes the trace: options, shapes, dtypes; its ``repr`` must be
    deterministic), JAX's version, the default backend and whether 64-bit floats are on."""
    import jax

    wide = jax.dtypes.canonicalize_dtype(np.float64) == np.float64  # jax.enable_x64 is thread-local
    return repr((tag, jax.__version__, jax.default_backend(), wide, parts))


def entry_path(directory: str | os.PathLike[str], name: str, key: str) -> Path:
    """The file of the program ``name`` with key ``key`` (:func:`key_text`) in ``directory``."""
    return Path(directory) / f"{name}-{hashlib.sha256(key.encode()).hexdigest()[:20]}.jaxexport"


def executable_path(directory: str | os.PathLike[str], name: str, key: str) -> Path:
    """The file of the compiled executable of program ``name`` with key ``key`` (its entry's key
    and the machine's: :func:`executable`) in ``directory``."""
    return entry_path(directory, name, key).with_suffix(".xlaexec")


@functools.lru_cache(maxsize=1)
def _machine() -> str:
    """What a compiled executable is valid for beyond its entry's key: jaxlib's version, the
    backend's platform and version, the processor's architecture and features (machine code for
    one CPU may use instructions another lacks: a cache directory in a home shared between
    machines)."""
    import jax
    import jaxlib

    client = jax.devices()[0].client
    flags = ""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text(errors="replace").splitlines():
            if line.startswith(("flags", "Features")):
                flags = line.partition(":")[2].strip()
                break
    return repr((jaxlib.__version__, client.platform, client.platform_version, platform.machine(),
                 platform.processor(), hashlib.sha256(flags.encode()).hexdigest()))


@contextlib.contextmanager
def one_at_a_time(path: Path) -> Iterator[bool]:
    """Hold the lock file ``path`` (the kernel's ``flock``: it goes with its process, killed or not)
    for the block, waiting up to :data:`LOCK_WAIT_S` for another process (or thread) that holds it;
    yields whether it is held. Around a program's tracing and compiling, so that processes starting
    together (the test workers, a refit's Dask workers, two stations on one PC) do the work once
    and the others read what it wrote (a cold run of the suite's three workers compiled 99 kept
    programs fresh for 95 written: docs/benchmarks.md). Best effort: without a lock (an
    unwritable directory, a path that is no regular file, the wait over) the work goes on unlocked.
    """
    fd = -1
    with contextlib.suppress(OSError):  # a link, a FIFO, a directory: no lock (the work goes on)
        fd = open_lock_file(path)
    held = False
    try:
        if fd >= 0:
            deadline = time.monotonic() + LOCK_WAIT_S
            while not held:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    held = True
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        break
                    time.sleep(0.02)
                except OSError:
                    break
        yield held
    finally:
        if fd >= 0:
            os.close(fd)  # the lock goes with the descriptor


def _read_entry(path: Path, key: str) -> bytes | None:
    """The payload of the entry at ``path`` if it is an intact entry for ``key`` (:func:`unpack`);
    ``None`` for anything else: none there, not a regular file (the bounded reader refuses a FIFO or
    a device unread: an open() of a FIFO waits for a writer), over :data:`MAX_ENTRY_BYTES`."""
    try:
        payload = unpack(read_bytes(path, max_bytes=MAX_ENTRY_BYTES, register=False), key)
    except Exception:  # noqa: BLE001 - an unreadable entry only costs the tracing or the compile
        return None
    if payload is not None:
        used(path)  # the directory's bound removes the least recently used first
    return payload


def _digest(key: bytes, payload: bytes) -> bytes:
    return hashlib.sha256(len(key).to_bytes(8, "little") + key + payload).digest()


def pack(key: str, payload: bytes) -> bytes:
    """An entry's bytes: :data:`MAGIC`, the key's length (4 bytes), the SHA-256 of key and payload,
    the key, the serialized program."""
    k = key.encode()
    return MAGIC + len(k).to_bytes(4, "little") + _digest(k, payload) + k + payload


def unpack(blob: bytes, key: str) -> bytes | None:
    """The serialized program in ``blob`` if it is an intact entry for ``key``, else ``None``."""
    k = key.encode()
    head = len(MAGIC) + 4 + 32
    if len(blob) < head or not blob.startswith(MAGIC):
        return None
    n = int.from_bytes(blob[len(MAGIC):len(MAGIC) + 4], "little")
    digest = blob[len(MAGIC) + 4:head]
    if n != len(k) or blob[head:head + n] != k:
        return None  # another program's entry under this name (or a damaged header)
    payload = blob[head + n:]
    return payload if _digest(k, payload) == digest else None


def signature(args: Any) -> tuple:
    """The argument structure and ``(shape, dtype)`` of every leaf, as JAX would trace them."""
    import jax

    leaves, tree = jax.tree_util.tree_flatten(args)
    shapes = tuple(tuple(x.shape) if hasattr(x, "shape") else np.shape(x) for x in leaves)
    dtypes = tuple(jax.dtypes.canonicalize_dtype(x.dtype if hasattr(x, "dtype") else np.result_type(x)) for x in leaves)
    return tree, tuple(zip(shapes, dtypes, strict=True))


def load(directory: str | os.PathLike[str] | None, name: str, key: str, args: tuple) -> Callable | None:
    """The program ``name`` with key ``key`` from ``directory``, jitted, if an intact entry holds it
    and it takes the positional arguments ``args`` (arrays, or ``jax.ShapeDtypeStruct``, in the
    structure of the call);
    ``None`` otherwise (no directory, no entry, a damaged, foreign or oversized one). Never raises."""
    if directory is None:
        return None
    payload = _read_entry(entry_path(directory, name, key), key)
    if payload is None:
        return None
    try:
        import jax
        from jax import export

        exp = export.deserialize(bytearray(payload))
        tree, avals = signature((tuple(args), {}))  # an export's inputs are (args, kwargs)
        if exp.in_tree != tree or tuple((tuple(a.shape), a.dtype) for a in exp.in_avals) != avals:
            return None
        fn = jax.jit(_kept_call(exp))
    except Exception:  # noqa: BLE001 - an unreadable entry only costs the tracing
        return None
    return executable(directory, name, key, fn, args, tree, exp.out_tree, exp.platforms) or fn


def _kept_call(exp: Any) -> Callable:
    """``exp.call`` under a name of its own (JAX's compiled programs are named after the function),
    so that its compiled program is not the one JAX's compilation cache holds from before the
    executables were kept (``jit_call``): that one could not be written (:func:`executable`)."""

    def kept_program(*args: Any) -> Any:
        return exp.call(*args)

    return kept_program


def executable(directory: str | os.PathLike[str], name: str, key: str, fn: Any, args: tuple, in_tree: Any,
               out_tree: Any, platforms: tuple[str, ...]) -> Callable | None:
    """``fn`` (the jitted program of entry ``name``/``key``) compiled for ``args``, its executable kept
    in ``directory`` beside the entry (:func:`executable_path`): read back when an intact one was
    written for this key on this machine, else compiled and written. ``None`` when neither works
    (the caller runs ``fn``: the same program). Never raises.

    A compiled program is called without lowering: the jitted call lowers the exported module
    again in every process (the firmware estimator's scan ~0.1 s of a warm ``eol-cal fit`` on a
    2-core machine, issue 37) before JAX's compilation cache can even be asked. It takes exactly
    ``args``' shapes and dtypes (what :func:`load` checked); anything else raises.

    Only a fresh compile is written, and only once its copy has run: an executable that XLA's CPU
    client read from JAX's compilation cache serializes without its kernels (jaxlib 0.10.2: the
    copy fails when run, "Function wrapped_broadcast not found", and would fail every later
    process), so a compile that JAX's cache answered is not written, and the copy is deserialized
    and run once on zeros of ``args``' shapes before the file is written.

    Before one is read, the process is made ready for it as ``jax.export`` makes it ready for an
    exported program on ``platforms`` (its lowering links LAPACK's routines into XLA's CPU
    kernels; an executable read without it crashed the process in its first Cholesky factor).

    Loading one runs its machine code, as JAX's own compilation cache in the same directory does:
    the directory is as trusted as the installation (:mod:`eol_cal.numerics.exported`).
    """
    try:
        from jax._src.lax.linalg import initialize_lapack  # what jax.export's call runs (no public name)

        if "cpu" in platforms:
            initialize_lapack()
        ekey = key + "\n" + _machine()
        path = executable_path(directory, name, ekey)
        read = _read_executable(path, ekey, in_tree, out_tree)
        if read is not None:
            return read
        with one_at_a_time(lock_of(path)):
            read = _read_executable(path, ekey, in_tree, out_tree)  # written meanwhile by the lock's holder
            return read if read is not None else _compile_and_keep(fn, args, in_tree, out_tree, path, ekey)
    except Exception:  # noqa: BLE001 - the executable is an optimisation, never a failure
        return None


def _read_executable(path: Path, ekey: str, in_tree: Any, out_tree: Any) -> Any:
    """The executable kept at ``path`` for ``ekey``, loaded; ``None`` when there is none intact."""
    from jax.experimental import serialize_executable as se

    payload = _read_entry(path, ekey)
    if payload is None:
        return None
    try:
        return se.deserialize_and_load(payload, in_tree, out_tree)
    except Exception:  # noqa: BLE001 - compiled afresh instead
        return None


def _compile_and_keep(fn: Any, args: tuple, in_tree: Any, out_tree: Any, path: Path, ekey: str) -> Any:
    """``fn`` compiled for ``args``; its executable written to ``path`` when the compile was fresh
    and its copy runs (:func:`executable`)."""
    import jax
    from jax.experimental import serialize_executable as se

    hits: list[str] = []

    def heard(event: str, **_: object) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            hits.append(event)

    jax.monitoring.register_event_listener(heard)
    try:
        compiled = fn.lower(*args).compile()
    finally:
        jax.monitoring.unregister_event_listener(heard)
    if not hits:  # another thread's hit meanwhile is counted too: not written, only the time lost
        with contextlib.suppress(Exception):
            blob = se.serialize(compiled)[0]
            zeros = jax.tree_util.tree_map(lambda a: np.zeros(a.shape, a.dtype), args)
            jax.block_until_ready(se.deserialize_and_load(blob, in_tree, out_tree)(*zeros))
            atomic_write(path, pack(ekey, blob))
            prune(path.parent, keep=path)
    return compiled


def save(directory: str | os.PathLike[str] | None, name: str, key: str, fn: Any, args: tuple) -> bool:
    """Export the jitted ``fn`` at ``args`` into ``directory`` as ``name`` with key ``key``
    (atomically; best effort: False when not written, nothing when ``directory`` is ``None``).

    Custom calls (LAPACK's) carry no compatibility guarantee across JAX versions; the key holds
    the version, so an entry is only read back by the installation that wrote it.
    """
    if directory is None:
        return False
    try:
        from jax import export

        names: set[str] = set()
        for _ in range(20):
            try:
                checks = [export.DisabledSafetyCheck.custom_call(n) for n in sorted(names)]
                exp = export.export(fn, disabled_checks=checks)(*args)
                break
            except ValueError as exc:
                new = set(re.findall(r"custom_call @(\w+)", str(exc))) - names
                if not new:
                    return False
                names |= new
        else:
            return False
        path = entry_path(directory, name, key)
        atomic_write(path, pack(key, bytes(exp.serialize())))
        prune(path.parent, keep=path)
        return True
    except Exception:  # noqa: BLE001 - the cache is an optimisation, never a failure
        return False


def kept(name: str, tag: str, parts: object, build: Callable[[], Callable], args: tuple) -> Callable:
    """The jitted program ``build()`` for the positional arguments ``args``, kept between processes.

    With a cache directory (:func:`set_cache_dir`) the program is read from there (:func:`load`)
    instead of traced, or exported there (:func:`save`) after its first trace, as ``name`` under
    the key :func:`key_text` makes of ``tag`` (the caller's code version), ``name``, ``parts``
    (everything else that changes the trace: options, packings) and the arguments' shapes and
    dtypes; kept in this process too, by directory and key. Without a directory: ``build()``. The
    program read back, not the traced one, is the one run after a save: the next process compiles
    nothing (JAX's persistent compilation cache holds this one's compiled form).
    """
    directory = cache_dir()
    if directory is None:
        return build()
    key = key_text(tag, (name, parts, signature(args)[1]))
    memo = (directory, name, key)
    fn = _KEPT.get(memo)
    if fn is None:
        fn = load(directory, name, key, args)
        if fn is None:
            with one_at_a_time(lock_of(entry_path(directory, name, key))):
                fn = load(directory, name, key, args)  # written meanwhile by the process that held the lock
                if fn is None:
                    fn = build()
                    if save(directory, name, key, fn, args):
                        fn = load(directory, name, key, args) or fn
        _KEPT[memo] = fn
    return fn


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """SHA-256 of every Python source of the ``eol_cal`` package (paths and bytes): part of the key
    of a program whose trace reaches across many modules (the plant's tick: its physics and the
    ECU's estimator, compensator and identifier), so that any change to the code traces it afresh
    instead of reading back a program of other code."""
    root = Path(__file__).resolve().parents[1]
    return _sources_sha256((path.relative_to(root).as_posix(), path) for path in sorted(root.rglob("*.py")))


def _sources_sha256(sources: Iterable[tuple[str, Path]]) -> str:
    """SHA-256 of ``(label, file)`` pairs in order: each label and the file's bytes, NUL-ended."""
    h = hashlib.sha256()
    for label, path in sources:
        h.update(label.encode() + b"\0")
        h.update(path.read_bytes() + b"\0")
    return h.hexdigest()


@functools.lru_cache(maxsize=8)
def sources_digest(*modules: str) -> str:
    """SHA-256 of the Python sources of ``modules`` (names, in that order): part of the key of a
    program whose trace reads only those modules' code (the fit's solver: its module and the model's
    constants), so that a change to them traces it afresh while a change elsewhere in the package
    keeps the entry (:func:`code_digest` for a program that reaches across the package)."""
    return _sources_sha256((name, _source_file(name)) for name in modules)


def _source_file(name: str) -> Path:
    """The source file of module ``name`` (imported or not)."""
    spec = importlib.util.find_spec(name)
    if spec is None or spec.origin is None:
        raise ValueError(f"no source file for module {name!r}")
    return Path(spec.origin)
