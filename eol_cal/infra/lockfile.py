"""Lock files (the kernel's ``flock``) opened as untrusted paths: the station's record journal,
the panel's station lock and the kept programs' compile locks.

A lock file lives in a directory other programs and users may write (a shared spool, ``/tmp``,
a cache). What sits at its path is not trusted: a symbolic link there would make the lock's
writes land in the link's target (the panel's lock truncated and rewrote whatever file a link
named), and an ``open()`` of a FIFO waits for a writer that never comes. So a lock file is
opened without following a link, without waiting, and is used only when it is a regular file.
"""

from __future__ import annotations

import errno
import os
import stat

#: how a lock file is opened: created if missing, never through a link, never blocking on a
#: FIFO, never becoming the process's controlling terminal, not inherited by child processes
LOCK_FLAGS = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC


class NotALockFile(OSError):
    """What sits at a lock file's path is no regular file (a FIFO, a device, a socket)."""


def open_lock_file(path: str | os.PathLike[str]) -> int:
    """A descriptor of the lock file ``path`` (created when missing, mode 0644), ready for ``flock``.

    Raises
    ------
    OSError
        ``ELOOP`` where ``path`` is a symbolic link, :class:`NotALockFile` where it is no regular
        file, else what ``open()`` raised (a directory, no permission, a missing parent); nothing
        at the path is changed. :func:`refusal` says it in words.
    """
    fd = os.open(path, LOCK_FLAGS, 0o644)
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise NotALockFile(errno.EINVAL, "not a regular file", os.fspath(path))
    except BaseException:
        os.close(fd)
        raise
    return fd


def refusal(exc: OSError) -> str:
    """Why :func:`open_lock_file` refused, in words for an operator (what to do about it)."""
    if isinstance(exc, NotALockFile):
        return "is not a regular file (a FIFO, a device or a socket sits at its path): remove it"
    if exc.errno == errno.ELOOP:
        return "is a symbolic link (a lock file is never followed to another file): remove it"
    if exc.errno == errno.EISDIR:
        return "is a directory: remove it"
    return f"cannot be opened ({exc.strerror or exc})"
