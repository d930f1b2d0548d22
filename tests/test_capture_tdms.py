"""NI TDMS captures: files written by npTDMS read through channel maps, and every bad one refused."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from _capture_helpers import small_capture
from click.testing import CliRunner
from nptdms import ChannelObject, GroupObject, RootObject, TdmsWriter

from cli.main import cli
from eol_cal.capture import read_capture
from eol_cal.errors import InputError

GROUP = "Messdaten"
MAP = """[channels]
torque = { name = "Messdaten/Drehmoment" }
enc_a  = { name = "DI0" }
enc_b  = { name = "DI1" }
hall   = { bits = ["HU", "HV", "HW"] }
iq_ref = { name = "Iq_soll", unit = "A" }
"""


def _write(path, channels, root=None, segments=1):
    """A TDMS file as a DAQ writes it: a root with properties, then ``segments`` segments of the channels."""
    objects = [RootObject(properties=root or {}), *(GroupObject(g) for g in dict.fromkeys(c.group for c in channels))]
    with TdmsWriter(str(path)) as writer:
        writer.write_segment(objects + list(channels))
        for _ in range(segments - 1):
            writer.write_segment(list(channels))
    return path


def _daq_channels(ref, group=GROUP, props=None, torque_unit="N*cm", **extra):
    """The small reference capture as a DAQ's waveforms: torque in N*cm, hall as three bit lines."""
    dt = float(ref.t[1] - ref.t[0])
    wf = {"wf_increment": dt, "wf_start_offset": 0.0, **(props or {})}
    chans = [
        ChannelObject(group, "Drehmoment", ref["torque"] * 100.0, properties={**wf, "unit_string": torque_unit}),
        ChannelObject(group, "DI0", ref["enc_a"].astype(np.uint8), properties=wf),
        ChannelObject(group, "DI1", ref["enc_b"].astype(np.uint8), properties=wf),
        *(ChannelObject(group, line, ((ref["hall"] >> bit) & 1).astype(np.uint8), properties=wf)
          for bit, line in enumerate(("HU", "HV", "HW"))),
        ChannelObject(group, "Iq_soll", ref["iq_ref"], properties={**wf, "unit_string": "A"}),
    ]
    return chans + [ChannelObject(group, name, values, properties=p) for name, (values, p) in extra.items()]


def _root(ref):
    return {"serial": ref.metadata["serial"], "poles": np.int32(6), "encoder_ppr": np.int32(64),
            "kt": ref.metadata["kt"], "ecu_before.bank": "none", "ecu_after.bank": "none",
            "NI_ExpTitle": "EOL bench 2", "not a key": "dropped"}


@pytest.fixture()
def ref():
    return small_capture()


@pytest.fixture()
def daq(tmp_path, ref):
    (tmp_path / "m.toml").write_text(MAP)
    return _write(tmp_path / "c.tdms", _daq_channels(ref), _root(ref)), tmp_path / "m.toml"


def _same_as(c, ref):
    assert np.allclose(c.t, ref.t, rtol=0, atol=1e-12)
    assert np.allclose(c["torque"], ref["torque"], rtol=1e-14, atol=0)
    assert np.allclose(c["iq_ref"], ref["iq_ref"], rtol=0, atol=0)
    for name in ("enc_a", "enc_b", "hall"):
        assert np.array_equal(c[name], ref[name]), name


def test_waveforms_through_a_map(daq, ref):
    c = read_capture(*daq)
    _same_as(c, ref)
    assert list(c.channels) == ["torque", "enc_a", "enc_b", "hall", "iq_ref"]
    # root properties are the metadata, typed as the capture format says; a name that is no key is left out
    assert c.metadata["poles"] == 6 and type(c.metadata["poles"]) is int
    assert c.metadata["serial"] == ref.metadata["serial"] and c.metadata["NI_ExpTitle"] == "EOL bench 2"
    assert "not a key" not in c.metadata


def test_canonical_names_need_no_map_and_segments_concatenate(tmp_path, ref):
    dt = float(ref.t[1] - ref.t[0])
    half = len(ref.t) // 2
    wf = {"wf_increment": dt}
    path = tmp_path / "c.tdms"
    with TdmsWriter(str(path)) as w:  # two segments, as a DAQ writes while it records
        for part, objects in ((slice(0, half), [RootObject(_root(ref)), GroupObject("g")]), (slice(half, None), [])):
            w.write_segment(objects + [
                ChannelObject("g", name, ref[name][part], properties={**wf, "unit_string": unit})
                for name, unit in (("torque", "N*m"), ("enc_a", ""), ("enc_b", ""), ("hall", ""), ("iq_ref", "A"))])
    _same_as(read_capture(path), ref)


def test_a_time_channel_gives_the_rows(tmp_path, ref):
    """No waveform properties: the map's t channel (in ms) carries the times of every row."""
    chans = [ChannelObject("g", "Zeit", ref.t * 1000.0, properties={"unit_string": "ms"}),
             *(ChannelObject("g", c.channel, c.data, properties={"unit_string": c.properties.get("unit_string", "")})
               for c in _daq_channels(ref, group="g"))]
    path = _write(tmp_path / "c.tdms", chans, _root(ref))
    (tmp_path / "m.toml").write_text(MAP.replace("Messdaten/", "g/") + 't = { name = "Zeit" }\n')
    _same_as(read_capture(path, tmp_path / "m.toml"), ref)
    # a time channel the file lacks is the map's fault (not "no time base" of the waveforms)
    (tmp_path / "n.toml").write_text(MAP.replace("Messdaten/", "g/") + 't = { name = "Uhrzeit" }\n')
    with pytest.raises(InputError, match=r"source channel 'Uhrzeit' not found in .*c\.tdms") as info:
        read_capture(path, tmp_path / "n.toml")
    assert info.value.file == str(tmp_path / "n.toml") and info.value.field == "t"
    # a channel of another length than the time channel
    chans[3] = ChannelObject("g", "DI1", ref["enc_b"][:-5].astype(np.uint8))
    _write(path, chans, _root(ref))
    with pytest.raises(InputError, match=r"\b\d+ values, but the time channel 'Zeit' has") as info:
        read_capture(path, tmp_path / "m.toml")
    assert info.value.field == "DI1" and info.value.file == str(path)


def test_sample_rate_from_the_map(tmp_path, ref):
    chans = [ChannelObject(c.group, c.channel, c.data, properties={"unit_string": c.properties["unit_string"]}
                           if "unit_string" in c.properties else {}) for c in _daq_channels(ref)]
    path = _write(tmp_path / "c.tdms", chans, _root(ref))
    (tmp_path / "m.toml").write_text(MAP)
    with pytest.raises(InputError, match="no time base") as info:
        read_capture(path, tmp_path / "m.toml")
    assert info.value.field == "Messdaten/Drehmoment"
    (tmp_path / "m.toml").write_text(MAP + "[file]\nsample_rate = 5000.0\n")
    _same_as(read_capture(path, tmp_path / "m.toml"), ref)
    # a map's rate that contradicts a channel's wf_increment
    _write(path, _daq_channels(ref), _root(ref))
    (tmp_path / "m.toml").write_text(MAP + "[file]\nsample_rate = 10000.0\n")
    with pytest.raises(InputError, match=r"wf_increment 0.0002 s is not 1/sample_rate of map .*m.toml"):
        read_capture(path, tmp_path / "m.toml")


def test_two_groups_on_one_clock_by_their_start_times(tmp_path, ref):
    """DAQmx writes an analog and a digital task as two groups; wf_start_time puts them on one clock."""
    t0 = np.datetime64("2026-11-28T12:00:00.000000")
    late = 40  # the digital task started 40 samples (8 ms) after the analog one
    dt = float(ref.t[1] - ref.t[0])
    analog = [c for c in _daq_channels(ref, group="AI", props={"wf_start_time": t0}) if c.channel in ("Drehmoment", "Iq_soll")]
    digital = [ChannelObject("DI", c.channel, c.data[late:], properties={"wf_increment": dt, "wf_start_time":
                                                                          t0 + np.timedelta64(8000, "us")})
               for c in _daq_channels(ref) if c.channel.startswith(("DI", "H"))]
    path = _write(tmp_path / "c.tdms", analog + digital, _root(ref))
    (tmp_path / "m.toml").write_text(MAP.replace("Messdaten/", "AI/"))
    c = read_capture(path, tmp_path / "m.toml")
    # the capture starts where both tasks ran; every digital level sits at its analog sample
    assert c.t[0] == pytest.approx(ref.t[late], abs=1e-12) and len(c.t) == len(ref.t) - late
    for name in ("enc_a", "enc_b", "hall"):
        assert np.array_equal(c[name], ref[name][late:]), name
    assert np.allclose(c["torque"], ref["torque"][late:], rtol=1e-14)


def test_group_and_channel_names(tmp_path, ref):
    extra = _daq_channels(ref, group="Zweite")[:1]  # a second "Drehmoment" in another group
    path = _write(tmp_path / "c.tdms", _daq_channels(ref) + extra, _root(ref))
    (tmp_path / "m.toml").write_text(MAP)  # names it as Messdaten/Drehmoment: fine
    _same_as(read_capture(path, tmp_path / "m.toml"), ref)
    (tmp_path / "m.toml").write_text(MAP.replace("Messdaten/Drehmoment", "Drehmoment"))
    with pytest.raises(InputError, match=r"channel 'Drehmoment' is in groups 'Messdaten', 'Zweite' of .*; name it as "
                                         r"'Messdaten/Drehmoment'") as info:
        read_capture(path, tmp_path / "m.toml")
    assert info.value.file == str(tmp_path / "m.toml") and info.value.field == "torque"


def test_without_a_map_a_foreign_name_is_refused(daq):
    with pytest.raises(InputError, match="a foreign file needs a channel map") as info:
        read_capture(daq[0])
    assert info.value.field == "Messdaten/Drehmoment"


@pytest.mark.parametrize(
    ("change", "field", "message"),
    [
        ("missing", "torque", r"source channel 'Messdaten/Drehmoment' not found in .*c\.tdms"),
        ("text", "Messdaten/Drehmoment", "not a numeric channel"),
        ("unit", "torque (source channel 'Messdaten/Drehmoment')", r"file states unit 'N\*cm' but map .* says 'N\*m'"),
        ("bad_unit", "torque (source channel 'Messdaten/Drehmoment')", "cannot be converted to 'N\\*m'"),
        ("increment", "DI0", "wf_increment -0.0002 is not a positive number of seconds"),
        ("tiny_increment", "DI0", "wf_increment 1e-300 s is a rate above 1e[+]09 Hz"),
        ("hall_bit", "hall (bit line 'HV')", "a bit line takes 0 or 1"),
    ],
)
def test_bad_channels_refused_naming_file_field_reason(tmp_path, ref, change, field, message):
    chans = _daq_channels(ref)
    mapping = MAP
    if change == "missing":
        chans = chans[1:]
    elif change == "text":
        chans[0] = ChannelObject(GROUP, "Drehmoment", np.array(["3.1"] * len(ref.t)))
    elif change == "unit":
        mapping = MAP.replace('"Messdaten/Drehmoment"', '"Messdaten/Drehmoment", unit = "N*m"')
    elif change == "bad_unit":
        chans = _daq_channels(ref, torque_unit="V")
    elif change == "increment":
        chans[1] = ChannelObject(GROUP, "DI0", chans[1].data, properties={"wf_increment": -0.0002})
    elif change == "tiny_increment":
        chans[1] = ChannelObject(GROUP, "DI0", chans[1].data, properties={"wf_increment": 1e-300})
    elif change == "hall_bit":
        chans[4] = ChannelObject(GROUP, "HV", chans[4].data * 2, properties=chans[4].properties)
    path = _write(tmp_path / "c.tdms", chans, _root(ref))
    (tmp_path / "m.toml").write_text(mapping)
    with pytest.raises(InputError, match=message) as info:
        read_capture(path, tmp_path / "m.toml")
    assert info.value.field == field


def test_an_unused_text_channel_is_not_read(tmp_path, ref):
    chans = _daq_channels(ref, Kommentar=(np.array(["a", "b"]), {}))
    _same_as(read_capture(_write(tmp_path / "c.tdms", chans, _root(ref)), _map(tmp_path)), ref)


def _map(tmp_path, text=MAP):
    (tmp_path / "m.toml").write_text(text)
    return tmp_path / "m.toml"


def _declared_values_at(data: bytes, path: bytes) -> int:
    """Offset of the number of values in the raw data index that follows object ``path``."""
    at = data.index(path) + len(path)
    assert struct.unpack_from("<I", data, at)[0] == 20  # a plain raw data index: type, dimension, count
    return at + 12


def test_damaged_files_refused(tmp_path, ref, daq):
    good = daq[0].read_bytes()
    bad = tmp_path / "bad.tdms"
    cases = {
        "truncated data": good[:-100],
        "truncated metadata": good[:200],
        "truncated lead-in": good[:20],
        "not TDMS": b"Zeit;Moment\n0;1\n",
    }
    at = _declared_values_at(good, b"/'Messdaten'/'Drehmoment'")
    huge = bytearray(good)
    struct.pack_into("<Q", huge, at, 1 << 40)  # a trillion values declared in a 50 kB file
    cases["huge declared size"] = bytes(huge)
    reasons = {}
    for case, data in cases.items():
        bad.write_bytes(data)
        with pytest.raises(InputError) as info:
            read_capture(bad, daq[1])
        assert info.value.file == str(bad), case
        reasons[case] = info.value.reason
    assert reasons["truncated data"].startswith("truncated or damaged TDMS file: Last segment of file has less data")
    assert reasons["truncated metadata"] == "truncated or damaged TDMS file: Last segment metadata is incomplete"
    assert reasons["truncated lead-in"] == "truncated TDMS file: 20 bytes, less than one segment's 28-byte lead-in"
    assert reasons["not TDMS"] == "not a TDMS file: it starts with b'Zeit', not a segment's tag b'TDSm'"
    # npTDMS sizes the array by the data the segment holds and says so in a warning: refused
    assert reasons["huge declared size"].startswith("truncated or damaged TDMS file: Data size")
    assert "is not a multiple of the chunk size 8796093" in reasons["huge declared size"]


def test_declared_size_checked_before_an_array_is_made(tmp_path, ref, monkeypatch):
    """Defence behind npTDMS's own: a channel whose declared count exceeds the file is refused unread."""
    from nptdms.tdms import TdmsChannel

    path = _write(tmp_path / "c.tdms", _daq_channels(ref), _root(ref))
    monkeypatch.setattr(TdmsChannel, "__len__", lambda self: 1 << 40)
    with pytest.raises(InputError, match=r"declares 1099511627776 values of 8 bytes, more than the file's \d+ bytes") as info:
        read_capture(path, _map(tmp_path))
    assert info.value.field == "Messdaten/Drehmoment"


def test_cli_reads_tdms_and_exits_2_on_a_bad_one(daq, tmp_path):
    ok = CliRunner().invoke(cli, ["capture", "info", str(daq[0]), "--map", str(daq[1]), "--json"])
    assert ok.exit_code == 0, ok.output
    assert '"format": "tdms"' in ok.stdout and '"valid": true' in ok.stdout
    out = tmp_path / "c.csv"
    assert CliRunner().invoke(cli, ["capture", "convert", str(daq[0]), str(out), "--map", str(daq[1])]).exit_code == 0
    assert read_capture(out).metadata["serial"] == "T-0001"
    bad = tmp_path / "bad.tdms"
    bad.write_bytes(daq[0].read_bytes()[:-100])
    res = CliRunner().invoke(cli, ["capture", "convert", str(bad), str(tmp_path / "x.csv"), "--map", str(daq[1])])
    assert res.exit_code == 2 and f"file {bad}: truncated or damaged TDMS file" in res.output
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.slow  # 300 files: a few seconds
def test_mutated_files_read_or_refused_never_crash(tmp_path, ref, daq):
    """Bit flips, 32/64-bit fields overwritten (counts, offsets, lengths), cuts and spliced-in copies of
    a good file: each one reads as a capture or is refused as input, nothing else escapes."""
    import random

    good, rng = daq[0].read_bytes(), random.Random(38)
    outcomes = {"read": 0, "refused": 0}
    for _ in range(300):
        data = bytearray(good)
        how = rng.choice(["flip", "u32", "u64", "cut", "splice"])
        if how == "flip":
            for _ in range(rng.randint(1, 4)):
                data[rng.randrange(len(data))] = rng.randrange(256)
        elif how in ("u32", "u64"):
            size, fmt = (4, "<I") if how == "u32" else (8, "<Q")
            value = rng.choice([0, 1, (1 << (8 * size)) - 1, 1 << (8 * size - 1), rng.randrange(1 << (8 * size))])
            struct.pack_into(fmt, data, rng.randrange(len(data) - size), value)
        elif how == "cut":
            data = data[:rng.randrange(len(data))]
        else:
            at = rng.randrange(len(data))
            data = data[:at] + good[rng.randrange(len(good)):][:rng.randrange(1, 2000)] + data[at:]
        bad = tmp_path / "m.tdms"
        bad.write_bytes(bytes(data))
        try:
            read_capture(bad, daq[1])
            outcomes["read"] += 1
        except InputError as exc:
            assert exc.file in (str(bad), str(daq[1])) and exc.reason, how
            outcomes["refused"] += 1
    assert outcomes["read"] > 0 and outcomes["refused"] > 100, outcomes


def test_daqmx_fixture_reproduces_the_model():
    """fixtures/daq_export_daqmx.tdms: two DAQmx tasks at 10 and 20 kHz, the digital one started 5 ms
    later; through its map the capture starts at 5 ms on the analog clock, every level in place."""
    from pathlib import Path

    from eol_cal.capture.synthetic import synthetic_capture

    fixtures = Path(__file__).resolve().parent.parent / "fixtures"
    c = read_capture(fixtures / "daq_export_daqmx.tdms", fixtures / "daq_export_daqmx.map.toml")
    ref = synthetic_capture(rpm=60.0, i_qo=65.0, seconds=1.0, fs=20000.0, serial="M-0002", seed=4)
    on_analog = slice(100, None, 2)  # 5 ms = 100 samples of 20 kHz; the analog task took every second one
    assert c.t[0] == pytest.approx(0.005, abs=1e-12) and c.sample_rate == pytest.approx(10000.0)
    assert len(c.t) == len(ref.t[on_analog])
    assert np.allclose(c["torque"], ref["torque"][on_analog], rtol=1e-14, atol=0)
    for name in ("enc_a", "enc_b", "hall"):
        assert np.array_equal(c[name], ref[name][on_analog]), name
    assert c.metadata["serial"] == "M-0002" and c.metadata["station"] == "EOL-3" and c.metadata["poles"] == 6
