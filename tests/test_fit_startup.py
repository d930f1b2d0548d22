"""``eol-cal fit`` without a wait (issue 37 item 3): nothing on its path imports scipy's heavy
submodules, and the caches that keep its traced solver and compiled programs between runs never
break a fit when an entry is torn."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from eol_cal.capture.io import write_capture
from eol_cal.capture.synthetic import synthetic_capture

pytestmark = pytest.mark.slow  # processes of their own

_PROBE = """
import runpy, sys
sys.argv = ["eol-cal", *sys.argv[1:]]
try:
    runpy.run_module("cli.main", run_name="__main__")
except SystemExit:
    pass
print(*sorted(m for m in sys.modules if m.startswith("scipy.")), file=sys.stderr)
"""


def test_eol_cal_fit_imports_neither_scipy_signal_nor_stats_interpolate_ndimage(tmp_path):
    path = tmp_path / "one.csv"
    write_capture(synthetic_capture(rpm=600.0, i_qo=65.0, seconds=0.3, seed=1, serial="B-1"), path)
    res = subprocess.run([sys.executable, "-c", _PROBE, "fit", str(path), "-o", str(tmp_path / "r.json"), "--no-c6",
                          "--delay", "0"], capture_output=True, text=True, timeout=600,
                         env=dict(os.environ, EOL_CAL_JAX_CACHE=str(tmp_path / "cache")))
    assert (tmp_path / "r.json").exists(), res.stderr[-3000:]
    mods = set(res.stderr.strip().splitlines()[-1].split())
    assert "scipy.special" in mods  # the probe sees scipy's modules
    assert {m.split(".")[1] for m in mods} & {"signal", "stats", "interpolate", "ndimage", "optimize"} == set()


def _fit(path, out, cache):
    return subprocess.run([sys.executable, "-m", "cli.main", "fit", str(path), "-o", str(out), "--no-c6", "--delay", "0",
                           "--bench", "none"], capture_output=True, text=True, timeout=600,
                          env=dict(os.environ, EOL_CAL_JAX_CACHE=str(cache)))


def test_a_torn_cache_entry_costs_only_the_time(tmp_path):
    """Every file of a filled cache (JAX's compiled programs and the serialized solver) overwritten
    with garbage: the next `eol-cal fit` succeeds with the same result, as does one with the cache off."""
    path = tmp_path / "one.csv"
    write_capture(synthetic_capture(rpm=600.0, i_qo=65.0, seconds=0.3, seed=1, serial="B-1"), path)
    cache = tmp_path / "cache"
    first = _fit(path, tmp_path / "a.json", cache)
    assert first.returncode == 0, first.stderr[-3000:]
    entries = [p for p in cache.rglob("*") if p.is_file()]
    assert entries  # the first run filled it
    for p in entries:
        p.write_bytes(b"\x00torn" * 64)
    again = _fit(path, tmp_path / "b.json", cache)
    assert again.returncode == 0, again.stderr[-3000:]
    off = _fit(path, tmp_path / "c.json", "off")
    assert off.returncode == 0, off.stderr[-3000:]
    motors = [json.loads((tmp_path / f"{n}.json").read_text())["motors"] for n in "abc"]
    assert motors[0] == motors[1] == motors[2]
