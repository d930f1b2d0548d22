"""Reading and writing captures by file suffix: ``.csv`` and ``.mf4`` (capture format v1), and
reading NI TDMS (``.tdms``) and delimited text of any suffix when a channel map says what it is."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from eol_cal.capture.channel_map import ChannelMap, load_channel_map
from eol_cal.capture.file_options import SUFFIX_FORMATS
from eol_cal.capture.data import Capture
from eol_cal.capture.validate import validate as _validate
from eol_cal.errors import InputError, WriteError

#: file suffixes the writers take (the readers take these and ``.tdms``, and any with a map's ``[file] format``)
SUFFIXES = (".csv", ".mf4")


def _suffix(path: str | Path) -> str:
    suffix = Path(path).suffix.lower()
    if suffix not in SUFFIXES:
        raise InputError(str(path), None, f"unknown capture file type {suffix or '(none)'!r}; known: {', '.join(SUFFIXES)}")
    return suffix


def capture_format(path: str | Path, channel_map: ChannelMap | None = None) -> str:
    """What ``path`` is read as: ``"text"``, ``"tdms"`` or ``"mf4"``; the map's ``[file] format``,
    else the suffix's.

    Raises
    ------
    InputError
        An unknown suffix and no format in the map; a map option of another format.
    """
    file = str(path)
    fmt = channel_map.file.format if channel_map is not None else None
    if fmt is None:
        suffix = Path(path).suffix.lower()
        fmt = SUFFIX_FORMATS.get(suffix)
        if fmt is None:
            raise InputError(file, None, f"unknown capture file type {suffix or '(none)'!r}; known: "
                                         f"{', '.join(SUFFIX_FORMATS)} (a channel map's [file] format reads any "
                                         "suffix: format = \"text\" for delimited text)")
    if channel_map is not None:
        channel_map.file.check_format(fmt, file, channel_map.source)
    return fmt


def read_capture(
    path: str | Path,
    channel_map: ChannelMap | str | Path | None = None,
    validate: bool = True,
) -> Capture:
    """Read a capture file into canonical channels (SI units) and check it.

    Parameters
    ----------
    path : path
        ``.csv``, ``.mf4`` or ``.tdms`` file, or any file whose format the map's ``[file]`` names.
    channel_map : ChannelMap or path, optional
        Channel map (or its TOML file) for a foreign file's channel names, units and format.
    validate : bool
        Refuse a capture that cannot be trusted (:func:`eol_cal.capture.validate.validate`).
        ``False`` only for tools that describe a file, never for analyses.

    Returns
    -------
    Capture
        ``source`` is ``str(path)``.

    Raises
    ------
    InputError
        Unknown suffix, unreadable file, a bad map, or a capture that fails validation.
    """
    if channel_map is not None and not isinstance(channel_map, ChannelMap):
        channel_map = load_channel_map(channel_map)
    fmt = capture_format(path, channel_map)
    try:
        if fmt == "text":
            from eol_cal.capture.csv_io import read_csv

            capture = read_csv(path, channel_map)
        elif fmt == "tdms":
            from eol_cal.capture.tdms_io import read_tdms

            capture = read_tdms(path, channel_map)
        else:
            from eol_cal.capture.mdf4_io import read_mdf4

            capture = read_mdf4(path, channel_map)
    except OSError as exc:
        raise InputError(str(path), None, f"cannot read: {exc.strerror or exc}") from exc
    return _validate(capture) if validate else capture


def write_capture(capture: Capture, path: str | Path, **opts: Any) -> None:
    """Write a capture, atomically, in the format its suffix names.

    Parameters
    ----------
    capture : Capture
        The capture (written as it is: writers do not validate, so tests can write bad files).
    path : path
        ``.csv`` or ``.mf4`` target; replaced atomically.
    **opts
        Writer options: ``.mf4`` takes ``digital="levels"|"events"`` and ``compression``;
        ``.csv`` takes none.
    """
    suffix = _suffix(path)
    try:
        _write(capture, path, suffix, opts)
    except WriteError:
        raise
    except OSError as exc:
        raise InputError(str(path), None, f"cannot write: {exc.strerror or exc}") from exc


def _write(capture: Capture, path: str | Path, suffix: str, opts: dict[str, Any]) -> None:
    if suffix == ".csv":
        from eol_cal.capture.csv_io import write_csv

        if opts:
            raise InputError(str(path), sorted(opts)[0], "CSV writer takes no options")
        write_csv(capture, path)
    else:
        from eol_cal.capture.mdf4_io import write_mdf4

        unknown = set(opts) - {"digital", "compression"}
        if unknown:
            raise InputError(str(path), sorted(unknown)[0], "unknown MDF4 writer option; known: digital, compression")
        write_mdf4(capture, path, **opts)
