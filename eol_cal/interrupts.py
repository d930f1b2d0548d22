"""SIGINT, SIGTERM and SIGHUP as an exception, and holding them off while a record is written.

The CLI's handler (``cli.common.signals_interrupt``) calls :func:`deliver`, which raises
:class:`~eol_cal.errors.Interrupted` in the main thread at once, so every ``finally`` runs (the
dyno's safe state, the ECU's clean-up). Code that must not be cut short once it started (writing
a run's record and report) runs inside :func:`shielded`: a signal arriving there is raised when
the block ends.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from eol_cal.errors import Interrupted

_depth = 0
_pending: str | None = None


def deliver(signal_name: str) -> None:
    """Raise :class:`Interrupted` now, or at the end of the enclosing :func:`shielded` block."""
    global _pending
    if _depth:
        _pending = _pending or signal_name
        return
    raise Interrupted(signal_name)


@contextlib.contextmanager
def shielded() -> Iterator[None]:
    """Hold signals off for the block; one that arrived meanwhile is raised after it."""
    global _depth, _pending
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
    if _depth == 0 and _pending is not None:
        name, _pending = _pending, None
        raise Interrupted(name)
