"""The OEM's seed-to-key algorithm (issue 23, class 9): named one way (an entry point of group
``eol_cal.seed_to_key`` or ``MODULE:FUNC``) by ``flash``, ``ecu restore``, ``run``, ``station``
and the station settings' ``key_algo``; a wrong one refused before the dyno moves.

Real parts: an installed plug-in (a distribution with an entry point, found by
``importlib.metadata`` on the path), the ECU simulator on a python-can virtual bus or over
python-can-remote, the loopback station (dyno simulator on 127.0.0.1), SQLite.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.ecu import protocol as P
from eol_cal.ecu.keyalgo import ENTRY_POINT_GROUP, oem_seed_to_key, seed_to_key_from
from eol_cal.ecu.sim_ecu import SimConfig
from eol_cal.errors import InputError
from eol_cal.sim.loopback import loopback_station

from eol_cal.sim.virtual_rig import example_block, virtual_rig

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"

# the OEM's algorithm, as its plug-in ships it: the contract's HMAC with a secret built in (no key file)
PLUGIN = f'''
import hashlib, hmac
SECRET = bytes.fromhex("{P.DEV_SECRET.hex()}")

def key(seed, secret):
    return hmac.new(secret or SECRET, seed, hashlib.sha256).digest()[:4]

def broken(seed, secret):
    raise RuntimeError("dongle not found")

def text(seed, secret):
    return "not bytes"
'''


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    """A distribution ``oem-eps`` with entry points ``oem-eps``, ``oem-broken`` in the group,
    importable from ``tmp_path/site`` (in this process and in children through PYTHONPATH)."""
    site = tmp_path / "site"
    (site / "oem_eps_key.py").parent.mkdir(parents=True)
    (site / "oem_eps_key.py").write_text(PLUGIN)
    dist = site / "oem_eps-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: oem-eps\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\noem-eps = oem_eps_key:key\n"
                                           "oem-broken = oem_eps_key:broken\n")
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(site), *sys.path]))
    yield site
    sys.modules.pop("oem_eps_key", None)


def test_both_ways_of_naming_it_give_the_same_key(plugin):
    seed = bytes.fromhex("a1b2c3d4")
    want = P.security_key(P.DEV_SECRET, seed)
    assert oem_seed_to_key("oem-eps", None)(seed) == want
    assert oem_seed_to_key("oem_eps_key:key", None)(seed) == want
    assert seed_to_key_from(None, "oem-eps")(seed) == want


@pytest.mark.parametrize("spec, words", [
    ("oem-missing", ["no entry point", "oem-eps"]),
    ("oem-broken", ["dongle not found"]),
    ("oem_eps_key:text", ["returned str"]),
    ("oem_eps_key:nothing", ["no function"]),
    ("no_such_module_xyz:f", ["cannot load"]),
    (":f", ["MODULE:FUNC"]),
])
def test_a_wrong_algorithm_is_refused_when_loaded(plugin, spec, words):
    with pytest.raises(InputError) as err:
        oem_seed_to_key(spec, None)
    for w in words:
        assert w in str(err.value)


@pytest.mark.parametrize("spec", ["oem-eps", "oem_eps_key:key"])
def test_flash_and_ecu_restore_take_it_without_a_key_file(plugin, tmp_path, spec):
    a, b = tmp_path / "a.bin", tmp_path / "b.bin"
    a.write_bytes(example_block(seed=1))
    b.write_bytes(example_block(seed=2))
    with virtual_rig(tmp_path / "f.bin", config=SimConfig()) as rig:
        bus = ["-i", "virtual", "-c", rig.channel]
        for block in (a, b):
            res = CliRunner().invoke(cli, ["flash", str(block), *bus, "--key-algo", spec])
            assert res.exit_code == 0, res.output
        res = CliRunner().invoke(cli, ["ecu", "restore", "--bank", "previous", *bus, "--key-algo", spec,
                                       "--save", str(tmp_path / "saved.bin")])
        assert res.exit_code == 0, res.output
        assert rig.sim.active.sequence == 3


def _env() -> dict[str, str | None]:
    return {k: None for k in os.environ if k.startswith("EOL_CAL_") and k != "EOL_CAL_JAX_CACHE"}


def _settings(d: Path, dyno: str, channel: str, key_lines: str) -> Path:
    (d / "limits.toml").write_bytes((FIXTURES / "limits.toml").read_bytes())
    path = d / "station.toml"
    path.write_text(f'station_id = "L3"\nlimits = "limits.toml"\ndb = "records.sqlite"\nreport_dir = "reports"\n'
                    # the analytic source's torque path is a rigid coupling: the bench file that is its own
                    f'spool_dir = "spool"\nbench = "none"\n{key_lines}\n[dyno]\naddress = "{dyno}"\n[can]\ninterface = "remote"\n'
                    f'channel = "{channel}"\n')
    return path


@pytest.mark.slow  # a whole cycle per case: 15-21 s
@pytest.mark.parametrize("how", ["option", "settings"])
def test_run_goes_through_the_cycle_with_the_oem_algorithm(plugin, tmp_path, how):
    with loopback_station("K-7", 7, tmp_path / "sim", source=synthetic_source) as st:
        key_line = 'key_algo = "oem-eps"' if how == "settings" else ""
        path = _settings(tmp_path, st.dyno_address, st.can_channel, key_line)
        extra = ["--key-algo", "oem-eps"] if how == "option" else []
        res = CliRunner().invoke(cli, ["run", "--station", str(path), "--serial", "K-7", "--json", *extra], env=_env())
    assert res.exit_code in (0, 1), res.output  # pass or fail by the limits: the cycle ran through the flash
    rec = json.loads(res.stdout)["record"]
    assert rec["error"] is None and "calibrated" in {b["role"] for b in rec["blocks"]}, rec.get("error")


@pytest.mark.slow  # a station cycle: 14 s
def test_station_takes_it_from_its_settings(plugin, tmp_path):
    with loopback_station("K-8", 8, tmp_path / "sim", source=synthetic_source) as st:
        path = _settings(tmp_path, st.dyno_address, st.can_channel, 'key_algo = "oem-eps"')
        res = CliRunner().invoke(cli, ["station", "--station", str(path), "--operator", "bob"], env=_env(),
                                 input="K-8\nq\n")
    assert res.exit_code == 0, res.output
    assert "K-8: PASS" in res.output or "K-8: FAIL" in res.output, res.output


@pytest.mark.parametrize("command", ["run", "station"])
@pytest.mark.parametrize("spec, words", [("oem-missing", "no entry point"), ("oem-broken", "dongle not found"),
                                         ("oem_eps_key:text", "returned str")])
def test_a_wrong_algorithm_stops_run_and_station_before_the_dyno_moves(plugin, tmp_path, command, spec, words):
    path = _settings(tmp_path, "127.0.0.1:1", "ws://127.0.0.1:1/", f'key_algo = "{spec}"')
    args = ["run", "--station", str(path), "--serial", "K-1"] if command == "run" else \
        ["station", "--station", str(path), "--operator", "bob"]
    res = CliRunner().invoke(cli, args, env=_env(), input="K-1\nq\n")
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    line = res.stderr.strip().splitlines()[-1]
    assert str(path) in line and "key_algo" in line and words in line, res.output
    assert not (tmp_path / "records.sqlite").exists() and not (tmp_path / "reports").exists()


def test_run_without_key_file_or_algorithm_is_refused(tmp_path):
    path = _settings(tmp_path, "127.0.0.1:1", "ws://127.0.0.1:1/", "")
    res = CliRunner().invoke(cli, ["run", "--station", str(path), "--serial", "K-1"], env=_env())
    assert res.exit_code == 2 and "key_file" in res.output and "key_algo" in res.output, res.output
