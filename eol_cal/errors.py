"""Exceptions shared by the library; the CLI maps them to exit codes.

Exit codes: 0 ok, 1 a check or limit failed (:class:`CheckFailed`), 2 bad input or usage
(:class:`InputError` and every other :class:`EolCalError`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator


class EolCalError(Exception):
    """Base class of every error the tool reports to its user."""

    exit_code = 2


#: longest field name and reason said whole in a message: a hostile header cell or metadata value
#: of 200 000 characters is cut, not echoed into a one-line error
MAX_FIELD_CHARS = 120
MAX_REASON_CHARS = 1000


def _message(file: str | None, field: str | None, reason: str) -> str:
    if field and len(field) > MAX_FIELD_CHARS:
        field = f"{field[:MAX_FIELD_CHARS // 2]}... ({len(field)} characters)"
    if len(reason) > MAX_REASON_CHARS:
        reason = f"{reason[:MAX_REASON_CHARS // 2]}... ({len(reason)} characters)"
    where = ", ".join(p for p in (f"file {file}" if file else "", f"field {field!r}" if field else "") if p)
    return f"{where}: {reason}" if where else reason


class InputError(EolCalError):
    """Input that cannot be trusted: names the file, the field (channel, key) and the reason."""

    def __init__(self, file: str | None, field: str | None, reason: str) -> None:
        self.file = file
        self.field = field
        self.reason = reason
        super().__init__(_message(file, field, reason))

    def located(self, file: str) -> InputError:
        """This refusal naming ``file`` (itself when it names a file already), same class and field."""
        if self.file is not None:
            return self
        new = self.__class__.__new__(self.__class__)
        new.__dict__.update(self.__dict__)
        new.file = file
        new.args = (_message(file, self.field, self.reason),)
        return new


@contextlib.contextmanager
def naming(file: str | None) -> Iterator[None]:
    """Refusals raised inside that name no file name ``file``: a library check that sees only
    values (a block's fields, a table's harmonics) reports the file the values came from."""
    try:
        yield
    except InputError as exc:
        if file is None or exc.file is not None:
            raise
        raise exc.located(file) from None


class WriteError(InputError, OSError):
    """An output file could not be written (full disk, no permission): names the target, not the
    temporary file; nothing of it was left behind (exit code 2).

    Also an :class:`OSError` with the original ``errno`` and ``strerror``, so callers that spool or
    retry on OS errors keep doing so.
    """

    def __init__(self, file: str, cause: OSError) -> None:
        super().__init__(file, None, f"cannot write: {cause.strerror or cause}")
        self.errno = cause.errno
        self.strerror = cause.strerror or str(cause)

    __str__ = BaseException.__str__  # the message, not OSError's "[Errno 28] ..."


class CheckFailed(EolCalError):
    """A check or limit did not hold (exit code 1); the run itself worked."""

    exit_code = 1


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived: the command stops after its own cleanup (exit code 2).

    A :class:`KeyboardInterrupt`, so ``except Exception`` in a library never swallows it and
    code that already makes a machine safe on Ctrl-C does so for SIGTERM too.

    Parameters
    ----------
    signal_name : str
        ``SIGINT`` or ``SIGTERM``.
    during : str or None
        The step that was running.
    detail : str
        What the interruption left behind (e.g. which block the ECU boots).
    """

    exit_code = 2

    def __init__(self, signal_name: str = "SIGINT", during: str | None = None, detail: str = "") -> None:
        self.signal_name = signal_name
        self.during = during
        self.detail = detail
        text = f"interrupted by {signal_name}" + (f" during {during}" if during else "")
        super().__init__(text + (f"; {detail}" if detail else ""))


class ResultFormatError(InputError, ValueError):
    """A fit result (``eol-cal/fit-result/1``) that does not hold what its schema says (exit code 2)."""
