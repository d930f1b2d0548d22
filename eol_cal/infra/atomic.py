"""Atomic file replacement: a reader never sees a half-written capture, block, record or report."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from collections.abc import Iterator

from eol_cal.errors import WriteError
from eol_cal.infra.inputs import refuse_overwriting_input


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success fsync it and ``os.replace`` it there.

    The temporary file keeps ``path``'s suffix (asammdf picks the format from it) and lives in
    the same directory, so the final rename is atomic. On an exception it is removed and
    ``path`` is left as it was; an :class:`OSError` (a full disk) becomes a
    :class:`~eol_cal.errors.WriteError` naming ``path``. A ``path`` that the running command
    read is refused (:func:`eol_cal.infra.inputs.refuse_overwriting_input`).
    """
    path = Path(path)
    refuse_overwriting_input(path)  # whatever named it: an option, a setting, a default
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent or ".")
    except OSError as exc:
        raise WriteError(str(path), exc) from exc
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        # mkstemp creates 0600; a capture gets the permissions any new file would get
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        if isinstance(exc, OSError) and not isinstance(exc, WriteError):
            # a full disk (ENOSPC) or a refused rename: the target named, nothing left behind
            raise WriteError(str(path), exc) from exc
        raise
    with contextlib.suppress(OSError):
        dir_fd = os.open(path.parent or ".", os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def atomic_write(path: str | Path, data: bytes | str, encoding: str = "utf-8") -> None:
    """Write ``data`` to ``path`` so that readers see the old or the new file, never a part.

    Creates missing parent directories.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise WriteError(str(path), exc) from exc
    raw = data.encode(encoding) if isinstance(data, str) else data
    with atomic_path(path) as tmp:
        tmp.write_bytes(raw)
