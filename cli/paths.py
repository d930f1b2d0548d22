"""The one check of a command's file arguments: no output may be one of its inputs, and no
output may be a device, FIFO or socket.

Every path a command writes counts, from any option, setting or default: the declared
outputs, the ``--log-file`` (appended to: it named the block being flashed, and the next run
failed), and, for ``run`` and ``station``, what the station settings name (:func:`check_more`).
Every records database is an input whether it exists yet or not: no output may be it or a
file SQLite keeps beside it (``-wal``, ``-shm``, ``-journal``); ``station --demo --lot
D/results.sqlite`` replaced the database it had just created with the lot page. Files read and written at
run time are guarded by :func:`eol_cal.infra.inputs.refuse_overwriting_input` (every atomic write).

``eol-cal fit X.mf4 -o X.mf4`` used to replace the capture with the result and exit 0. Every
command that writes declares its inputs and outputs with :func:`io_paths`; before it runs, each
output is compared with each input (and with the other outputs) as files: the same inode when
both exist (a hard link, a symbolic link, ``./x`` and ``x`` alike), else the same path after
resolving links. An existing output that is not a regular file (``/dev/sda``, a FIFO) is refused
too: outputs are written atomically, by renaming a new file over the old name, which would
replace the device node itself. Every refusal names the file (exit 2).
"""

from __future__ import annotations

import functools
import os
import stat
from collections.abc import Sequence
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from eol_cal.errors import InputError

PathArg = str | os.PathLike | None

#: ``click`` context meta keys: the ``--log-file`` of the command, and the paths already checked
LOG_FILE = "eol_cal.log_file"
_CHECKED = "eol_cal.io_checked"


def _paths(value: Any) -> list[str]:
    """A parameter's value as path strings (``nargs=-1`` tuples, ``None`` and URLs left out)."""
    if value is None:
        return []
    if isinstance(value, (tuple, list)):
        return [p for v in value for p in _paths(v)]
    text = os.fspath(value) if isinstance(value, os.PathLike) else str(value)
    return [] if "://" in text or not text else [text]


def _identity(path: str) -> tuple[str, object]:
    """What makes two names the same file: (dev, inode) when it exists, else the resolved path."""
    try:
        info = os.stat(path)
        return "inode", (info.st_dev, info.st_ino)
    except OSError:
        return "path", str(Path(path).resolve())


def _same(a: str, b: str) -> bool:
    kind_a, id_a = _identity(a)
    kind_b, id_b = _identity(b)
    if kind_a == kind_b == "inode":
        return id_a == id_b
    return str(Path(a).resolve()) == str(Path(b).resolve())


def _special(path: str) -> str | None:
    """Why an existing output cannot be written atomically (None when it can)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    for test, name in ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return None


def database_files(databases: Iterable[PathArg]) -> list[str]:
    """The files of records databases: each SQLite file and the files SQLite keeps beside it (URLs left out)."""
    from eol_cal.infra.inputs import SQLITE_SIDE_FILES

    return [f"{db}{side}" for v in databases for db in _paths(v) for side in ("", *SQLITE_SIDE_FILES)]


def check_io(inputs: Iterable[PathArg], outputs: Iterable[PathArg], output_dirs: Iterable[PathArg] = (),
             databases: Iterable[PathArg] = ()) -> None:
    """Refuse outputs that are inputs or files of a records database, that repeat each other, or
    that are devices/FIFOs; output directories that are files of a database.

    Parameters
    ----------
    inputs : iterable of path
        Files the command reads.
    outputs : iterable of path
        Files it writes (replaced atomically).
    output_dirs : iterable of path
        Directories it writes into: refused when they exist as something else than a directory.
    databases : iterable of path or URL
        Records databases it reads or writes (through SQLite, never as an output): no output or
        output directory may be one of their files, existing or not.

    Raises
    ------
    InputError
        Naming the output, and the input it is the same file as.
    """
    ins = [p for v in inputs for p in _paths(v)]
    outs = [p for v in outputs for p in _paths(v)]
    db_files = database_files(databases)
    for db in db_files[::4]:  # SQLite would write into it: a database is no other input of the command
        for inp in ins:
            if _same(db, inp):
                same = "" if os.path.normpath(db) == os.path.normpath(inp) else f" ({inp})"
                raise InputError(db, None, f"output is also an input of this command{same}; the records database "
                                           "would be written into it")
    for out in (*outs, *(p for v in output_dirs for p in _paths(v))):
        for k, db in enumerate(db_files):
            if _same(out, db):
                base = db_files[k - k % 4]  # each database's files: the file, then the three beside it
                what = "the records database" if db == base else f"a file SQLite keeps beside the records database {base}"
                raise InputError(out, None, f"output is {what}; it would be overwritten")
    for k, out in enumerate(outs):
        special = _special(out)
        if special is not None:
            raise InputError(out, None, f"output is {special}; outputs are regular files, replaced atomically")
        if os.path.isdir(out):
            raise InputError(out, None, "output is a directory; give a file name")
        for inp in ins:
            if _same(out, inp):
                same = "" if os.path.normpath(out) == os.path.normpath(inp) else f" ({inp})"
                raise InputError(out, None, f"output is also an input of this command{same}; it would be overwritten")
        for other in outs[:k]:
            if _same(out, other):
                raise InputError(out, None, f"given as two outputs ({other}); one would overwrite the other")
    for d in (p for v in output_dirs for p in _paths(v)):
        if os.path.exists(d) and not os.path.isdir(d):
            raise InputError(d, None, "output directory exists and is not a directory")


def _context() -> Any:
    import click

    return click.get_current_context(silent=True)


def _checked(ctx: Any) -> dict[str, Any]:
    if ctx is None:
        return {"inputs": [], "outputs": [], "dirs": []}
    return ctx.meta.setdefault(_CHECKED, {"inputs": [], "outputs": [], "dirs": []})


def check_more(inputs: Sequence[PathArg] = (), outputs: Sequence[PathArg] = (),
               output_dirs: Sequence[PathArg] = (), databases: Sequence[PathArg] = ()) -> None:
    """:func:`check_io` on paths a command learns while it runs (its settings file's, its
    defaults), together with those it was given (its options, the log file); each input and
    database noted for the run-time guard (:func:`eol_cal.infra.inputs.protect_database`: a file the
    command creates later cannot take a database's place either).

    Raises
    ------
    InputError
        As :func:`check_io`.
    """
    from eol_cal.infra.inputs import protect_database, register_input

    ctx = _context()
    seen = _checked(ctx)
    log_file = ctx.meta.get(LOG_FILE) if ctx is not None else None
    ins = [*seen["inputs"], *(p for v in inputs for p in _paths(v))]
    outs = [*seen["outputs"], *(p for v in outputs for p in _paths(v))]
    if log_file is not None and not seen.get("log"):
        outs.append(log_file)
        seen["log"] = True
    dirs = [*seen["dirs"], *(p for v in output_dirs for p in _paths(v))]
    dbs = [*seen.get("databases", []), *(p for v in databases for p in _paths(v))]
    check_io(ins, outs, dirs, dbs)
    seen.update(inputs=ins, outputs=outs, dirs=dirs, databases=dbs)
    for path in ins:
        register_input(path)
    for db in dbs:
        protect_database(db)


def io_paths(inputs: tuple[str, ...] = (), outputs: tuple[str, ...] = (), output_dirs: tuple[str, ...] = (),
             databases: tuple[str, ...] = ()) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorator of a command: :func:`check_io` on the named parameters (and the ``--log-file``)
    before it runs; ``databases`` names its records database parameters (``--db``).

    Put it under :func:`cli.common.handle_errors` (and :func:`cli.common.exchange_log_options`),
    so that a refusal is one line and exit 2.
    """

    def decorate(func: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(func)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            check_more([kwargs.get(n) for n in inputs], [kwargs.get(n) for n in outputs],
                       [kwargs.get(n) for n in output_dirs], [kwargs.get(n) for n in databases])
            return func(*args, **kwargs)

        return wrapper

    return decorate
