"""Round trips of captures through CSV and MDF4 (levels and events), metadata types, time bases."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _capture_helpers import assert_same_capture, small_capture, with_metadata

from eol_cal.capture import read_capture, write_capture
from eol_cal.capture.columns import zoh
from eol_cal.capture.csv_io import read_csv_columns
from eol_cal.capture.mdf4_io import read_mdf4_columns
from eol_cal.errors import InputError


@pytest.fixture(scope="module")
def capture():
    return small_capture()


def test_csv_round_trip_exact(capture, tmp_path):
    path = tmp_path / "c.csv"
    write_capture(capture, path)
    back = read_capture(path)
    assert back.source == str(path)
    # CSV holds levels only: the exact edge times are not kept
    assert back.events == {}
    assert_same_capture(capture, back, events=False)


@pytest.mark.parametrize("digital", ["levels", "events"])
def test_mdf4_round_trip_exact(capture, tmp_path, digital):
    path = tmp_path / "c.mf4"
    write_capture(capture, path, digital=digital)
    back = read_capture(path)
    assert_same_capture(capture, back, events=digital == "events")
    if digital == "levels":
        assert back.events == {}


def test_mdf4_events_groups_hold_only_changes(capture, tmp_path):
    path = tmp_path / "c.mf4"
    write_capture(capture, path, digital="events")
    columns, _, unusable = read_mdf4_columns(path)
    assert unusable == {}
    for name in ("enc_a", "enc_b", "hall"):
        col = columns[name]
        assert col.events
        times, levels = capture.events[name]
        # first row: the level at the start; then exactly the recorded changes
        assert col.times[0] == capture.t[0]
        assert np.array_equal(col.times[1:], times)
        assert np.array_equal(col.values[1:], levels)
        assert np.all(col.values[1:] != col.values[:-1])
    assert not columns["torque"].events


def test_events_derived_from_levels_when_capture_has_none(capture, tmp_path):
    plain = dataclasses.replace(capture, events={})
    path = tmp_path / "c.mf4"
    write_capture(plain, path, digital="events")
    back = read_capture(path)
    assert_same_capture(plain, back, events=False)
    for name in ("enc_a", "hall"):
        times, levels = back.events[name]
        # derived change times are the sample times at which the new level first appears
        idx = np.searchsorted(capture.t, times)
        assert np.array_equal(capture.t[idx], times)
        assert np.array_equal(capture.channels[name][idx], levels)
        assert np.all(capture.channels[name][idx - 1] != levels)


def test_memory_csv_mdf4_csv_chain(capture, tmp_path):
    write_capture(capture, tmp_path / "a.csv")
    a = read_capture(tmp_path / "a.csv")
    write_capture(a, tmp_path / "b.mf4", digital="events")
    b = read_capture(tmp_path / "b.mf4")
    write_capture(b, tmp_path / "c.csv")
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "c.csv").read_bytes()


META = {
    "serial": "0001",  # a serial that looks like a number stays a string
    "poles": 6,
    "encoder_ppr": 64,
    "kt": 0.04905,
    "iq_ref": 65,  # an int given for a float key is read back as float 65.0
    "station": "EOL 3",
    "operator": ' "quoted" name ',
    "created": "2026-11-22T14:00:00+00:00",
    "comment": "line one\nline two",
    "batch": 17,
    "ratio": 0.25,
    "lot": "12345",
    "note": "1e5 rpm? no",
    "big": 1e300,
}


@pytest.mark.parametrize("suffix", [".csv", ".mf4"])
def test_metadata_types_round_trip(capture, tmp_path, suffix):
    cap = dataclasses.replace(capture, metadata=dict(META), truth={"k6": 0.00062, "seed": 3, "model": "x", "tag": "7"})
    path = tmp_path / f"m{suffix}"
    write_capture(cap, path)
    back = read_capture(path)
    expect = dict(META, iq_ref=65.0)
    assert back.metadata == expect
    assert {k: type(v) for k, v in back.metadata.items()} == {k: type(v) for k, v in expect.items()}
    assert back.truth == {"k6": 0.00062, "seed": 3, "model": "x", "tag": "7"}
    assert type(back.truth["seed"]) is int and type(back.truth["tag"]) is str
    assert not any(k.startswith("truth.") for k in back.metadata)


def test_csv_text_layout(capture, tmp_path):
    path = tmp_path / "c.csv"
    write_capture(capture, path)
    lines = path.read_text().splitlines()
    assert lines[0] == "# serial: T-0001"
    assert "# truth.k6: 0.00062" in lines
    header = next(line for line in lines if not line.startswith("#"))
    assert header == "t [s],torque [N*m],enc_a,enc_b,hall,iq_ref [A],speed [rpm]"


def test_mdf4_header_comment_common_properties(capture, tmp_path):
    from asammdf import MDF

    path = tmp_path / "c.mf4"
    write_capture(capture, path)
    with MDF(path) as mdf:
        comment = mdf.header.comment
    assert '<e name="serial">T-0001</e>' in comment
    assert '<e name="poles">6</e>' in comment
    assert '<e name="truth.k6">0.00062</e>' in comment


def test_mdf4_several_time_bases_resampled_onto_torque(tmp_path):
    """A DAQ-style file: torque at 5 kHz, iq_ref at 500 Hz, temp at 10 Hz, hall/enc as events."""
    from asammdf import MDF, Signal

    from eol_cal.capture.mdf4_io import header_comment

    ref = small_capture()
    t = ref.t
    t_slow = np.arange(0, 0.5, 1 / 500.0)
    iq_slow = 60.0 + 10.0 * t_slow  # a ramp: linear interpolation reproduces it exactly
    t_temp = np.arange(0, 0.6, 0.1)
    mdf = MDF(version="4.10")
    mdf.header.comment = header_comment({"serial": "X", "poles": 6, "encoder_ppr": 64})
    mdf.append([Signal(ref["torque"], t, name="torque", unit="N*m")])
    mdf.append([Signal(iq_slow, t_slow, name="iq_ref", unit="A")])
    mdf.append([Signal(20.0 + t_temp, t_temp, name="temp", unit="degC")])
    for name in ("enc_a", "hall"):
        times, levels = ref.events[name]
        mdf.append(
            [Signal(np.concatenate([[ref[name][0]], levels]).astype(np.uint8), np.concatenate([[0.0], times]), name=name)]
        )
    mdf.save(tmp_path / "daq.mf4", overwrite=True)
    mdf.close()
    back = read_capture(tmp_path / "daq.mf4")
    # samples after the last iq_ref sample are outside what every sampled channel covers
    keep = t <= t_slow[-1]
    assert np.array_equal(back.t, t[keep])
    assert np.allclose(back["iq_ref"], 60.0 + 10.0 * t[keep], rtol=0, atol=1e-12)
    assert np.allclose(back["temp"], 20.0 + t[keep], rtol=0, atol=1e-12)
    for name in ("enc_a", "hall"):
        assert np.array_equal(back[name], ref[name][keep])
        assert back[name].dtype == np.int8
        inside = ref.events[name][0] <= t[keep][-1]
        assert np.array_equal(back.events[name][0], ref.events[name][0][inside])


def test_zoh_holds_last_level():
    times = np.array([0.0, 1.0, 2.5])
    levels = np.array([1, 3, 2])
    assert zoh(times, levels, np.array([0.0, 0.99, 1.0, 2.4, 2.5, 9.0])).tolist() == [1, 1, 3, 3, 2, 2]


@pytest.mark.parametrize("suffix", [".csv", ".mf4"])
def test_writes_are_atomic(capture, tmp_path, monkeypatch, suffix):
    import eol_cal.infra.atomic as atomic

    path = tmp_path / f"c{suffix}"
    path.write_bytes(b"old content\n")

    def failing_fsync(fd):
        raise OSError("disk gone")

    # the data is fully written to the temporary file when fsync fails: the target must not change
    monkeypatch.setattr(atomic.os, "fsync", failing_fsync)
    with pytest.raises(InputError, match="cannot write: disk gone") as info:
        write_capture(capture, path)
    assert info.value.file == str(path)
    assert path.read_bytes() == b"old content\n"
    assert [p.name for p in tmp_path.iterdir()] == [path.name]
    monkeypatch.undo()
    write_capture(capture, path)
    assert read_capture(path).serial == "T-0001"
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def test_csv_columns_keep_units_and_comment_lines(tmp_path):
    path = tmp_path / "x.csv"
    path.write_text("\ufeff# exported by a DAQ, not metadata\n# serial: 9\nZeit [ms], Moment [N*cm]\n0.5,1\n1.5,2\n")
    columns, props = read_csv_columns(path)
    assert props == {"serial": "9"}
    assert columns["Zeit"].unit == "ms" and columns["Moment"].unit == "N*cm"
    assert columns["Zeit"].values.tolist() == [0.5, 1.5]


def test_metadata_iq_ref_instead_of_channel(tmp_path):
    cap = small_capture(iq_ref_channel=False)
    assert "iq_ref" not in cap.channels
    write_capture(cap, tmp_path / "c.csv")
    back = read_capture(tmp_path / "c.csv")
    assert back.metadata["iq_ref"] == 65.0
    assert np.all(back.iq_ref() == 65.0)
    assert_same_capture(cap, with_metadata(back), events=False)
