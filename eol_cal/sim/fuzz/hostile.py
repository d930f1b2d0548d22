"""Hostile sizes and shapes (issue 23): numbers of thousands of digits, nesting thousands deep,
cells and headers that make a parser backtrack, MDF4 header comments and record counts that a
decoder believes. Each maker returns bytes; the fault benchmark and the tests place them in
files of every kind the tool reads (see :mod:`eol_cal.sim.fuzz`)."""

from __future__ import annotations

import struct

from eol_cal.capture.mdf4_check import check_mdf4_bytes
from eol_cal.sim.fuzz.mutate import mdf4_blocks

#: hostile TOML lines, each placed at the top of an otherwise valid file of any TOML kind
TOML_LINES: dict[str, str] = {
    "5000-digit integer": "zz = " + "9" * 5000,
    "400-digit integer": "zz = " + "9" * 400,
    "integer beyond 64 bits": "zz = 9223372036854775808",
    "arrays 5000 deep": "zz = " + "[" * 5000 + "]" * 5000,
    "arrays 100 deep": "zz = " + "[" * 100 + "]" * 100,
    "inline tables 5000 deep": "zz = " + "{a=" * 5000 + "1" + "}" * 5000,
    "dotted key 5000 deep": "zz" + ".a" * 5000 + " = 1",
    "table header 300 deep": "[" + ".".join(["t"] * 300) + "]\nx = 1",
}

#: hostile JSON values, each put in place of one value of a valid document
JSON_TOKENS: dict[str, str] = {
    "NaN": "NaN", "Infinity": "-Infinity", "1e400": "1e400", "5000-digit integer": "9" * 5000,
    "400-digit integer": "9" * 400, "arrays 100000 deep": "[" * 100000 + "]" * 100000,
    "objects 1000 deep": '{"a":' * 1000 + "1" + "}" * 1000, "arrays 70 deep": "[" * 70 + "]" * 70,
}

#: hostile CSV header cells and metadata lines (each must be parsed in linear time)
CSV_HEADER_CELLS: dict[str, str] = {
    "200000 '['": "torque " + "[" * 200000,
    "200000 '[' closed": "torque [" + "[" * 200000 + "]",
    "unit of 100000 '('": "torque [" + "(" * 100000 + "]",
    "name of 200000 spaces then '['": "torque" + " " * 200000 + "[",
    "unit of 5000 '*N'": "torque [" + "*N" * 5000 + "]",
}
CSV_META_LINES: dict[str, str] = {
    "key of 200000 characters": "# " + "k" * 200000 + ": 1",
    "200000 blanks before ':'": "# serial" + " " * 200000 + ":x",
    "value of 200000 digits": "# poles: " + "9" * 200000,
}


def csv_with_header_cell(base: bytes, cell: str) -> bytes:
    """A CSV capture whose header gets ``cell`` in place of its second column's name and unit."""
    lines = base.decode().split("\n")
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    cells = lines[first].split(",")
    cells[1] = cell
    lines[first] = ",".join(cells)
    return "\n".join(lines).encode()


def csv_with_meta_line(base: bytes, line: str) -> bytes:
    """A CSV capture with ``line`` as its first metadata line."""
    return (line + "\n").encode() + base


def _blocks(data: bytes) -> dict[int, tuple[bytes, int, tuple[int, ...]]]:
    return mdf4_blocks(data)


def mdf4_with_header_comment(base: bytes, xml: str) -> bytes:
    """An MDF4 capture whose header comment is ``xml`` exactly as given (a new ##MD block at the
    end of the file, linked from the header): asammdf would rebuild a comment it writes itself."""
    blocks = _blocks(base)
    data = bytearray(base)
    data += b"\0" * (-len(data) % 8)
    at = len(data)
    body = xml.encode("utf-8") + b"\0"
    body += b"\0" * (-len(body) % 8)
    data += struct.pack("<4sIQQ", b"##MD", 0, 24 + len(body), 0) + body
    header_links = blocks[64][2]
    struct.pack_into("<Q", data, 64 + 24 + 8 * 5, at)
    assert len(header_links) == 6
    return bytes(data)


def header_comment_with(base: bytes, extra: str, where: str = "e") -> str:
    """The base file's header comment XML with ``extra`` added inside ``common_properties``
    (``where="e"``) or after it (``where="root"``)."""
    xml = check_mdf4_bytes(base).header_comment
    if where == "root":
        return xml.replace("</HDcomment>", extra + "</HDcomment>")
    return xml.replace("</common_properties>", extra + "</common_properties>")


#: hostile additions to an MDF4 header comment: (name, XML, where)
MDF4_COMMENTS: tuple[tuple[str, str, str], ...] = (
    ("key given twice", '<e name="poles">8</e>', "e"),
    ("key given twice with blanks", '<e name=" poles ">8</e>', "e"),
    ("key given twice in the ASAM namespace", '<e xmlns="http://www.asam.net/mdf/v4" name="poles">8</e>', "e"),
    ("second common_properties", '<common_properties><e name="poles">8</e></common_properties>', "root"),
    ("element without a name", "<e>8</e>", "e"),
    ("tree without a name", '<tree><e name="x">1</e></tree>', "e"),
    ("100000 nested elements", "<x>" * 100000 + "</x>" * 100000, "root"),
)


def mdf4_with_cg_field(base: bytes, field: str, value: int) -> bytes:
    """An MDF4 capture whose first channel group's ``field`` (``cycles``, ``flags``,
    ``record_bytes``, ``invalid_bytes``) is ``value``."""
    blocks = _blocks(base)
    cg = next(o for o in sorted(blocks) if blocks[o][0] == b"##CG")
    at = cg + 24 + 8 * len(blocks[cg][2])
    fmt, offset = {"cycles": ("<Q", 8), "flags": ("<H", 16), "record_bytes": ("<I", 24),
                   "invalid_bytes": ("<I", 28)}[field]
    data = bytearray(base)
    struct.pack_into(fmt, data, at + offset, value)
    return bytes(data)


#: channel-group fields and the values the benchmark sets them to
MDF4_CG_FIELDS: dict[str, tuple[int, ...]] = {
    "cycles": (0, 1, 2**31, 2**62), "flags": (1, 3, 0xFFFF), "record_bytes": (0, 2**31),
    "invalid_bytes": (1, 2**31),
}
