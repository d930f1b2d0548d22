"""Every bad input of docs/capture-format.md is refused, naming file, channel and reason (exit code 2)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _capture_helpers import small_capture, with_channel, with_metadata
from click.testing import CliRunner

from cli.main import cli
from eol_cal.capture import read_capture, validate, write_capture
from eol_cal.errors import InputError

BASE = small_capture()
N = len(BASE.t)


def _nan_at(name, index, value=np.nan):
    values = BASE[name].astype(np.float64).copy()
    values[index] = value
    return with_channel(BASE, name, values)


def _digital(name, index, value):
    values = BASE[name].copy()
    values[index] = value
    return with_channel(BASE, name, values)


def _time_back_step():
    t = BASE.t.copy()
    t[500] = t[498]
    return dataclasses.replace(BASE, t=t)


def _hall_glitch(state, start, count):
    hall = BASE["hall"].copy()
    hall[start : start + count] = state
    return with_channel(BASE, "hall", hall)


# (id, capture, channel named, words the reason must contain)
CASES = [
    ("missing torque", with_channel(BASE, "torque", None), "torque", "required channel missing"),
    ("missing enc_a", with_channel(BASE, "enc_a", None), "enc_a", "required channel missing"),
    ("missing hall", with_channel(BASE, "hall", None), "hall", "required channel missing"),
    ("missing iq_ref", with_channel(BASE, "iq_ref", None), "iq_ref", "required channel missing"),
    ("missing serial", with_metadata(BASE, serial=None), "serial", "required metadata missing"),
    ("missing poles", with_metadata(BASE, poles=None), "poles", "required metadata missing"),
    ("missing encoder_ppr", with_metadata(BASE, encoder_ppr=None), "encoder_ppr", "required metadata missing"),
    ("odd poles", with_metadata(BASE, poles=5), "poles", "positive even integer"),
    ("time backwards", _time_back_step(), "t", "t[500] = 0.0996 s after t[499] = 0.0998 s"),
    ("NaN torque", _nan_at("torque", 1234), "torque", "NaN at t = 0.2468 s (sample 1234); 1 non-finite"),
    ("inf iq_ref", _nan_at("iq_ref", 17, np.inf), "iq_ref", "infinite value at t = 0.0034 s (sample 17)"),
    ("hall 0", _hall_glitch(0, 800, 5), "hall",
     "hall state 0 (a sensor fault; valid states are 1..6) at t = 0.16 s (sample 800); 5 faulty samples"),
    ("hall 7", _hall_glitch(7, 1500, 40), "hall",
     "hall state 7 (a sensor fault; valid states are 1..6) at t = 0.3 s (sample 1500); 40 faulty samples"),
    ("enc_a stuck", with_channel(BASE, "enc_a", np.zeros(N, np.int8)), "enc_a", "encoder never toggles: stuck at 0"),
    ("enc_b stuck", with_channel(BASE, "enc_b", np.ones(N, np.int8)), "enc_b", "encoder never toggles: stuck at 1"),
    ("too short", small_capture(seconds=0.2), "hall", "too short to hold a full electrical revolution: 3 hall state changes"),
    ("enc_a out of range", _digital("enc_a", 100, 2), "enc_a", "value 2 at t = 0.02 s (sample 100) outside 0..1"),
    ("hall out of range", _digital("hall", 101, 9), "hall", "value 9 at t = 0.0202 s (sample 101) outside 0..7"),
    ("enc_b not integral", _nan_at("enc_b", 7, 0.5), "enc_b", "value 0.5 at t = 0.0014 s (sample 7) outside 0..1"),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_validate_refuses_in_memory(case):
    _, capture, channel, reason = case
    with pytest.raises(InputError) as info:
        validate(capture)
    assert info.value.field == channel
    assert reason in info.value.reason
    assert info.value.file == "<synthetic>"


@pytest.mark.parametrize("suffix", [".csv", ".mf4"])
@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_reader_refuses_bad_file(case, suffix, tmp_path):
    _, capture, channel, reason = case
    path = tmp_path / f"bad{suffix}"
    write_capture(capture, path)
    with pytest.raises(InputError) as info:
        read_capture(path)
    message = str(info.value)
    assert str(path) in message and repr(channel) in message and reason in message
    assert info.value.exit_code == 2


@pytest.mark.parametrize("case", CASES[::3], ids=[c[0] for c in CASES[::3]])
def test_cli_exit_code_2(case, tmp_path):
    _, capture, channel, reason = case
    path = tmp_path / "bad.csv"
    write_capture(capture, path)
    for args in (["capture", "info", str(path)], ["capture", "convert", str(path), str(tmp_path / "out.mf4")]):
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 2, result.output
        assert str(path) in result.stderr and repr(channel) in result.stderr and reason in result.stderr
    assert not (tmp_path / "out.mf4").exists()


def test_truth_key_leaking_into_metadata_is_refused():
    leaked = with_metadata(BASE, **{"truth.k6": 0.1})
    with pytest.raises(InputError, match="simulator truth key found in metadata") as info:
        validate(leaked)
    assert info.value.field == "truth.k6"


def _csv(tmp_path, text, name="x.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


GOOD_HEAD = "# serial: A\n# poles: 6\n# encoder_ppr: 64\n"


@pytest.mark.parametrize(
    "text, field, reason",
    [
        (GOOD_HEAD + "torque,enc_a,hall,iq_ref\n1,0,1,2\n1,1,5,2\n", "t", "required channel missing"),
        (GOOD_HEAD + "t,torque [flurbs],enc_a,hall,iq_ref\n0,1,0,1,2\n", "torque", "unknown unit 'flurbs'"),
        (GOOD_HEAD + "t,torque [A],enc_a,hall,iq_ref\n0,1,0,1,2\n", "torque", "unit 'A' cannot be converted to 'N*m'"),
        (GOOD_HEAD + "t,torque,enc_a [V],hall,iq_ref\n0,1,0,1,2\n", "enc_a", "given for a digital channel"),
        (GOOD_HEAD + "t,torque,enc_a,hall,iq_ref,vbat\n0,1,0,1,2,12\n", "vbat", "unknown channel name"),
        (GOOD_HEAD + "t,torque,enc_a,hall,iq_ref\n0,1,0,1,2\n0.1,x1,0,1,2\n", "torque", "unreadable data (data row 2"),
        (GOOD_HEAD + "t,torque,torque,hall,iq_ref\n0,1,0,1,2\n", "torque", "channel named twice"),
        (GOOD_HEAD + "t,torque,enc_a,hall,iq_ref\n", "t", "no data rows"),
        (GOOD_HEAD, None, "no header line"),
        ("# poles: six\nt\n0\n", "poles", "must be an integer"),
        ("# serial: a\n# serial: b\nt\n0\n", "serial", "metadata key given twice"),
    ],
    ids=["no t", "unknown unit", "wrong dimension", "unit on digital", "unknown column", "not a number",
         "duplicate column", "no rows", "no header", "poles not int", "duplicate key"],
)
def test_malformed_csv_refused(tmp_path, text, field, reason):
    path = _csv(tmp_path, text)
    with pytest.raises(InputError) as info:
        read_capture(path)
    assert info.value.file == str(path)
    assert info.value.field == field
    assert reason in info.value.reason


def test_decimal_comma_refused_with_hint(tmp_path):
    path = _csv(tmp_path, GOOD_HEAD + "t;torque\n0,0;1,5\n")
    with pytest.raises(InputError, match="unreadable data") as info:
        read_capture(path)
    assert info.value.file == str(path)


def test_unknown_suffix_and_missing_file(tmp_path):
    with pytest.raises(InputError, match="unknown capture file type '.txt'"):
        read_capture(tmp_path / "x.txt")
    with pytest.raises(InputError, match="unknown capture file type"):
        write_capture(BASE, tmp_path / "x.parquet")
    for name in ("none.csv", "none.mf4"):
        with pytest.raises(InputError, match="file not found") as info:
            read_capture(tmp_path / name)
        assert info.value.file == str(tmp_path / name)


def test_garbage_mdf4_refused(tmp_path):
    path = tmp_path / "junk.mf4"
    path.write_bytes(b"this is not an MDF file" * 10)
    with pytest.raises(InputError, match="not a readable MDF file") as info:
        read_capture(path)
    assert info.value.file == str(path)
    result = CliRunner().invoke(cli, ["capture", "info", str(path)])
    assert result.exit_code == 2 and "junk.mf4" in result.stderr


def test_mdf4_ambiguous_channel_refused(tmp_path):
    from asammdf import MDF, Signal

    from eol_cal.capture.mdf4_io import header_comment

    t = BASE.t
    mdf = MDF(version="4.10")
    mdf.header.comment = header_comment(BASE.metadata)
    mdf.append([Signal(BASE[n].astype(np.float64), t, name=n) for n in ("torque", "enc_a", "hall", "iq_ref")])
    mdf.append([Signal(BASE["torque"][::2], t[::2], name="torque")])
    mdf.save(tmp_path / "two.mf4", overwrite=True)
    mdf.close()
    with pytest.raises(InputError, match="more than one channel group") as info:
        read_capture(tmp_path / "two.mf4")
    assert info.value.field == "torque"
