"""Issue 38's "done when" for the DAQ files: a TDMS file and a tab-separated decimal-comma export of
the same captures give `eol-cal fit` the same result as their CSV."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from nptdms import ChannelObject, GroupObject, RootObject, TdmsWriter

from cli.main import cli
from eol_cal.capture import read_capture
from eol_cal.capture.io import write_capture
from eol_cal.capture.metadata import encode_value
from eol_cal.capture.synthetic import synthetic_capture

pytestmark = pytest.mark.slow  # three fits of six captures

# the operating points of tests/test_fit_cli.py: two speeds, two loads and reverse
POINTS = [(120.0, 20.0), (120.0, 65.0), (240.0, 20.0), (240.0, 65.0), (-120.0, -20.0), (-120.0, -65.0)]
TRUTH = dict(k6=0.00062, phase_k6=0.3, c6=0.004, phase_c6=1.1)

TDMS_MAP = """[channels]
torque = { name = "AI/Moment" }                  # unit from unit_string: N*cm
enc_a  = { name = "Encoder A" }
enc_b  = { name = "Encoder B" }
hall   = { bits = ["Hall U", "Hall V", "Hall W"] }
iq_ref = { name = "Iq Soll" }
speed  = { name = "Drehzahl", unit = "1/min" }
"""

TEXT_MAP = """[channels]
t      = { name = "Zeit" }
torque = { name = "Moment" }
enc_a  = { name = "Spur A" }
enc_b  = { name = "Spur B" }
hall   = { name = "Hall" }
iq_ref = { name = "Iq Soll" }
speed  = { name = "Drehzahl" }

[file]
format = "text"
delimiter = "\\t"
decimal = ","
units_row = true
"""


def _tdms(c, path):
    """The capture as a DAQmx task writes it: waveforms with wf_increment, units in unit_string."""
    wf = {"wf_increment": float(c.t[1] - c.t[0]), "wf_start_offset": float(c.t[0])}

    def channel(name, values, unit=""):
        return ChannelObject("AI", name, values, properties={**wf, "unit_string": unit})

    bits = [channel(f"Hall {line}", ((c["hall"] >> bit) & 1).astype(np.uint8)) for bit, line in enumerate("UVW")]
    with TdmsWriter(str(path)) as w:
        w.write_segment([RootObject(properties=dict(c.metadata)), GroupObject("AI"),
                         channel("Moment", c["torque"] * 100.0, "N*cm"),
                         channel("Encoder A", c["enc_a"].astype(np.uint8)), channel("Encoder B", c["enc_b"].astype(np.uint8)),
                         *bits, channel("Iq Soll", c["iq_ref"], "A"), channel("Drehzahl", c["speed"], "1/min")])


def _tsv(c, path):
    """The capture as a German spreadsheet export: tab-separated, decimal comma, a units row, .txt."""
    head = [f"# {k}: {encode_value(k, v)}" for k, v in c.metadata.items()]
    head += ["Zeit\tMoment\tSpur A\tSpur B\tHall\tIq Soll\tDrehzahl", "ms\tN*m\t-\t-\t-\tA\t1/min"]
    columns = [c.t * 1000.0, c["torque"], c["enc_a"], c["enc_b"], c["hall"], c["iq_ref"], c["speed"]]
    rows = ("\t".join(repr(float(v)).replace(".", ",") if isinstance(v, float) else str(v) for v in row)
            for row in zip(*(col.tolist() for col in columns), strict=True))
    path.write_text("\n".join([*head, *rows]) + "\n", encoding="utf-8")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("daqfit")
    (d / "tdms.toml").write_text(TDMS_MAP)
    (d / "text.toml").write_text(TEXT_MAP)
    out: dict = {"csv": [], "tdms": [], "txt": [], "dir": d}
    for i, (rpm, iq) in enumerate(POINTS):
        c = synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=i, theta_r0=0.7 * i, serial="M-0007", **TRUTH)
        write_capture(c, d / f"c{i}.csv")
        _tdms(c, d / f"c{i}.tdms")
        _tsv(c, d / f"c{i}.txt")
        for ext in ("csv", "tdms", "txt"):
            out[ext].append(str(d / f"c{i}.{ext}"))
    return out


def test_the_three_files_hold_the_same_capture(files):
    for csv, tdms, txt in zip(files["csv"], files["tdms"], files["txt"], strict=True):
        a = read_capture(csv)
        for b in (read_capture(tdms, files["dir"] / "tdms.toml"), read_capture(txt, files["dir"] / "text.toml")):
            assert np.allclose(b.t, a.t, rtol=1e-13, atol=1e-15)
            assert list(b.channels) == list(a.channels)
            for name in a.channels:
                assert np.allclose(b[name], a[name], rtol=1e-13, atol=0), name
            assert b.metadata == a.metadata


def _fit(inputs, out, map_file=None):
    args = ["fit", *inputs, "-o", str(out), "--bench", "none"] + (["--map", str(map_file)] if map_file else [])
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    (motor,) = json.loads(out.read_text())["motors"]
    return motor


def test_tdms_and_tab_separated_decimal_comma_fit_as_the_csv(files):
    d = files["dir"]
    a = _fit(files["csv"], d / "csv.json")
    assert a["status"] == "ok" and abs(a["k6"]["value"] - TRUTH["k6"]) < 0.02 * TRUTH["k6"]
    for ext, map_file in (("tdms", d / "tdms.toml"), ("txt", d / "text.toml")):
        b = _fit(files[ext], d / f"{ext}.json", map_file)
        assert b["status"] == a["status"] and b["serial"] == a["serial"], ext
        for key in ("k6", "phase_k6", "c6", "phase_c6", "delay_s"):
            assert b[key]["value"] == pytest.approx(a[key]["value"], rel=1e-9, abs=1e-15), (ext, key)
            assert b[key]["ci95"] == pytest.approx(a[key]["ci95"], rel=1e-6), (ext, key)
        assert b["fit"]["n_samples"] == a["fit"]["n_samples"] and len(b["segments"]) == len(a["segments"])
