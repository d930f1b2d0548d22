"""Reading untrusted input files: the one place that opens them, so every refusal names the file.

A FIFO named ``capture.csv`` must not block the tool, a directory or a device must not be read
as data, non-UTF-8 bytes in a TOML file, JSON nested a million deep or a number of 100 000
digits must end in one line naming the file (:class:`~eol_cal.errors.InputError`, exit 2), not
in a traceback or a hang. The file type is checked before the file is opened (and again on the
open descriptor, which is opened non-blocking so that a FIFO swapped in meanwhile cannot block).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import stat
import threading
import tomllib
from collections.abc import Iterator
from typing import Any

from eol_cal.errors import InputError



def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


# --------------------------------------------------------------------------------------------
# the inputs of the running command: no file it read may be replaced by a file it writes

_ledger: dict[tuple[int, int], str] | None = None
_ledger_lock = threading.Lock()
#: paths no output of the running command may land on, resolved, with what they are: the records
#: database and the files SQLite keeps beside it, named before they exist (a database the command
#: creates is not in the ledger of inodes when the command starts, and its journal never is)
_guarded: dict[str, str] = {}

#: the files SQLite keeps beside a database (``DB-wal``, ``DB-shm``, ``DB-journal``)
SQLITE_SIDE_FILES = ("-wal", "-shm", "-journal")
#: how a file SQLite wrote starts: a database, a write-ahead log (two byte orders), a rollback journal
_SQLITE_MAGIC = ((b"SQLite format 3\x00", "a SQLite database"), (b"\x37\x7f\x06\x82", "a SQLite write-ahead log"),
                 (b"\x37\x7f\x06\x83", "a SQLite write-ahead log"),
                 (b"\xd9\xd5\x05\xf9\x20\xa1\x63\xd7", "a SQLite rollback journal"))


@contextlib.contextmanager
def command_inputs() -> Iterator[None]:
    """Keep, while a command runs, the identity (device, inode) of every file it reads.

    The CLI's one entry (``cli.common.handle_errors``) enters it; :func:`refuse_overwriting_input`
    then refuses a write over any of them, whatever option, setting or default named the output
    (checks made before the command runs see the paths known then; this sees every one). A
    command run inside another (a test) shares the outer one's record.
    """
    global _ledger
    with _ledger_lock:
        outer = _ledger is not None
        if not outer:
            _ledger = {}
    try:
        yield
    finally:
        if not outer:
            with _ledger_lock:
                _ledger = None
                _guarded.clear()


def protect_database(db: str | os.PathLike) -> None:
    """Note the records database ``db`` (a SQLite file; a URL is left out) and the files SQLite
    keeps beside it as no output's place while the command runs, whether they exist yet or not
    (:func:`refuse_overwriting_input`)."""
    text = os.fspath(db)
    if _ledger is None or "://" in text or not text:
        return
    register_input(text)
    with _ledger_lock:
        for side in ("", *SQLITE_SIDE_FILES):
            _guarded.setdefault(os.path.realpath(text + side), "the records database" + (f" ({side[1:]} file)" if side else ""))


def _sqlite_file(path: str | os.PathLike) -> str | None:
    """What SQLite file ``path`` is (a database, its write-ahead log or journal, or the shared
    memory beside a database), or None."""
    try:
        with open(path, "rb", opener=lambda p, f: os.open(p, f | os.O_NONBLOCK)) as fh:
            head = fh.read(16)
    except OSError:
        return None
    for magic, what in _SQLITE_MAGIC:
        if head.startswith(magic):
            return what
    text = os.fspath(path)
    for side in SQLITE_SIDE_FILES:  # DB-shm has no magic of its own: named by the database beside it
        if text.endswith(side) and _sqlite_file(text[: -len(side)]) == "a SQLite database":
            return f"the {side[1:]} file of a SQLite database"
    return None


def register_input(path: str | os.PathLike) -> None:
    """Note ``path`` as read by the running command (no-op outside one, or for a missing file)."""
    if _ledger is None:
        return
    try:
        info = os.stat(path)
    except OSError:
        return
    with _ledger_lock:
        if _ledger is not None:
            _ledger.setdefault((info.st_dev, info.st_ino), str(path))


def refuse_overwriting_input(path: str | os.PathLike) -> None:
    """Raise :class:`InputError` when ``path`` is a file the running command has read, its records
    database or a file of it (:func:`protect_database`), or any SQLite database or journal.

    Raises
    ------
    InputError
        Naming ``path`` and the input it is (the same file by another name, a link, too).
    """
    guarded = _guarded.get(os.path.realpath(os.fspath(path)))
    if guarded is not None:
        raise InputError(str(path), None, f"output is {guarded} of this command; it would be overwritten")
    if os.path.isfile(path) and (what := _sqlite_file(path)) is not None:
        # whichever database it is: no output of eol-cal replaces one (records, journals, baselines)
        raise InputError(str(path), None, f"output is {what}; eol-cal never replaces a database with an output")
    ledger = _ledger
    if ledger is None:
        return
    try:
        info = os.stat(path)
    except OSError:
        return  # a new file
    read_as = ledger.get((info.st_dev, info.st_ino))
    if read_as is not None:
        same = "" if os.path.normpath(str(path)) == os.path.normpath(read_as) else f" ({read_as})"
        raise InputError(str(path), None, f"output is also an input of this command{same}; it would be overwritten")


def check_regular(path: str | os.PathLike, field: str | None = None, register: bool = True) -> None:
    """Refuse ``path`` unless it is an existing regular file (links are followed), without opening it.

    With ``register`` (the default) the file is noted as an input of the running command
    (:func:`register_input`).

    Raises
    ------
    InputError
        Missing, unreadable, or a directory, FIFO, device or socket.
    """
    file = str(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise InputError(file, field, "cannot read: file not found") from None
    except OSError as exc:
        raise InputError(file, field, f"cannot read: {exc.strerror or exc}") from None
    if not stat.S_ISREG(mode):
        raise InputError(file, field, f"{_kind(mode)}, expected a regular file")
    if register:
        register_input(path)


def read_bytes(path: str | os.PathLike, field: str | None = None, max_bytes: int | None = None,
               register: bool = True) -> bytes:
    """The bytes of a regular file; :class:`InputError` naming it for anything else.

    Parameters
    ----------
    path : path
        The input file.
    field : str, optional
        Field named in errors (e.g. the option's subject: ``"key"``).
    max_bytes : int, optional
        Refuse a larger file (bytes).
    register : bool
        Note the file as an input of the running command (False: a state file the caller
        rewrites itself, the ECU simulator's flash image).
    """
    file = str(path)
    check_regular(path, field, register)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        raise InputError(file, field, f"cannot read: {exc.strerror or exc}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):  # swapped for a FIFO or device since the check
            raise InputError(file, field, f"{_kind(info.st_mode)}, expected a regular file")
        if max_bytes is not None and info.st_size > max_bytes:
            raise InputError(file, field, f"{info.st_size} bytes, more than the {max_bytes} such a file may have")
        with os.fdopen(fd, "rb", closefd=False) as fh:
            return fh.read()
    except OSError as exc:
        raise InputError(file, field, f"cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def read_text(path: str | os.PathLike, field: str | None = None, encoding: str = "utf-8",
              max_bytes: int | None = None) -> str:
    """The text of a regular file in ``encoding`` (``utf-8-sig`` tolerates a byte-order mark)."""
    raw = read_bytes(path, field, max_bytes)
    try:
        return raw.decode(encoding)
    except UnicodeDecodeError as exc:
        name = "UTF-8" if encoding.startswith("utf-8") else encoding
        raise InputError(str(path), field, f"not {name} text (byte 0x{raw[exc.start]:02x} at offset {exc.start})") from None


#: deepest nesting of tables and arrays a TOML or JSON input may have (the tool's own: < 10)
MAX_NESTING = 64
#: largest TOML file the tool reads (settings, limits, maps, motors, benches, profiles: < 20 KiB)
MAX_TOML_BYTES = 1 << 20
#: TOML integers are 64-bit signed (TOML 1.0, "Integer"); JSON ones are held to the same range,
#: so that no reader meets an integer that overflows a float or a C field
INT_RANGE = (-(1 << 63), (1 << 63) - 1)
#: a dotted key of more than MAX_NESTING parts (bare or quoted: TOML's ``a . "b" . c``) anywhere in
#: the text. Python's TOML parser takes quadratic time in a dotted key's length (10 000 parts 4 s, a
#: 1 MiB file of one key hours: measured 2026-11-29), so such a key is refused before parsing.
#: Strings are not told apart: a value of 65 dot-joined words would be refused too (the tool's
#: files hold none). Linear in practice: a match starts only where a part starts, and each part is
#: taken whole (possessive), so no start rescans more than 64 parts.
_DEEP_DOTTED_KEY = re.compile(
    r"(?<![A-Za-z0-9_-])(?:(?:[A-Za-z0-9_-]++|\"[^\"\n]*+\"|'[^'\n]*+')[ \t]*+\.[ \t]*+)"
    + f"{{{MAX_NESTING}}}")


def _check_tree(doc: Any, source: str | None, field: str | None, finite: bool) -> None:
    """Walk a parsed document (iteratively): nesting, integer range, and (``finite``) no NaN or
    infinity; the refusal names the offending value's path (``motors[0].k6.value``)."""
    stack: list[tuple[Any, str, int]] = [(doc, field or "", 0)]
    while stack:
        value, where, depth = stack.pop()
        if isinstance(value, dict):
            if depth >= MAX_NESTING:
                raise InputError(source, where or None, f"nested deeper than {MAX_NESTING} levels")
            stack.extend((v, f"{where}.{k}" if where else str(k), depth + 1) for k, v in value.items())
        elif isinstance(value, list):
            if depth >= MAX_NESTING:
                raise InputError(source, where or None, f"nested deeper than {MAX_NESTING} levels")
            stack.extend((v, f"{where}[{i}]", depth + 1) for i, v in enumerate(value))
        elif isinstance(value, bool):
            continue
        elif isinstance(value, int) and not INT_RANGE[0] <= value <= INT_RANGE[1]:
            raise InputError(source, where or None, f"integer of {len(str(abs(value)))} digits, outside the "
                                                    "64-bit range")
        elif finite and isinstance(value, float) and not math.isfinite(value):
            raise InputError(source, where or None, f"{value!r} is not a finite number")


def loads_toml(text: str, source: str | None) -> dict[str, Any]:
    """Parse untrusted TOML text: :class:`InputError` naming ``source`` for anything it cannot be.

    The one TOML parser of the tool (settings, limits, channel and register maps, motors,
    benches, profiles). Refused: bad TOML, nesting deeper than :data:`MAX_NESTING` (arrays,
    inline tables or dotted keys: the parser recurses per level), integers outside 64 bits
    (a 5000-digit one is a ``ValueError`` in the parser, a 400-digit one overflows a float
    later). ``nan``/``inf`` are left to the reader's own check, which names the key.
    """
    if text.count(".") > MAX_NESTING and _DEEP_DOTTED_KEY.search(text):
        raise InputError(source, None, f"a dotted key of more than {MAX_NESTING} parts (nested deeper than "
                                       f"{MAX_NESTING} levels)")
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(source, None, f"not valid TOML: {exc}") from None
    except (ValueError, RecursionError) as exc:  # an integer of too many digits; deep arrays or tables
        raise InputError(source, None, f"not valid TOML: {str(exc)[:200]}") from None
    _check_tree(doc, source, None, finite=False)
    return doc


def load_toml(path: str | os.PathLike, max_bytes: int = MAX_TOML_BYTES) -> dict[str, Any]:
    """A TOML file as a dict (:func:`loads_toml`): a FIFO, a device, more than ``max_bytes``,
    non-UTF-8 bytes or bad TOML are refused with the file named."""
    return loads_toml(read_text(path, max_bytes=max_bytes), str(path))


def _depth(text: str) -> int:
    """Deepest nesting of ``[``/``{`` outside strings (linear; only to refuse before parsing)."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def loads_json(text: str, source: str | None, field: str | None = None) -> Any:
    """Parse untrusted JSON text: :class:`InputError` naming ``source`` for anything it cannot be.

    The one JSON parser of the tool's inputs (fit results, spool files, refit results, stored
    records). Refused: invalid JSON, nesting deeper than :data:`MAX_NESTING`, integers outside
    64 bits (longer than Python converts: 4300 digits, or beyond a float), ``NaN``/``Infinity``
    and numbers beyond binary64 (``1e400``, read as infinity): the tool writes none of them
    (``allow_nan=False``), and a reader that met one would fail far from here. The refusal
    names the value's path (``field 'motors[0].k6.value'``).
    """
    # the C parser recurses per level; refuse deep documents before they reach it
    if text.count("[") + text.count("{") > MAX_NESTING and _depth(text) > MAX_NESTING:
        raise InputError(source, field, f"nested deeper than {MAX_NESTING} levels")
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(source, field, f"not valid JSON: {exc}") from None
    except (ValueError, RecursionError) as exc:  # an integer of too many digits
        raise InputError(source, field, f"not valid JSON: {exc}") from None
    _check_tree(doc, source, field, finite=True)
    return doc


def load_json(path: str | os.PathLike, max_bytes: int | None = None) -> Any:
    """A JSON file (UTF-8), parsed as :func:`loads_json` does."""
    return loads_json(read_text(path, max_bytes=max_bytes), str(path))
