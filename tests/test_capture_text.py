"""Delimited text exports (tab, semicolon, blanks; decimal comma; a units row; any suffix) through a
channel map's ``[file]`` table, on files written by hand as DAQ software writes them."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.capture import load_channel_map, read_capture
from eol_cal.errors import InputError

CHANNELS = """[channels]
t      = { name = "Zeit" }
torque = { name = "Moment" }
enc_a  = { name = "A" }
hall   = { name = "Hall" }
"""
META = '[metadata]\nserial = "H-1"\npoles = 6\nencoder_ppr = 64\niq_ref = 65.0\n'

#: a German DAQ's tab-separated export: preamble, units row, decimal comma, CRLF
TSV = (
    "MessDAQ 3.2\tExport\r\n"
    "Datum\t28.11.2026\r\n"
    "Zeit\tMoment\tA\tHall\r\n"
    "ms\tN*cm\t-\t\r\n"
    "0,0\t317,315\t1\t5\r\n"
    "0,1\t317,127\t1\t5\r\n"
    "0,2\t-12,5\t0\t1\r\n"
)


def _files(tmp_path, text, mapping, name="export.txt", encoding="utf-8"):
    data, map_file = tmp_path / name, tmp_path / "m.toml"
    data.write_bytes(text.encode(encoding))
    map_file.write_text(mapping, encoding="utf-8")
    return data, map_file


def _read(data, map_file):
    return read_capture(data, map_file, validate=False)


def test_tab_separated_decimal_comma_with_units_row_and_preamble(tmp_path):
    data, map_file = _files(tmp_path, TSV, CHANNELS + META + '[file]\nformat = "text"\ndelimiter = "\\t"\n'
                                           'decimal = ","\nunits_row = true\nskip_lines = 2\n')
    c = _read(data, map_file)
    assert c.t.tolist() == [0.0, 0.0001, 0.0002]  # ms -> s from the units row
    assert c["torque"].tolist() == pytest.approx([3.17315, 3.17127, -0.125], rel=1e-15)  # N*cm -> N*m
    assert c["enc_a"].tolist() == [1, 1, 0] and c["hall"].tolist() == [5, 5, 1]
    assert c["enc_a"].dtype == np.int8
    assert c.metadata == {"serial": "H-1", "poles": 6, "encoder_ppr": 64, "iq_ref": 65.0}


def test_semicolon_quoted_header_units_in_brackets_cp1252_any_suffix(tmp_path):
    text = ('# serial: S-7\n'
            '"Zeit [s]";"Moment";"A";"Hall";"T_Wicklung"\n'
            ';[Nm];;;[°C]\n'
            '0,000;3,5;0;3;20,5\n'
            '0,001;3,25;1;2;20,75\n')
    mapping = (CHANNELS + 'temp = { name = "T_Wicklung" }\n[metadata]\npoles = 6\nencoder_ppr = 64\n'
               '[file]\nformat = "text"\ndelimiter = ";"\ndecimal = ","\nunits_row = true\nencoding = "cp1252"\n')
    c = _read(*_files(tmp_path, text, mapping, name="lauf.dat", encoding="cp1252"))
    assert c.t.tolist() == [0.0, 0.001] and c["torque"].tolist() == [3.5, 3.25]
    assert c["temp"].tolist() == [20.5, 20.75] and c.metadata["serial"] == "S-7"


def test_every_line_ending_with_the_delimiter(tmp_path):
    """Some DAQ software ends each line with the separator: no empty last column is read."""
    text = "Zeit;Moment;A;Hall;\ns;N*m;;;\n0,0;3,5;0;3;\n0,001;3,25;1;2;\n"
    mapping = CHANNELS + '[file]\nformat = "text"\ndelimiter = ";"\ndecimal = ","\nunits_row = true\n'
    c = _read(*_files(tmp_path, text, mapping))
    assert c.t.tolist() == [0.0, 0.001] and c["torque"].tolist() == [3.5, 3.25] and c["hall"].tolist() == [3, 2]
    # a header that does not end with it keeps an empty last cell an error
    text = "Zeit;Moment;A;Hall\n0,0;3,5;0;3;\n"
    with pytest.raises(InputError, match="unreadable data"):
        _read(*_files(tmp_path, text, mapping.replace("units_row = true", "units_row = false")))


def test_blank_separated_columns(tmp_path):
    text = "Zeit Moment   A Hall\n0.0  3.5   0 3\n0.001 3.25 1   2\n"
    mapping = CHANNELS + '[file]\nformat = "text"\ndelimiter = " "\n'
    c = _read(*_files(tmp_path, text, mapping, name="x.asc"))
    assert c["torque"].tolist() == [3.5, 3.25] and c["hall"].tolist() == [3, 2]


def test_a_csv_map_may_describe_the_csv_it_reads(tmp_path):
    """Without format the suffix decides; text options go with a .csv file."""
    text = "Zeit,Moment,A,Hall\ns,N*m,,\n0.0,3.5,0,3\n0.001,3.25,1,2\n"
    c = _read(*_files(tmp_path, text, CHANNELS + "[file]\nunits_row = true\n", name="x.csv"))
    assert c["torque"].tolist() == [3.5, 3.25]


@pytest.mark.parametrize(
    ("name", "mapping", "file_is", "field", "message"),
    [
        # a suffix no reader takes: refused, however the text looks, unless the map names the format
        ("x.txt", CHANNELS, "data", None, r"unknown capture file type '\.txt'; .*format = \"text\""),
        ("x.txt", CHANNELS + '[file]\ndelimiter = "\\t"\n', "data", None, "unknown capture file type"),
        # text options for a file read as TDMS or MDF4
        ("x.tdms", CHANNELS + '[file]\ndelimiter = "\\t"\n', "map", "file.delimiter",
         "an option of text files, but .*x.tdms is read as tdms"),
        ("x.txt", CHANNELS + '[file]\nformat = "text"\nsample_rate = 1000\n', "map", "file.sample_rate",
         "an option of tdms files, but the file is read as text"),
        ("x.txt", CHANNELS + '[file]\nformat = "xlsx"\n', "map", "file.format", "'xlsx' is not one of"),
        ("x.txt", CHANNELS + '[file]\nformat = "text"\ndelimiter = "x"\n', "map", "file.delimiter", "'x' is not one of"),
        ("x.txt", CHANNELS + '[file]\nformat = "text"\ndecimal = ","\n', "map", "file.decimal",
         "the decimal mark cannot also be the delimiter"),
        ("x.txt", CHANNELS + '[file]\nformat = "text"\nencoding = "klingon"\n', "map", "file.encoding",
         "unknown encoding 'klingon'"),
        ("x.txt", CHANNELS + '[file]\nformat = "text"\nskip_lines = -1\n', "map", "file.skip_lines", "must be an integer"),
        ("x.txt", CHANNELS + '[file]\nformat = "text"\nunits_row = "yes"\n', "map", "file.units_row", "true or false"),
        ("x.txt", CHANNELS + '[file]\nformat = "text"\nquote = "\'"\n', "map", "file.quote", "unknown key"),
        ("x.tdms", CHANNELS + '[file]\nsample_rate = inf\n', "map", "file.sample_rate", "must be a number of Hz"),
    ],
)
def test_map_file_options_refused(tmp_path, name, mapping, file_is, field, message):
    data, map_file = _files(tmp_path, "Zeit\tMoment\tA\tHall\n0\t1\t0\t1\n", mapping, name=name)
    with pytest.raises(InputError, match=message) as info:
        _read(data, map_file)
    assert info.value.file == str(data if file_is == "data" else map_file)
    assert info.value.field == field


@pytest.mark.parametrize(
    ("text", "options", "field", "message"),
    [
        # a decimal comma the map does not announce: the hint says how to read it
        ("Zeit;Moment;A;Hall\n0,0;3,5;0;3\n", 'delimiter = ";"', "Zeit",
         r"could not convert string '0,0' to float64 .*a channel map's \[file\] decimal = \",\" reads a decimal comma"),
        ("Zeit\tMoment\tA\tHall\nms\tN*cm\t\n0\t1\t0\t3\n", 'delimiter = "\\t"\nunits_row = true', None,
         r"units row \(line 2\) holds 3 cells, the header 4"),
        ("Zeit [s]\tMoment\tA\tHall\nms\tN*cm\t\t\n0\t1\t0\t3\n", 'delimiter = "\\t"\nunits_row = true', "Zeit",
         r"header states unit 's', the units row \(line 2\) 'ms'"),
        ("Zeit\tMoment\tA\tHall\n", 'delimiter = "\\t"\nunits_row = true', None, "no units row after the header line"),
        ("Zeit\tMoment\tA\tHall\ns\tkg\t\t\n0\t1\t0\t3\n", 'delimiter = "\\t"\nunits_row = true',
         "torque (source channel 'Moment')", r"unit 'kg' cannot be converted to 'N\*m'"),
        ("Zeit\tMoment\tA\tHall\n0\t1,5\t0\t3\n0\t1\t0\n", 'delimiter = "\\t"\ndecimal = ","', None,
         r"unreadable data .*number of columns"),
        ("Zeit\tMoment\tA\tHall\n0\tzwei\t0\t3\n", 'delimiter = "\\t"', "Moment",
         r"unreadable data \(data row 1, about line 2\)"),
        ("Zeit Moment A Hall\nms N*cm -\n0 1 0 3\n", 'delimiter = " "\nunits_row = true', None,
         r"units row \(line 2\) holds 3 units for 4 channels; .*write 1 or -"),
        ("Vorspann\n", 'delimiter = "\\t"\nskip_lines = 5', None, "1 lines, and the map skips 5 before the header"),
        ("Zeit\tMoment\tA\tHall\n", 'delimiter = "\\t"', "t", "no data rows after the header line"),
        ("", 'delimiter = "\\t"', None, "no header line of channel names"),
        ("Zeit\tMoment\tA\tHall\n0\t\xff\t0\t3\n", 'delimiter = "\\t"', None, r"not UTF-8 text \(byte 0xff at offset 21\)"),
    ],
)
def test_bad_text_refused_naming_file_field_reason(tmp_path, text, options, field, message):
    data, map_file = _files(tmp_path, text, CHANNELS + f'[file]\nformat = "text"\n{options}\n', name="x.txt",
                            encoding="latin-1" if "\xff" in text else "utf-8")
    if "\xff" in text:  # bytes that are not UTF-8: write them as latin-1, read as the default UTF-8
        data.write_bytes(text.encode("latin-1"))
    with pytest.raises(InputError, match=message) as info:
        _read(data, map_file)
    assert info.value.file == str(data) and info.value.field == field


def test_map_file_table_round_trip_and_cli_exit_codes(tmp_path):
    data, map_file = _files(tmp_path, TSV, CHANNELS + META + '[file]\nformat = "text"\ndelimiter = "\\t"\n'
                                           'decimal = ","\nunits_row = true\nskip_lines = 2\n')
    options = load_channel_map(map_file).file
    assert (options.format, options.delimiter, options.decimal, options.units_row, options.skip_lines) == (
        "text", "\t", ",", True, 2)
    # three samples are no capture: `capture info` prints what it read and exits 2 naming the reason
    res = CliRunner().invoke(cli, ["capture", "info", str(data), "--map", str(map_file)])
    assert res.exit_code == 2 and "samples" in res.output and "error: invalid capture" in res.output
    res = CliRunner().invoke(cli, ["capture", "info", str(data), "--map", str(map_file), "--json"])
    assert res.exit_code == 2 and '"format": "text"' in res.stdout and '"samples": 3' in res.stdout
    res = CliRunner().invoke(cli, ["capture", "info", str(data)])
    assert res.exit_code == 2 and "unknown capture file type '.txt'" in res.output


def test_any_suffix_read_as_the_format_the_map_names(tmp_path):
    """An MDF4 logger's ``.mdf`` and a TDMS file saved as ``.dat`` read once the map names their format."""
    import dataclasses

    from _capture_helpers import assert_same_capture, small_capture
    from nptdms import ChannelObject, GroupObject, RootObject, TdmsWriter

    from eol_cal.capture import write_capture

    ref = small_capture()
    write_capture(ref, tmp_path / "c.mf4")
    (tmp_path / "c.mf4").rename(tmp_path / "c.mdf")
    (tmp_path / "mf4.toml").write_text('[file]\nformat = "mf4"\n')
    assert_same_capture(read_capture(tmp_path / "c.mdf", tmp_path / "mf4.toml"), ref, events=False)
    with TdmsWriter(str(tmp_path / "c.dat")) as w:
        w.write_segment([RootObject(properties=dict(ref.metadata)), GroupObject("g"), *(
            ChannelObject("g", name, ref[name]) for name in ("t", *ref.channels))])
    (tmp_path / "tdms.toml").write_text('[file]\nformat = "tdms"\n')
    c = read_capture(tmp_path / "c.dat", tmp_path / "tdms.toml")
    assert_same_capture(c, dataclasses.replace(ref, truth={}), events=False)  # no truth.* written
    with pytest.raises(InputError, match=r"unknown capture file type '\.mdf'"):
        read_capture(tmp_path / "c.mdf")


def test_tab_export_fixture_reproduces_the_model():
    """fixtures/daq_export_tab.txt (preamble, tabs, decimal comma, units row, °C, cp1252, CRLF) through its map."""
    from pathlib import Path

    from eol_cal.capture.synthetic import synthetic_capture

    fixtures = Path(__file__).resolve().parent.parent / "fixtures"
    c = read_capture(fixtures / "daq_export_tab.txt", fixtures / "daq_export_tab.map.toml")
    ref = synthetic_capture(rpm=60.0, i_qo=65.0, seconds=0.5, fs=10000.0, serial="M-0003", seed=5)
    assert np.allclose(c.t, ref.t, rtol=0, atol=1e-12)
    assert np.allclose(c["torque"], ref["torque"], rtol=0, atol=0.5e-6 + 1e-12)  # written to 6 decimals
    for name in ("enc_a", "enc_b", "hall"):
        assert np.array_equal(c[name], ref[name]), name
    assert np.allclose(c["temp"], 21.5 + 0.25 * ref.t, atol=0.5e-3 + 1e-12)
    assert c.metadata == {"serial": "M-0003", "poles": 6, "encoder_ppr": 64}
