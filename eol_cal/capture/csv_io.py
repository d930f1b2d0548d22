"""CSV captures (capture format v1): ``# key: value`` metadata lines, a header, numeric rows.

::

    # serial: M-0001
    # poles: 6
    # truth.k6: 0.00062
    t [s],torque [N*m],enc_a,enc_b,hall,iq_ref [A]
    0.0,3.1875,1,0,5,65.0

UTF-8 (a byte-order mark is tolerated), comma-separated, ``.`` as decimal mark. ``#`` lines
that do not read ``key: value`` are comments. Floats are written in their shortest exact form
(Python ``repr``), so a write-read round trip returns the same float64 values. CSV cannot hold
change events: digital channels are written as the levels at the sample times.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from eol_cal.atomic import atomic_path
from eol_cal.capture.channel_map import ChannelMap, apply_channel_map
from eol_cal.capture.columns import Column, assemble
from eol_cal.capture.metadata import KEY_PATTERN, MetaValue, decode_value, encode_value, join_truth, split_truth
from eol_cal.capture.model import CANONICAL_CHANNELS, DIGITAL_CHANNELS, Capture
from eol_cal.errors import InputError
from eol_cal.inputs import read_text

_META_LINE = re.compile(r"^#\s*([^:\s]+)\s*:\s?(.*)$")


def _split_cell(cell: str) -> tuple[str, str | None]:
    """``name [unit]`` -> (name, unit): the unit is what lies between the first ``[`` and a final
    ``]``. No regular expression: ``^(.*?)\\s*\\[(.*)\\]$`` backtracked quadratically on a cell of
    200 000 ``[`` (minutes)."""
    opening = cell.find("[")
    if not cell.endswith("]") or opening < 0:
        return cell, None
    return cell[:opening].strip(), cell[opening + 1:-1].strip() or None


def _parse_header(line: str, file: str) -> list[tuple[str, str | None]]:
    cells = []
    for position, cell in enumerate(line.split(","), start=1):
        name, unit = _split_cell(cell.strip())
        if not name:
            raise InputError(file, f"column {position}", "empty channel name in the header line")
        cells.append((name, unit))
    seen: set[str] = set()
    for name, _ in cells:  # a set, not list.count: a 100 000-column header must stay linear
        if name in seen:
            raise InputError(file, name, "channel named twice in the header line")
        seen.add(name)
    return cells


def _load_rows(lines: list[str], header: list[tuple[str, str | None]], first_line: int, file: str) -> np.ndarray:
    if not any(line.strip() and not line.lstrip().startswith("#") for line in lines):
        raise InputError(file, "t", "no data rows after the header line")
    try:
        data = np.loadtxt(lines, delimiter=",", dtype=np.float64, ndmin=2, comments="#")
    except ValueError as exc:
        message = str(exc)
        field = None
        col = re.search(r"column (\d+)", message)
        if col and int(col.group(1)) - 1 < len(header) and "number of columns" not in message:
            # numpy counts columns from 1 in this message
            field = header[int(col.group(1)) - 1][0]
        row = re.search(r"at row (\d+)", message)
        where = f" (data row {int(row.group(1)) + 1}, about line {first_line + int(row.group(1))})" if row else ""
        hint = "; the decimal mark must be '.'" if "," in message.split("at row")[0] else ""
        raise InputError(file, field, f"unreadable data{where}: {message}{hint}") from None
    if data.shape[0] == 0:
        raise InputError(file, "t", "no data rows after the header line")
    if data.shape[1] != len(header):
        raise InputError(file, None, f"header names {len(header)} channels but rows hold {data.shape[1]} values")
    return data


def read_csv_columns(path: str | Path) -> tuple[dict[str, Column], dict[str, MetaValue]]:
    """Raw columns (source names, units as stated) and all ``# key: value`` properties of a CSV.

    Raises
    ------
    InputError
        Unreadable file, no header, malformed or duplicate metadata, non-numeric data.
    """
    file = str(path)
    text = read_text(path, encoding="utf-8-sig")
    lines = text.splitlines()
    properties: dict[str, MetaValue] = {}
    index = 0
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
    header = _parse_header(lines[index], file)
    data = _load_rows(lines[index + 1 :], header, index + 2, file)
    columns = {name: Column(data[:, k], unit) for k, (name, unit) in enumerate(header)}
    return columns, properties


def read_csv(path: str | Path, channel_map: ChannelMap | None = None) -> Capture:
    """Read a CSV capture into canonical channels and units (not validated; see ``read_capture``).

    Parameters
    ----------
    path : path
        The CSV file.
    channel_map : ChannelMap, optional
        Map for a foreign file's names and units.
    """
    file = str(path)
    columns, properties = read_csv_columns(path)
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
