"""Reading untrusted input files: the one place that opens them, so every refusal names the file.

A FIFO named ``capture.csv`` must not block the tool, a directory or a device must not be read
as data, non-UTF-8 bytes in a TOML file, JSON nested a million deep or a number of 100 000
digits must end in one line naming the file (:class:`~eol_cal.errors.InputError`, exit 2), not
in a traceback or a hang. The file type is checked before the file is opened (and again on the
open descriptor, which is opened non-blocking so that a FIFO swapped in meanwhile cannot block).
"""

from __future__ import annotations

import json
import os
import stat
import tomllib
from typing import Any

from eol_cal.errors import InputError

#: deepest nesting of arrays and objects a JSON input may have (the tool's own documents: < 10)
MAX_JSON_DEPTH = 64


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def check_regular(path: str | os.PathLike, field: str | None = None) -> None:
    """Refuse ``path`` unless it is an existing regular file (links are followed), without opening it.

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


def read_bytes(path: str | os.PathLike, field: str | None = None, max_bytes: int | None = None) -> bytes:
    """The bytes of a regular file; :class:`InputError` naming it for anything else.

    Parameters
    ----------
    path : path
        The input file.
    field : str, optional
        Field named in errors (e.g. the option's subject: ``"key"``).
    max_bytes : int, optional
        Refuse a larger file (bytes).
    """
    file = str(path)
    check_regular(path, field)
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


def load_toml(path: str | os.PathLike) -> dict[str, Any]:
    """A TOML file as a dict: refuses non-UTF-8 bytes and bad TOML with the file named."""
    text = read_text(path)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(str(path), None, f"not valid TOML: {exc}") from None


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

    Refused: invalid JSON, nesting deeper than :data:`MAX_JSON_DEPTH`, integers longer than
    Python converts (4300 digits). ``NaN``/``Infinity`` and numbers beyond binary64 (``1e400``,
    read as infinity) are left to the reader's type check, which names the field.
    """
    # the C parser recurses per level; refuse deep documents before they reach it
    if text.count("[") + text.count("{") > MAX_JSON_DEPTH and _depth(text) > MAX_JSON_DEPTH:
        raise InputError(source, field, f"nested deeper than {MAX_JSON_DEPTH} levels")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(source, field, f"not valid JSON: {exc}") from None
    except (ValueError, RecursionError) as exc:  # an integer of too many digits
        raise InputError(source, field, f"not valid JSON: {exc}") from None


def load_json(path: str | os.PathLike, max_bytes: int | None = None) -> Any:
    """A JSON file (UTF-8), parsed as :func:`loads_json` does."""
    return loads_json(read_text(path, max_bytes=max_bytes), str(path))
