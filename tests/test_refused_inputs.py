"""Inputs that must be refused (issue 23, class 6), several members of each: an MDF4 channel that
is not real numbers, a header comment that gives a key twice (asammdf hid it) or is malformed, an
ECU-state record at one end only, station settings whose values fail only at first use (estimator,
dyno address, database address, CAN configuration), a serial a block cannot carry, and a NUL in
the operator's line. Each is one line naming the file or variable and the key, exit 2, before
anything runs."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from _capture_helpers import small_capture, with_metadata
from cli.main import cli
from eol_cal.capture.io import write_capture
from eol_cal.ecu import protocol as P
from eol_cal.sim.fuzz import hostile, scenarios

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "fixtures"


def _refused(res, *words: str) -> str:
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output, res.output
    line = res.stderr.strip().splitlines()[-1]
    for w in words:
        assert w in line, res.output
    return line


def _env() -> dict[str, str | None]:
    return {k: None for k in os.environ if k.startswith("EOL_CAL_") and k != "EOL_CAL_JAX_CACHE"}


# ------------------------------------------------------------------------------------------ MDF4


@pytest.fixture(scope="module")
def mdf4_base() -> bytes:
    from eol_cal.sim.fuzz import base_files

    return base_files()["mdf4"]


@pytest.mark.parametrize("dtype", [np.complex128, np.complex64])
def test_a_complex_channel_is_refused_not_read_as_its_real_part(tmp_path, dtype):
    from asammdf import MDF, Signal

    cap = small_capture()
    src = tmp_path / "base.mf4"
    write_capture(cap, src)
    with MDF(str(src)) as m:
        sigs = []
        for name in ("torque", "enc_a", "enc_b", "hall", "iq_ref"):
            s = m.get(name)
            if name == "iq_ref":
                s = Signal(samples=s.samples.astype(dtype) + 1j, timestamps=s.timestamps, name=name, unit=s.unit)
            sigs.append(s)
        out = MDF(version="4.10")
        out.append(sigs)
        out.header.comment = m.header.comment
        bad = tmp_path / "complex.mf4"
        out.save(str(bad), overwrite=True)
        out.close()
    res = CliRunner().invoke(cli, ["capture", "info", str(bad)])
    _refused(res, str(bad), "iq_ref", "complex")


@pytest.mark.parametrize("name, extra, where", [c for c in hostile.MDF4_COMMENTS if "nested" not in c[0]])
def test_a_header_comment_with_a_key_twice_or_malformed_is_refused(tmp_path, mdf4_base, name, extra, where):
    path = tmp_path / "c.mf4"
    path.write_bytes(hostile.mdf4_with_header_comment(mdf4_base, hostile.header_comment_with(mdf4_base, extra, where)))
    res = CliRunner().invoke(cli, ["capture", "info", "--json", str(path)])
    _refused(res, str(path))
    assert res.stdout == ""  # asammdf's traceback on stdout does not reach a --json reader


def test_the_same_comment_written_back_unchanged_is_read(tmp_path, mdf4_base):
    path = tmp_path / "c.mf4"
    path.write_bytes(hostile.mdf4_with_header_comment(mdf4_base, hostile.header_comment_with(mdf4_base, "")))
    res = CliRunner().invoke(cli, ["capture", "info", "--json", str(path)])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["metadata"]["poles"] == 6


@pytest.mark.parametrize("suffix", [".csv", ".mf4"])
@pytest.mark.parametrize("keep", ["ecu_before", "ecu_after"])
def test_an_ecu_state_recorded_at_one_end_only_is_refused_by_capture_info(tmp_path, suffix, keep):
    drop = "ecu_after" if keep == "ecu_before" else "ecu_before"
    cap = with_metadata(small_capture(), **{f"{drop}.bank": None, f"{keep}.bank": "1", f"{keep}.sequence": 2,
                                            f"{keep}.crc32": "5be1c0a7", f"{keep}.flags": "INTERP_ENABLE"})
    path = tmp_path / f"one-end{suffix}"
    write_capture(cap, path)
    res = CliRunner().invoke(cli, ["capture", "info", str(path)])
    _refused(res, str(path), drop, "only at one end")


# ------------------------------------------------------------------------------ station settings


def _station(d: Path, *, top: str = "", dyno: str = '"127.0.0.1:1"', db: str = '"records.sqlite"', can: str = "") -> Path:
    (d / "ecu.key").write_text(P.DEV_SECRET.hex() + "\n")
    (d / "limits.toml").write_bytes((FIXTURES / "limits.toml").read_bytes())
    path = d / "station.toml"
    path.write_text(f'{top}\nstation_id = "L3"\nlimits = "limits.toml"\ndb = {db}\nkey_file = "ecu.key"\n'
                    f'[dyno]\naddress = {dyno}\n[can]\ninterface = "virtual"\nchannel = "x"\n{can}\n')
    return path


BAD_SETTINGS = [
    ({"top": 'estimator = "foo"'}, "estimator"),
    ({"top": 'estimator = "best+nonsense"'}, "estimator"),
    ({"dyno": '"a b"'}, "dyno.address"),
    ({"dyno": '"http://192.0.2.10"'}, "dyno.address"),
    ({"dyno": '"http://dyno:502"'}, "dyno.address"),
    ({"dyno": '"dyno_3"'}, "dyno.address"),
    ({"dyno": '"[zz]:502"'}, "dyno.address"),
    ({"db": '"."'}, "db"),
    ({"db": '"sqlite:///x.sqlite"'}, "db"),
    ({"db": '"postgresql+psycopg2://u@h/eol"'}, "db"),
    ({"db": '"mysql://u@h/eol"'}, "db"),
    ({"db": '"postgresql://u@h:port/eol"'}, "db"),
    ({"db": '"postgresql://u@h"'}, "db"),
    ({"db": '"no-such-dir/records.sqlite"'}, "db"),
    ({"db": '"/dev/null"'}, "db"),
    ({"can": 'config = "garbage.cfg"'}, "can.config"),
    ({"can": 'config = "other.cfg"'}, "can.config"),
]


@pytest.mark.parametrize("command", ["run", "station"])
@pytest.mark.parametrize("keys, field", BAD_SETTINGS)
def test_a_settings_value_that_would_fail_in_the_cycle_is_refused_at_the_start(tmp_path, command, keys, field):
    (tmp_path / "garbage.cfg").write_bytes(b"\x00\x01garbage [[[\n= = =\n")
    (tmp_path / "other.cfg").write_text("[default]\nbitrate = fast\n")
    path = _station(tmp_path, **keys)
    args = ["run", "--station", str(path), "--serial", "M-1"] if command == "run" else \
        ["station", "--station", str(path), "--operator", "bob"]
    res = CliRunner().invoke(cli, args, env=_env(), input="q\n")
    _refused(res, str(path), f"field '{field}'")
    assert not (tmp_path / "records.sqlite").exists() and not (tmp_path / "reports").exists()


@pytest.mark.parametrize("variable, value, field", [
    ("EOL_CAL_DB", "mysql://a@b/c", "db"), ("EOL_CAL_DYNO_ADDRESS", "a b", "dyno.address"),
    ("EOL_CAL_ESTIMATOR", "foo", "estimator"),
])
def test_the_same_values_from_a_variable_name_the_variable(tmp_path, variable, value, field):
    path = _station(tmp_path)
    res = CliRunner().invoke(cli, ["run", "--station", str(path), "--serial", "M-1"], env={**_env(), variable: value})
    _refused(res, f"${variable}", f"field '{field}'")


@pytest.mark.parametrize("db", ["sqlite:///x.sqlite", "postgresql+psycopg2://u@h/eol", "postgresql://u@h", "/dev/null"])
def test_the_db_option_takes_the_same_rule(tmp_path, db):
    res = CliRunner().invoke(cli, ["records", "--db", db])
    assert res.exit_code == 2 and "--db" in res.output and "Traceback" not in res.output, res.output


# --------------------------------------------------------------------------------------- serials


@pytest.mark.parametrize("serial", ["", "   ", " M-1", "M\x001", "M\t1", "X" * 17, "Mé"])
def test_a_fit_result_whose_serial_a_block_cannot_carry_is_refused_by_table(tmp_path, serial):
    doc = json.loads((FIXTURES / "fit_paper.json").read_text())
    doc["motors"][0]["serial"] = serial
    bad = tmp_path / "fit.json"
    bad.write_text(json.dumps(doc))
    res = CliRunner().invoke(cli, ["table", str(bad), "-o", str(tmp_path / "b.bin")])
    _refused(res, str(bad), "motors[0].serial")
    assert not (tmp_path / "b.bin").exists()



@pytest.mark.parametrize("converged", [False, None, "yes", 1])
def test_a_fit_result_that_did_not_converge_is_never_a_result_whatever_its_status(tmp_path, converged):
    doc = json.loads((FIXTURES / "fit_paper.json").read_text())
    assert doc["motors"][0]["status"] == "ok"
    doc["motors"][0]["fit"]["converged"] = converged
    bad = tmp_path / "fit.json"
    bad.write_text(json.dumps(doc))
    res = CliRunner().invoke(cli, ["table", str(bad), "-o", str(tmp_path / "b.bin")])
    _refused(res, str(bad), "motors[0].fit.converged")
    assert not (tmp_path / "b.bin").exists()

# ------------------------------------------------------- revision 1.2: a fit result's mech object


@pytest.mark.parametrize("name,path,value", [pytest.param(*m, id=m[0]) for m in scenarios.BAD_MECH])
def test_a_fit_result_whose_mechanical_part_is_out_of_bounds_is_refused_by_table(tmp_path, name, path, value):
    """The layout-2 block (table's default) is built from ``mech``; every member is refused with
    its field, nothing written (an order outside 1..3 or given twice was dropped or overwritten)."""
    from eol_cal.sim.fuzz.mutate import fit_result_with_mech

    doc = json.loads(fit_result_with_mech((FIXTURES / "fit_paper.json").read_bytes()))
    at = doc["motors"][0]["mech"]
    for k in path[:-1]:
        at = at[k]
    at[path[-1]] = float("nan") if value == "NaN" else value
    bad = tmp_path / "fit.json"
    bad.write_text(json.dumps(doc))
    res = CliRunner().invoke(cli, ["table", str(bad), "-o", str(tmp_path / "b.bin")])
    _refused(res, str(bad), "motors[0].mech.")
    assert not (tmp_path / "b.bin").exists()


def test_the_valid_mechanical_part_gives_a_layout_2_block_with_mech_on(tmp_path):
    from eol_cal.firmware import block as B
    from eol_cal.sim.fuzz.mutate import fit_result_with_mech

    good = tmp_path / "fit.json"
    good.write_bytes(fit_result_with_mech((FIXTURES / "fit_paper.json").read_bytes()))
    res = CliRunner().invoke(cli, ["table", str(good), "-o", str(tmp_path / "b.bin")])
    assert res.exit_code == 0, res.output
    blk = B.unpack((tmp_path / "b.bin").read_bytes())
    assert blk.layout_version == 2 and blk.flags & B.FLAG_MECH_COMP_ENABLE
    assert blk.mech.mech_c[0] == pytest.approx(0.004)


@pytest.mark.parametrize("value", ["-0.001", "11.0", "nan", "inf", '"0.01"', "true"])
def test_the_new_limit_row_takes_the_limits_rules(tmp_path, value):
    """``max_mech1_after_nm`` (revision 1.2) through the same checks as every limit row."""
    for name, data in scenarios.station_files().items():
        (tmp_path / name).write_bytes(data)
    text = (FIXTURES / "limits.toml").read_text().replace(
        "[variant.EPS-STD]\n", f"[variant.EPS-STD]\nmax_mech1_after_nm = {value}\n")
    (tmp_path / "limits.toml").write_text(text)
    res = CliRunner().invoke(cli, ["run", "--station", str(tmp_path / "station.toml"), "--serial", "M-1"], env=_env())
    _refused(res, "limits.toml", "max_mech1_after_nm")
    assert not (tmp_path / "records.sqlite").exists()


def test_a_nul_in_the_scanned_line_is_refused_not_swallowed(tmp_path):
    """Through a real terminal: the line "M\\0q" is not a serial (line editing swallowed the NUL
    and the motor was calibrated as "Mq"); nothing runs, the session ends on q."""
    from test_station_operator import Terminal

    t = Terminal(["station", "--demo", "--out", str(tmp_path / "out"), "--operator", "bob"], tmp_path)
    try:
        t.expect(r"Scan serial", 120)
        t.type("M\x00q", enter="\r")
        t.expect(r"not a serial", 120)  # hang guards: the order is what is checked
        t.expect(r"Scan serial", 120)
        t.type("q", enter="\r")
        assert t.exit_code() == 0
        assert "Mq" not in t.text.replace("M\x00q", "")
        assert not (tmp_path / "out" / "results.sqlite").exists() or "0 motor(s)" in t.text
    finally:
        t.close()
