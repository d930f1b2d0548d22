"""``eol-cal run --station FILE``: the cycle configured from a station settings file, options and
variables over it, and a bad key refused before the dyno moves.

Real parts: the loopback station (ECU simulator over python-can-remote, pymodbus dyno simulator
on 127.0.0.1; the dyno's analytic capture source, so the run is short), SQLite.
"""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

from click.testing import CliRunner
import pytest

from cli.main import cli
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.ecu import protocol as P
from eol_cal.sim.loopback import loopback_station

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"


def _station_file(d: Path, dyno: str, channel: str, **extra: str) -> Path:
    (d / "ecu.key").write_text(P.DEV_SECRET.hex() + "\n")
    (d / "limits.toml").write_bytes((FIXTURES / "limits.toml").read_bytes())
    top = "".join(f"{k} = {v}\n" for k, v in extra.items())
    path = d / "station.toml"
    path.write_text(f"""{top}station_id = "L3-EOL-02"
limits = "missing-limits.toml"
db = "records.sqlite"
report_dir = "reports"
spool_dir = "spool"
key_file = "ecu.key"
[dyno]
address = "{dyno}"
[can]
interface = "remote"
channel = "{channel}"
""")
    return path


def _env() -> dict[str, str | None]:
    # the test's own variables only: a station's EOL_CAL_* must not leak in (None unsets)
    import os

    return {k: None for k in os.environ if k.startswith("EOL_CAL_") and k != "EOL_CAL_JAX_CACHE"}


@pytest.mark.slow
def test_run_from_a_settings_file_with_an_option_and_a_variable_over_it(tmp_path):
    station_dir = tmp_path / "station"
    station_dir.mkdir()
    with loopback_station("S-7", 7, tmp_path / "sim", source=synthetic_source) as st:
        path = _station_file(station_dir, st.dyno_address, st.can_channel)
        env = {**_env(), "EOL_CAL_STATION_ID": "L3-EOL-09"}
        # the file names a limits file that does not exist: the option given replaces it unread
        res = CliRunner().invoke(cli, ["run", "--station", str(path), "--serial", "S-7", "--operator", "dana",
                                       "--limits", str(station_dir / "limits.toml"), "--json"], env=env)
    assert res.exit_code in (0, 1, 2) and res.stdout.startswith("{"), res.output
    rec = json.loads(res.stdout)["record"]
    assert rec["station"]["id"] == "L3-EOL-09" and rec["station"]["operator"] == "dana"
    assert rec["station"]["settings"] == str(path) and rec["station"]["dyno"] == st.dyno_address
    assert rec["limits"]["source"] == str(station_dir / "limits.toml")
    # paths in the file are relative to it, the database too
    assert rec["report_dir"].startswith(str(station_dir / "reports"))
    with sqlite3.connect(station_dir / "records.sqlite") as con:
        assert con.execute("SELECT serial, station, operator FROM runs").fetchall() == [("S-7", "L3-EOL-09", "dana")]


def test_a_bad_key_is_refused_before_the_dyno_moves(tmp_path):
    path = _station_file(tmp_path, "127.0.0.1:1", "ws://127.0.0.1:1/", rate_hz='"fast"')
    res = CliRunner().invoke(cli, ["run", "--station", str(path), "--serial", "S-1",
                                   "--limits", str(tmp_path / "limits.toml")], env=_env())
    assert res.exit_code == 2 and f"file {path}, field 'rate_hz': expected int" in res.output, res.output
    path = _station_file(tmp_path, "127.0.0.1:1", "ws://127.0.0.1:1/", variant='"NOPE"')
    res = CliRunner().invoke(cli, ["run", "--station", str(path), "--serial", "S-1",
                                   "--limits", str(tmp_path / "limits.toml")], env=_env())
    assert res.exit_code == 2 and f"file {path}, field 'variant'" in res.output and "NOPE" in res.output, res.output
    res = CliRunner().invoke(cli, ["run", "--station", str(path), "--serial", "S-1"], env=_env())
    assert res.exit_code == 2 and "field 'limits': no such file" in res.output and "missing-limits.toml" in res.output
    assert not (tmp_path / "records.sqlite").exists() and not (tmp_path / "reports").exists()


def test_run_without_a_file_takes_the_variables(tmp_path):
    path = _station_file(tmp_path, "127.0.0.1:1", "ws://127.0.0.1:1/")
    env = {**_env(), "EOL_CAL_DYNO_ADDRESS": "127.0.0.1:1", "EOL_CAL_LIMITS": str(tmp_path / "limits.toml"),
           "EOL_CAL_DB": str(tmp_path / "r.sqlite"), "EOL_CAL_KEY_FILE": str(tmp_path / "ecu.key"),
           "EOL_CAL_CAN_INTERFACE": "remote", "EOL_CAL_VARIANT": "NOPE"}
    res = CliRunner().invoke(cli, ["run", "--serial", "S-1"], env=env)
    # every required key came from a variable; the bad one is named as the variable
    assert res.exit_code == 2 and "file $EOL_CAL_VARIANT, field 'variant'" in res.output, res.output
    del env["EOL_CAL_DB"]
    res = CliRunner().invoke(cli, ["run", "--serial", "S-1"], env=env)
    assert res.exit_code == 2 and "field 'db': required: give --db" in res.output and "EOL_CAL_DB" in res.output, res.output
    assert path.is_file() and not (tmp_path / "r.sqlite").exists()


@pytest.mark.slow  # a loopback station and a full cycle; the bad-key tests keep the module in the fast loop
def test_the_operator_loop_on_a_settings_file(tmp_path):
    # the real station's path of `eol-cal station`: the dyno and the ECU from the file (here the
    # loopback station's), the operator asked, one motor, q; the lot page where --lot says
    station_dir = tmp_path / "station"
    station_dir.mkdir()
    with loopback_station("S-8", 8, tmp_path / "sim", source=synthetic_source) as st:
        path = _station_file(station_dir, st.dyno_address, st.can_channel)
        res = CliRunner().invoke(cli, ["station", "--station", str(path), "--limits", str(station_dir / "limits.toml"),
                                       "--lot", str(tmp_path / "lot.html")],
                                 input="  eve \nS-8\nq\n", env=_env())
    assert res.exit_code == 0, res.output
    assert "Operator: " in res.output and "S-8: " in res.output and "session: 1 run(s) of 1 motor(s)" in res.output
    assert (tmp_path / "lot.html").is_file()
    with sqlite3.connect(station_dir / "records.sqlite") as con:
        assert con.execute("SELECT serial, station, operator FROM runs").fetchall() == [("S-8", "L3-EOL-02", "eve")]
