"""An OEM's seed-to-key function cannot decide the exit code or the ECU's fate (issue 36, class 6).

It runs in a child process (eol_cal.ecu.keychild): whatever it does, when loaded or on the ECU's
real seed (exits, raises BaseException, returns text, an empty or a 200 MB key, prints), the
command refuses with exit 2 naming the algorithm, and the ECU's banks are as before. Real parts:
the ECU simulator on a python-can virtual bus, the plug-in a module on the path.
"""

from __future__ import annotations

import os
import sys

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.ecu.keyalgo import SEED_TRIAL, oem_seed_to_key
from eol_cal.ecu.sim_ecu import SimConfig
from eol_cal.errors import InputError

from eol_cal.sim.virtual_rig import example_block, virtual_rig

# each function answers the trial seed the tool tries when it loads it like the contract's HMAC would,
# and misbehaves on the ECU's real seed: what only the flash itself meets
PLUGIN = f'''
import hashlib, hmac, os, sys
TRIAL = {SEED_TRIAL!r}
SECRET = bytes(range(16))

def good(seed, secret):
    return hmac.new(secret or SECRET, seed, hashlib.sha256).digest()[:4]

def _trial(seed):
    return seed == TRIAL

def exits_1(seed, secret):
    return good(seed, secret) if _trial(seed) else sys.exit(1)

def exits_0(seed, secret):
    return good(seed, secret) if _trial(seed) else sys.exit(0)

def base_exception(seed, secret):
    if _trial(seed):
        return good(seed, secret)
    raise BaseException("not an Exception")

def keyboard_interrupt(seed, secret):
    if _trial(seed):
        return good(seed, secret)
    raise KeyboardInterrupt

def hard_exit(seed, secret):
    return good(seed, secret) if _trial(seed) else os._exit(7)

def empty(seed, secret):
    return good(seed, secret) if _trial(seed) else b""

def huge(seed, secret):
    return good(seed, secret) if _trial(seed) else b"k" * 200_000_000

def text(seed, secret):
    return good(seed, secret) if _trial(seed) else "0102"

def prints_then_keys(seed, secret):
    print('["key", "00000000"]')
    return good(seed, secret)
'''

MISBEHAVING = {"exits_1": "SystemExit: 1", "exits_0": "SystemExit: 0", "base_exception": "BaseException",
               "keyboard_interrupt": "KeyboardInterrupt", "hard_exit": "exit code 7", "empty": "0 bytes",
               "huge": "200000000 bytes", "text": "returned str"}


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    site = tmp_path / "site"
    site.mkdir()
    (site / "oem_hostile_key.py").write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(site), *sys.path]))
    yield site
    sys.modules.pop("oem_hostile_key", None)


@pytest.mark.parametrize("func, words", sorted(MISBEHAVING.items()))
def test_flash_refuses_with_exit_2_and_writes_nothing(plugin, tmp_path, func, words):
    block = tmp_path / "b.bin"
    block.write_bytes(example_block(seed=3))
    with virtual_rig(tmp_path / "f.bin", config=SimConfig()) as rig:
        before = (rig.sim.active.sequence, tmp_path.joinpath("f.bin").read_bytes())
        res = CliRunner().invoke(cli, ["flash", str(block), "-i", "virtual", "-c", rig.channel,
                                       "--key-algo", f"oem_hostile_key:{func}"])
        after = (rig.sim.active.sequence, tmp_path.joinpath("f.bin").read_bytes())
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith("error:") and "oem_hostile_key" in line and words in line, res.output
    assert after == before  # nothing erased, nothing flashed


def test_what_it_prints_is_not_read_as_a_key(plugin):
    algo = oem_seed_to_key("oem_hostile_key:prints_then_keys", None)
    import hashlib
    import hmac

    assert algo(b"\x01\x02\x03\x04") == hmac.new(bytes(range(16)), b"\x01\x02\x03\x04", hashlib.sha256).digest()[:4]


def test_an_import_that_exits_is_a_refusal(tmp_path, monkeypatch):
    (tmp_path / "oem_exits_on_import.py").write_text("import sys\nsys.exit(3)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(InputError) as err:
        oem_seed_to_key("oem_exits_on_import:key", None)
    assert "cannot load" in str(err.value) and "SystemExit: 3" in str(err.value)
