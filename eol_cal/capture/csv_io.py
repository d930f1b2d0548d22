"""CSV captures (capture format v1): ``# key: value`` metadata lines, a header, numeric rows.

::

    # serial: M-0001
    # poles: 6
    # truth.k6: 0.00062
    t [s],torque [N*m],enc_a,enc_b,hall,iq_ref [A]
    0.0,3.1875,1,0,5,65.0

UTF-8 (a byte-order mark is tolerated), comma-separated, ``.`` as decimal mark. A channel map's
``[file]`` table reads other delimited text (tab or semicolon separated, a decimal comma, a
units row, a preamble, another encoding; :mod:`eol_cal.capture.file_options`). ``#`` lines
that do not read ``key: value`` are comments. Floats are written in their shortest exact form
(Python ``repr``), so a write-read round trip returns the same float64 values. CSV cannot hold
change events: digital channels are written as the levels at the sample times.
"""

from __future__ import annotations

import codecs
import re
from pathlib import Path

import numpy as np

from eol_cal.infra.atomic import atomic_path
from eol_cal.capture.channel_map import ChannelMap, apply_channel_map
from eol_cal.capture.columns import Column, assemble
from eol_cal.capture.file_options import FileOptions
from eol_cal.capture.metadata import KEY_PATTERN, MetaValue, decode_value, encode_value, join_truth, split_truth
from eol_cal.capture.data import CANONICAL_CHANNELS, DIGITAL_CHANNELS, Capture
from eol_cal.errors import InputError
from eol_cal.infra.inputs import read_text

_META_LINE = re.compile(r"^#\s*([^:\s]+)\s*:\s?(.*)$")


def _split_cell(cell: str) -> tuple[str, str | None]:
    """``name [unit]`` -> (name, unit): the unit is what lies between the first ``[`` and a final
    ``]``. No regular expression: ``^(.*?)\\s*\\[(.*)\\]$`` backtracked quadratically on a cell of
    200 000 ``[`` (minutes)."""
    opening = cell.find("[")
    if not cell.endswith("]") or opening < 0:
        return cell, None
    return cell[:opening].strip(), cell[opening + 1:-1].strip() or None


def _cells(line: str, delimiter: str) -> list[str]:
    """A line's cells, blanks and one pair of surrounding double quotes taken off (``"Zeit [s]"``)."""
    cells = line.split() if delimiter == " " else line.split(delimiter)
    out = []
    for cell in cells:
        cell = cell.strip()
        if len(cell) >= 2 and cell[0] == cell[-1] == '"':
            cell = cell[1:-1].strip()
        out.append(cell)
    return out


def _without_trailing(line: str, delimiter: str) -> str:
    line = line.rstrip(" \r\n")
    return line[: -len(delimiter)] if line.endswith(delimiter) else line


def _parse_header(line: str, file: str, delimiter: str = ",") -> list[tuple[str, str | None]]:
    cells = []
    for position, cell in enumerate(_cells(line, delimiter), start=1):
        name, unit = _split_cell(cell)
        if not name:
            raise InputError(file, f"column {position}", "empty channel name in the header line")
        cells.append((name, unit))
    seen: set[str] = set()
    for name, _ in cells:  # a set, not list.count: a 100 000-column header must stay linear
        if name in seen:
            raise InputError(file, name, "channel named twice in the header line")
        seen.add(name)
    return cells


def _with_units_row(header: list[tuple[str, str | None]], line: str, line_no: int, file: str,
                    delimiter: str) -> list[tuple[str, str | None]]:
    """The header's names with the units of the units row (``[N*m]`` or ``N*m``; empty: none)."""
    units = _cells(line, delimiter)
    if delimiter == " " and len(units) < len(header):
        raise InputError(file, None, f"units row (line {line_no}) holds {len(units)} units for {len(header)} channels; "
                                     "with blank-separated columns every channel needs a unit (write 1 or -)")
    if len(units) != len(header):
        raise InputError(file, None, f"units row (line {line_no}) holds {len(units)} cells, the header {len(header)}")
    out = []
    for (name, stated), cell in zip(header, units, strict=True):
        unit = cell[1:-1].strip() if cell.startswith("[") and cell.endswith("]") else cell
        if stated is not None and unit and unit != stated:
            raise InputError(file, name, f"header states unit {stated!r}, the units row (line {line_no}) {unit!r}")
        out.append((name, stated or unit or None))
    return out


def _load_rows(lines: list[str], header: list[tuple[str, str | None]], first_line: int, file: str,
               delimiter: str = ",", decimal: str = ".") -> np.ndarray:
    if not any(line.strip() and not line.lstrip().startswith("#") for line in lines):
        raise InputError(file, "t", "no data rows after the header line")
    if decimal == ",":  # the delimiter is not a comma (file_options refuses that): the comma is the mark
        lines = [line.replace(",", ".") for line in lines]
    try:
        data = np.loadtxt(lines, delimiter=None if delimiter == " " else delimiter, dtype=np.float64, ndmin=2,
                          comments="#")
    except ValueError as exc:
        message = str(exc)
        field = None
        col = re.search(r"column (\d+)", message)
        if col and int(col.group(1)) - 1 < len(header) and "number of columns" not in message:
            # numpy counts columns from 1 in this message
            field = header[int(col.group(1)) - 1][0]
        row = re.search(r"at row (\d+)", message)
        where = f" (data row {int(row.group(1)) + 1}, about line {first_line + int(row.group(1))})" if row else ""
        hint = ""
        if decimal == "." and "," in message.split("at row")[0]:
            hint = "; the decimal mark must be '.' (a channel map's [file] decimal = \",\" reads a decimal comma)"
        raise InputError(file, field, f"unreadable data{where}: {message}{hint}") from None
    if data.shape[0] == 0:
        raise InputError(file, "t", "no data rows after the header line")
    if data.shape[1] != len(header):
        raise InputError(file, None, f"header names {len(header)} channels but rows hold {data.shape[1]} values")
    return data


def read_csv_columns(path: str | Path, options: FileOptions | None = None
                     ) -> tuple[dict[str, Column], dict[str, MetaValue]]:
    """Raw columns (source names, units as stated) and all ``# key: value`` properties of a CSV,
    or of delimited text as a map's ``[file]`` table describes it.

    Parameters
    ----------
    path : path
        The file.
    options : FileOptions, optional
        Delimiter, decimal mark, units row, lines to skip, encoding (default: a capture-format CSV).

    Raises
    ------
    InputError
        Unreadable file, no header, malformed or duplicate metadata, non-numeric data.
    """
    opts = options or FileOptions()
    file = str(path)
    encoding = "utf-8-sig" if codecs.lookup(opts.encoding).name == "utf-8" else opts.encoding
    lines = read_text(path, encoding=encoding).splitlines()
    if opts.skip_lines and opts.skip_lines >= len(lines):
        raise InputError(file, None, f"{len(lines)} lines, and the map skips {opts.skip_lines} before the header")
    properties: dict[str, MetaValue] = {}
    index = opts.skip_lines
    while index < len(lines) and (not lines[index].strip() or lines[index].lstrip().startswith("#")):
        match = _META_LINE.match(lines[index].strip())
        if match and KEY_PATTERN.match(match.group(1)):
            key = match.group(1)
            if key in properties:
                raise InputError(file, key, f"metadata key given twice (line {index + 1})")
            properties[key] = decode_value(key, match.group(2), file)
        index += 1
    if index == len(lines):
        raise InputError(file, None, "no header line of channel names")
    if opts.delimiter != " " and lines[index].rstrip(" \r\n").endswith(opts.delimiter):
        # an export that ends every line with the delimiter ("1;2;3;"): no empty last column
        lines = lines[:index] + [_without_trailing(line, opts.delimiter) for line in lines[index:]]
    header = _parse_header(lines[index], file, opts.delimiter)
    if opts.units_row:
        index += 1
        if index == len(lines):
            raise InputError(file, None, "no units row after the header line")
        header = _with_units_row(header, lines[index], index + 1, file, opts.delimiter)
    data = _load_rows(lines[index + 1 :], header, index + 2, file, opts.delimiter, opts.decimal)
    columns = {name: Column(data[:, k], unit) for k, (name, unit) in enumerate(header)}
    return columns, properties


def read_csv(path: str | Path, channel_map: ChannelMap | None = None) -> Capture:
    """Read a CSV capture into canonical channels and units (not validated; see ``read_capture``).

    Parameters
    ----------
    path : path
        The CSV file.
    channel_map : ChannelMap, optional
        Map for a foreign file's names and units, and its ``[file]`` table for delimited text
        other than a capture-format CSV.
    """
    file = str(path)
    columns, properties = read_csv_columns(path, channel_map.file if channel_map is not None else None)
    metadata, truth = split_truth(properties)
    columns, metadata = apply_channel_map(columns, metadata, channel_map, file)
    if "t" not in columns:
        raise InputError(file, "t", "required channel missing (a CSV carries its sample times in column t)")
    return assemble(columns, metadata, truth, file)


def _format_column(name: str, values: np.ndarray) -> list[str]:
    values = np.asarray(values)
    if name in DIGITAL_CHANNELS and np.issubdtype(values.dtype, np.integer):
        return [str(v) for v in values.tolist()]
    # repr gives the shortest text that reads back to the same float64
    return [repr(v) for v in np.asarray(values, dtype=np.float64).tolist()]


def write_csv(capture: Capture, path: str | Path) -> None:
    """Write a capture as CSV, atomically (temporary file, fsync, rename).

    Channels go in canonical order after ``t``, each analog one with its canonical unit;
    metadata and ``truth.*`` (simulator captures) as ``# key: value`` lines.
    """
    file = str(path)
    names = ["t", *(n for n in CANONICAL_CHANNELS if n in capture.channels and n != "t")]
    unknown = [n for n in capture.channels if n not in CANONICAL_CHANNELS or n == "t"]
    if unknown:
        raise InputError(file, unknown[0], "not a canonical channel name; cannot be written")
    head = [f"# {key}: {encode_value(key, value, file)}" for key, value in join_truth(capture.metadata, capture.truth).items()]
    unit = {n: CANONICAL_CHANNELS[n] for n in names}
    head.append(",".join(n if n in DIGITAL_CHANNELS or unit[n] == "1" else f"{n} [{unit[n]}]" for n in names))
    columns = [_format_column(n, capture[n]) for n in names]
    lengths = {len(c) for c in columns}
    if len(lengths) != 1:
        raise InputError(file, None, "channels differ in length from t; cannot be written")
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8", newline="\n") as fh:
        fh.write("\n".join(head))
        fh.write("\n")
        fh.writelines(",".join(row) + "\n" for row in zip(*columns, strict=True))
