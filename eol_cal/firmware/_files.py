"""File reads for the firmware artefacts that name the file on failure."""

from __future__ import annotations

import os
from pathlib import Path

from eol_cal.errors import InputError


def read_bytes(path: str | os.PathLike, field: str = "file") -> bytes:
    """Read a whole file; :class:`InputError` naming it when it cannot be read."""
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise InputError(str(path), field, exc.strerror or str(exc)) from exc
