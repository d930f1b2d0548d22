"""An output over an input by any route (issue 23, class 1): ``--log-file`` naming the block
being flashed, the key file or the limits file (it was appended to, and the next run failed);
``station --lot`` naming the records database of the station settings (the lot page replaced
every record); a settings database or report directory that is an input; an output named at run
time over a file the command read. Each is refused, exit 2, every input unchanged.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from test_refused_inputs import _refused
from eol_cal.infra.atomic import atomic_write
from eol_cal.ecu import protocol as P
from eol_cal.firmware.example import example_block
from eol_cal.errors import InputError
from eol_cal.infra.inputs import command_inputs, read_bytes

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def _digests(d: Path) -> dict[str, str]:
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*")) if p.is_file()}


def _env() -> dict[str, str | None]:
    return {k: None for k in os.environ if k.startswith("EOL_CAL_") and k != "EOL_CAL_JAX_CACHE"}


@pytest.fixture
def station_dir(tmp_path: Path) -> Path:
    d = tmp_path / "station"
    d.mkdir()
    (d / "ecu.key").write_text(P.DEV_SECRET.hex() + "\n")
    (d / "limits.toml").write_bytes((FIXTURES / "limits.toml").read_bytes())
    (d / "block.bin").write_bytes(example_block(serial="M-0007"))
    (d / "can.ini").write_text("[default]\ninterface = virtual\nchannel = nobody\n")
    (d / "motor.toml").write_text("poles = 6\n")
    (d / "profile.toml").write_bytes((Path(__file__).resolve().parents[1] / "eol_cal" / "profiles" / "paper.toml")
                                     .read_bytes())
    return d


def _settings(d: Path, **keys: str) -> Path:
    values = {"station_id": '"L3"', "limits": '"limits.toml"', "db": '"records.sqlite"', "key_file": '"ecu.key"',
              "report_dir": '"reports"', "spool_dir": '"spool"', **keys}
    path = d / "station.toml"
    path.write_text("".join(f"{k} = {v}\n" for k, v in values.items())
                    + '[dyno]\naddress = "127.0.0.1:1"\n[can]\ninterface = "virtual"\nchannel = "nobody"\n')
    return path


@pytest.mark.parametrize("victim", ["block.bin", "ecu.key", "can.ini", "motor.toml"])
def test_flash_log_file_over_any_input_is_refused(station_dir, victim):
    d = station_dir
    before = _digests(d)
    res = CliRunner().invoke(cli, ["flash", str(d / "block.bin"), "--can-config", str(d / "can.ini"),
                                   "--key-file", str(d / "ecu.key"), "--motor", str(d / "motor.toml"),
                                   "--log-file", str(d / victim)])
    _refused(res, str(d / victim), "output is also an input")
    assert _digests(d) == before


def test_acquire_log_file_over_its_profile_or_its_capture_is_refused(station_dir):
    d = station_dir
    before = _digests(d)
    res = CliRunner().invoke(cli, ["acquire", "--dyno", "127.0.0.1:1", "--profile", str(d / "profile.toml"),
                                   "-o", str(d / "cap.mf4"), "--log-file", str(d / "profile.toml")])
    _refused(res, "profile.toml", "output is also an input")
    res = CliRunner().invoke(cli, ["acquire", "--dyno", "127.0.0.1:1", "-o", str(d / "cap.mf4"),
                                   "--log-file", str(d / "cap.mf4")])
    _refused(res, "cap.mf4", "two outputs")
    assert _digests(d) == before and not (d / "cap.mf4").exists()


@pytest.mark.parametrize("victim", ["station.toml", "limits.toml", "ecu.key"])
def test_run_log_file_over_a_file_the_settings_name_is_refused(station_dir, victim):
    d = station_dir
    path = _settings(d)
    before = _digests(d)
    res = CliRunner().invoke(cli, ["run", "--station", str(path), "--serial", "M-1", "--log-file", str(d / victim)],
                             env=_env())
    _refused(res, victim, "output is also an input")
    assert _digests(d) == before and not (d / "reports").exists()


@pytest.mark.parametrize("keys, words", [
    ({"db": '"ecu.key"'}, ["ecu.key", "output is also an input"]),
    ({"db": '"limits.toml"'}, ["limits.toml", "output is also an input"]),
    ({"db": '"station.toml"'}, ["station.toml", "output is also an input"]),
    ({"report_dir": '"limits.toml"'}, ["limits.toml", "not a directory"]),
])
def test_a_settings_output_over_a_settings_input_is_refused(station_dir, keys, words):
    d = station_dir
    path = _settings(d, **keys)
    before = _digests(d)
    for args in (["run", "--station", str(path), "--serial", "M-1"], ["station", "--station", str(path), "--operator", "bob"]):
        res = CliRunner().invoke(cli, args, env=_env(), input="q\n")
        _refused(res, *words)
        assert _digests(d) == before


def test_station_lot_page_over_the_settings_database_is_refused_and_the_records_kept(station_dir):
    from eol_cal.records.record import RunRecord
    from eol_cal.records.write import insert_records
    from eol_cal.records.query import query_records

    d = station_dir
    path = _settings(d)
    insert_records(d / "records.sqlite", [RunRecord.from_json(json.loads((FIXTURES / "run_record_demo.json").read_text()))])
    before = _digests(d)
    for lot in (d / "records.sqlite", d / "limits.toml", d / "station.toml"):
        res = CliRunner().invoke(cli, ["station", "--station", str(path), "--operator", "bob", "--lot", str(lot)],
                                 env=_env(), input="q\n")
        _refused(res, str(lot))
    assert _digests(d) == before
    assert len(query_records(d / "records.sqlite")) == 1
    # the same through the database option and a link to it
    (d / "link.sqlite").symlink_to(d / "records.sqlite")
    res = CliRunner().invoke(cli, ["station", "--station", str(path), "--operator", "bob", "--db", str(d / "link.sqlite"),
                                   "--lot", str(d / "records.sqlite")], env=_env(), input="q\n")
    _refused(res, "records database")


def test_an_output_named_at_run_time_over_an_input_is_refused(tmp_path):
    """``simulate --motors --out-dir`` names its captures itself: one of them is the block it reads."""
    d = tmp_path / "lot"
    d.mkdir()
    victim = d / "SIM-000001.csv"
    victim.write_bytes(example_block(serial="SIM-000001"))
    before = victim.read_bytes()
    res = CliRunner().invoke(cli, ["simulate", "--motors", "2", "--out-dir", str(d), "--format", "csv", "--block",
                                   str(victim), "--mode", "compensated", "--seconds", "0.2", "--speed-rpm", "60",
                                   "--iq", "10", "--seed", "1"])
    _refused(res, str(victim), "output is also an input")
    assert victim.read_bytes() == before


def test_the_run_time_guard_knows_the_file_by_every_name(tmp_path):
    src = tmp_path / "in.bin"
    src.write_bytes(b"input")
    (tmp_path / "hard.bin").hardlink_to(src)
    (tmp_path / "soft.bin").symlink_to(src)
    with command_inputs():
        read_bytes(src)
        for name in ("in.bin", "hard.bin", "soft.bin", "./in.bin"):
            with pytest.raises(InputError, match="also an input"):
                atomic_write(tmp_path / name, b"output")
        atomic_write(tmp_path / "new.bin", b"output")  # a new file is written
    atomic_write(tmp_path / "in.bin", b"again")  # outside a command: the library's caller decides
    assert src.read_bytes() == b"again"
