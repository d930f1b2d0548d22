"""The direct MDF4 decoder (eol_cal.capture.mdf4_decode) gives asammdf's columns, or declines.

Every file here is decoded both ways, from the same checked bytes: where the direct decoder takes
a file, names, units, samples (values and dtypes), time stamps, the events flag, the header
properties and the unusable channels are those of the asammdf path; where it declines, the read
still works (asammdf decodes it). Hostile mutations of a valid file, too: a mutation the direct
decoder takes must be one asammdf reads the same.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from eol_cal.capture.io import read_capture, write_capture
from eol_cal.capture.mdf4_check import checked_mdf4
from eol_cal.capture.mdf4_decode import decode_checked
from eol_cal.capture.mdf4_io import _columns, _decode, _quiet_asammdf, header_properties, header_xml, parse_header_comment
from eol_cal.capture.synthetic import synthetic_capture
from eol_cal.errors import InputError
from eol_cal.sim.fuzz.mutate import mdf4_blocks

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"


def _direct(path: Path):
    with checked_mdf4(path) as (data, layout):
        header = header_xml(layout.header_comment, str(path))
        groups = decode_checked(data, layout, header)
    if groups is None:
        return None
    return _columns(groups, header_properties(header, str(path)))


def _asammdf(path: Path):
    """asammdf's columns; the properties from the file's own comment, as read_capture takes them."""
    with checked_mdf4(path) as (_data, layout):
        comment = layout.header_comment
    with _quiet_asammdf(str(path)) as decode:
        columns, _none, bad = decode(_decode, path, str(path))
    return columns, parse_header_comment(comment, str(path)), bad


def _assert_same(direct, slow) -> None:
    (cols, props, bad), (cols2, props2, bad2) = direct, slow
    assert props == props2 and bad == bad2
    assert list(cols) == list(cols2)
    for name, c in cols.items():
        d = cols2[name]
        assert (c.unit, c.events) == (d.unit, d.events), name
        assert c.values.dtype == d.values.dtype and np.array_equal(c.values, d.values, equal_nan=True), name
        assert np.array_equal(c.times, d.times, equal_nan=True), name


@pytest.mark.parametrize("digital", ["levels", "events"])
@pytest.mark.parametrize("compression", [0, 1, 2])
def test_own_files_decode_directly_as_asammdf_decodes_them(tmp_path: Path, digital: str, compression: int):
    c = synthetic_capture(rpm=-90.0, i_qo=30.0, seconds=0.3, seed=4, serial="D-1")
    path = tmp_path / "c.mf4"
    write_capture(c, path, digital=digital, compression=compression)
    direct = _direct(path)
    assert direct is not None  # eol-cal's own layout is plain, in every writer option
    _assert_same(direct, _asammdf(path))
    got = read_capture(path)
    assert got.metadata["serial"] == "D-1" and np.array_equal(got["torque"], c["torque"])


def test_the_fixture_decodes_directly():
    path = FIXTURES / "paper_60rpm.mf4"
    _assert_same(_direct(path), _asammdf(path))


def test_a_conversion_is_left_to_asammdf(tmp_path: Path):
    """A channel with a conversion rule (here: raw counts x 0.01 N*m) is not plain: asammdf
    decodes the file, conversion applied."""
    from asammdf import MDF, Signal

    from eol_cal.capture.mdf4_io import header_comment

    t = np.arange(2000) / 10000.0
    c = synthetic_capture(rpm=120.0, seconds=0.2, fs=10000.0, seed=2, serial="D-2")
    mdf = MDF(version="4.10")
    mdf.header.comment = header_comment(dict(c.metadata))
    counts = np.round(np.asarray(c["torque"]) * 100).astype(np.int32)
    signals = [Signal(counts, t, name="torque", unit="N*m", conversion={"a": 0.01, "b": 0.0})]
    signals += [Signal(np.asarray(c[n]).astype(np.uint8), t, name=n) for n in ("enc_a", "enc_b", "hall")]
    mdf.append(signals)
    path = tmp_path / "conv.mf4"
    mdf.save(path, overwrite=True)
    mdf.close()
    assert _direct(path) is None
    got = read_capture(path, validate=False)
    assert np.allclose(got["torque"], counts * 0.01)


def _with(data: bytes, at: int, fmt: str, value) -> bytes:
    buf = bytearray(data)
    struct.pack_into(fmt, buf, at, value)
    return bytes(buf)


def _base(tmp_path: Path) -> bytes:
    path = tmp_path / "base.mf4"
    write_capture(synthetic_capture(rpm=60.0, seconds=0.5, fs=5000.0, serial="F-0001", seed=7), path, compression=0)
    return path.read_bytes()


def _edits(base: bytes):
    """Single-field edits of a valid file: every channel's type, data type, bit offset, bit count,
    flags; each group's cycle count, record size, flags; texts; the header comment."""
    blocks = mdf4_blocks(base)
    for o, (kind, length, links) in sorted(blocks.items()):
        at = o + 24 + 8 * len(links)
        if kind == b"##CN":
            for field, fmt, values in ((0, "<B", (1, 3, 4, 5)), (2, "<B", (1, 2, 3, 5, 6, 8)), (3, "<B", (1, 3)),
                                       (8, "<I", (1, 7, 12, 16, 24, 32)), (12, "<I", (1, 2, 0x400, 0x1000))):
                for v in values:
                    yield f"CN at {o} field {field} = {v}", _with(base, at + field, fmt, v)
            for k, v in ((4, o), (1, 0)):  # a conversion link to a block that is not one; a composition
                yield f"CN at {o} link {k} = {v}", _with(base, o + 24 + 8 * k, "<Q", v)
        elif kind == b"##CG":
            for field, fmt, values in ((8, "<Q", (0, 1, 100)), (16, "<H", (1, 2)), (24, "<I", (1, 8, 9)),
                                       (28, "<I", (1,))):
                for v in values:
                    yield f"CG at {o} field {field} = {v}", _with(base, at + field, fmt, v)
        elif kind == b"##DG":
            yield f"DG at {o} record id 1", _with(base, at, "<B", 1)
        elif kind in (b"##TX", b"##MD"):
            text = base[o + 24:o + length]
            for old, new in ((b"serial", b"serial"), (b'">', b'">\n '), (b'">', b'"> '), (b"<e ", b"<x "),
                             (b"t", b"\xff"), (b"e", b"\x00")):
                if old in text and (old, new) != (b"serial", b"serial"):
                    yield f"{kind.decode()} at {o}: {old!r} -> {new!r}", base.replace(text, text.replace(old, new, 1))


def _taken(path: Path, data: bytes, how: str) -> bool | None:
    """Decode ``data`` both ways: None when the structure check refuses it (as before), False when
    the direct decoder leaves it to asammdf, True when it takes it (and then asammdf must read the
    same columns)."""
    path.write_bytes(data)
    try:
        direct = _direct(path)
    except InputError:
        return None
    if direct is None:
        return False
    try:
        slow = _asammdf(path)
    except Exception as exc:  # noqa: BLE001 - whatever asammdf raises, the file read as an error before
        pytest.fail(f"{how}: decoded directly, but asammdf refuses it: {exc!r}")
    try:
        _assert_same(direct, slow)
    except AssertionError as exc:
        raise AssertionError(how) from exc
    return True


def test_edited_files_decode_as_asammdf_decodes_them_or_are_left_to_it(tmp_path: Path):
    outcomes = [_taken(tmp_path / "edit.mf4", data, how) for how, data in _edits(_base(tmp_path))]
    assert outcomes.count(True) > 10 and outcomes.count(False) > 10, outcomes


def test_hostile_mutations_decode_as_asammdf_decodes_them_or_are_left_to_it(tmp_path: Path):
    from eol_cal.sim.fuzz.mutate import cases

    outcomes = [_taken(tmp_path / "m.mf4", case.data, case.how)
                for case in cases(11, 150, {"mdf4": _base(tmp_path)}, kinds=("mdf4",))]
    assert outcomes.count(True) > 5, outcomes
