"""XLA's CPU pool of one thread unless the user asks for more (eol_cal/numerics/xla.py, start_xla)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest

from eol_cal.errors import InputError
from eol_cal.numerics.xla import THREADS_ENV, xla_threads

# XLA names its CPU pool's threads "tf_XLAEigen" (the kernel's comm of each)
PROBE = (
    "import json, os, sys\n"
    "from eol_cal.numerics.xla import start_xla\n"
    "first = start_xla()\n"
    "again = start_xla()\n"
    "import jax.numpy as jnp\n"
    "float(jnp.arange(1000.0).sum())\n"
    "pool, masks = 0, set()\n"
    "for tid in os.listdir('/proc/self/task'):\n"
    "    pool += open(f'/proc/self/task/{tid}/comm').read().startswith('tf_XLAEigen')\n"
    "    masks.add(tuple(sorted(os.sched_getaffinity(int(tid)))))\n"
    "print(json.dumps({'first': first, 'again': again, 'pool': pool, 'masks': sorted(masks),\n"
    "                  'cpus': sorted(os.sched_getaffinity(0))}))\n"
)


def _probe(**env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if k != THREADS_ENV}
    out = subprocess.run([sys.executable, "-c", PROBE], env={**clean, **env}, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_one_pool_thread_by_default_and_every_thread_on_every_core():
    got = _probe()
    if len(got["cpus"]) == 1:  # nothing to narrow: XLA's own pool is one thread already
        assert got["first"] is False and got["pool"] == 1
        return
    assert got["first"] is True
    assert got["again"] is False  # the backend had started: nothing changes
    assert got["pool"] == 1
    # the pool's thread and the caller got the process's cores back: no thread is pinned
    assert got["masks"] == [got["cpus"]]


def test_all_leaves_xla_its_own_pool():
    got = _probe(**{THREADS_ENV: "all"})
    assert got["first"] is False
    assert got["pool"] == len(got["cpus"])


@pytest.mark.parametrize("text", ["0", "-1", "two", "1.5"])
def test_a_bad_count_names_the_variable(text):
    with pytest.raises(InputError, match=re.escape(f"field '${THREADS_ENV}': '{text}' is not")):
        xla_threads({THREADS_ENV: text})


def test_counts_read_from_the_variable():
    assert xla_threads({}) == 1
    assert xla_threads({THREADS_ENV: " 3 "}) == 3
    assert xla_threads({THREADS_ENV: "all"}) is None
