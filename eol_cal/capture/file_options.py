"""How a channel map says what a file is: its ``[file]`` table (format, delimiter, decimal mark, ...).

::

    [file]
    format = "text"      # "text" (delimited text: CSV, TSV, ...), "tdms" or "mf4": whatever the suffix
    delimiter = "\\t"    # text: "," (default), ";", "\\t", "|", or " " (any run of blanks)
    decimal = ","        # text: "." (default) or ","
    units_row = true     # text: the line after the header names each column's unit
    skip_lines = 3       # text: lines before the header that are read as nothing (a DAQ's preamble)
    encoding = "cp1252"  # text: the file's encoding (default UTF-8, a byte-order mark tolerated)
    sample_rate = 1e4    # tdms: sample rate (Hz) of the channels whose wf_increment is missing

Without ``format`` the file's suffix decides (``.csv`` text, ``.tdms``, ``.mf4``); an option
of another format than the one the file is read as is refused.
"""

from __future__ import annotations

import codecs
import math
from dataclasses import dataclass

from eol_cal.errors import InputError

#: formats a capture file may be read as
FORMATS = ("text", "tdms", "mf4")
#: the format of each known suffix (a map's ``format`` reads any suffix)
SUFFIX_FORMATS = {".csv": "text", ".tdms": "tdms", ".mf4": "mf4"}
DELIMITERS = (",", ";", "\t", "|", " ")
#: most preamble lines skipped (a DAQ's preamble is a few dozen)
MAX_SKIP_LINES = 100_000
#: highest sample rate taken (Hz): far beyond any DAQ on a motor bench
MAX_SAMPLE_RATE = 1e9

#: option -> the format it belongs to
_OPTION_FORMAT = {"delimiter": "text", "decimal": "text", "units_row": "text", "skip_lines": "text",
                  "encoding": "text", "sample_rate": "tdms"}


@dataclass(frozen=True)
class FileOptions:
    """A map's ``[file]`` table (defaults: a capture-format CSV).

    Attributes
    ----------
    format : str or None
        ``"text"``, ``"tdms"`` or ``"mf4"``; ``None``: the file's suffix decides.
    delimiter, decimal : str
        Text: the column separator (``" "``: any run of blanks) and the decimal mark.
    units_row : bool
        Text: the line after the header gives each column's unit.
    skip_lines : int
        Text: lines before the header skipped unread.
    encoding : str
        Text: the file's encoding.
    sample_rate : float or None
        TDMS: sample rate (Hz) of channels without a ``wf_increment`` property.
    given : tuple of str
        The options the map set (to refuse those of another format).
    """

    format: str | None = None
    delimiter: str = ","
    decimal: str = "."
    units_row: bool = False
    skip_lines: int = 0
    encoding: str = "utf-8"
    sample_rate: float | None = None
    given: tuple[str, ...] = ()

    def check_format(self, file_format: str, file: str, map_file: str) -> None:
        """Refuse an option that belongs to another format than ``file_format``."""
        for option in self.given:
            if _OPTION_FORMAT.get(option, file_format) != file_format:
                raise InputError(map_file, f"file.{option}",
                                 f"an option of {_OPTION_FORMAT[option]} files, but {file} is read as {file_format}")


def _fail(path: str, key: str, reason: str) -> InputError:
    return InputError(path, f"file.{key}", reason)


def parse_file_options(table: object, path: str) -> FileOptions:
    """The checked ``[file]`` table of a map file ``path``.

    Raises
    ------
    InputError
        Unknown keys or formats, a delimiter or decimal mark not listed, the same character for
        both, an unknown encoding, a negative skip, a sample rate not finite and positive.
    """
    if not isinstance(table, dict):
        raise InputError(path, "file", "must be a table")
    unknown = set(table) - {"format", *_OPTION_FORMAT}
    if unknown:
        raise _fail(path, sorted(unknown)[0], f"unknown key; allowed: format, {', '.join(_OPTION_FORMAT)}")
    values: dict[str, object] = {"given": tuple(k for k in table if k != "format")}
    fmt = table.get("format")
    if fmt is not None:
        if fmt not in FORMATS:
            raise _fail(path, "format", f"{fmt!r} is not one of {', '.join(map(repr, FORMATS))}")
        values["format"] = fmt
    for key, allowed in (("delimiter", DELIMITERS), ("decimal", (".", ","))):
        if key in table:
            if table[key] not in allowed:
                raise _fail(path, key, f"{table[key]!r} is not one of {', '.join(map(repr, allowed))}")
            values[key] = table[key]
    if values.get("delimiter", ",") == values.get("decimal", "."):
        raise _fail(path, "decimal", "the decimal mark cannot also be the delimiter")
    if "units_row" in table:
        if not isinstance(table["units_row"], bool):
            raise _fail(path, "units_row", "must be true or false")
        values["units_row"] = table["units_row"]
    if "skip_lines" in table:
        skip = table["skip_lines"]
        if isinstance(skip, bool) or not isinstance(skip, int) or not 0 <= skip <= MAX_SKIP_LINES:
            raise _fail(path, "skip_lines", f"must be an integer 0..{MAX_SKIP_LINES}, got {skip!r}")
        values["skip_lines"] = skip
    if "encoding" in table:
        encoding = table["encoding"]
        try:
            codecs.lookup(encoding)
        except (LookupError, TypeError):
            raise _fail(path, "encoding", f"unknown encoding {encoding!r}") from None
        values["encoding"] = encoding
    if "sample_rate" in table:
        rate = table["sample_rate"]
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not (
                math.isfinite(rate) and 0 < rate <= MAX_SAMPLE_RATE):
            raise _fail(path, "sample_rate", f"must be a number of Hz in (0, {MAX_SAMPLE_RATE:g}], got {rate!r}")
        values["sample_rate"] = float(rate)
    options = FileOptions(**values)  # type: ignore[arg-type]
    if options.format is not None:
        options.check_format(options.format, "the file", path)
    return options
