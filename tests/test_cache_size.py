"""The cache directory held to a size (eol_cal.numerics.cache_size): past its bound the least
recently used kept programs and executables go first, with their lock files, down to a fraction of
it; a program read back counts as used; links, folders and other files are never touched; JAX's own
cache gets a bound unless the user set one."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from eol_cal.numerics import cache_size, exported


def _file(path, size: int, age_s: float):
    path.write_bytes(b"x" * size)
    t = 1_700_000_000 - age_s
    os.utime(path, (t, t))
    return path


def test_the_least_recently_used_go_first_down_to_a_fraction_of_the_bound(tmp_path):
    old = [_file(tmp_path / f"fit-{i}.xlaexec", 100, 1000 - i) for i in range(6)]  # old[0] the oldest
    new = _file(tmp_path / "est-scan-a.jaxexport", 100, 1)
    locks = [_file(tmp_path / f"fit-{i}.lock", 0, 5000) for i in range(6)]
    other = _file(tmp_path / "jit_f-abc-cache", 10_000, 9999)  # JAX's entry: JAX's own bound, not this one
    outside = _file(tmp_path.parent / "big.xlaexec", 10_000, 9999)
    (tmp_path / "link.xlaexec").symlink_to(outside)
    (tmp_path / "dir.jaxexport").mkdir()
    assert cache_size.prune(tmp_path, max_bytes=700) == []  # 700 bytes kept: within the bound
    removed = cache_size.prune(tmp_path, max_bytes=600)
    # 700 > 600: the oldest go until at most 0.75 x 600 = 450 bytes are left
    assert removed == old[:3]
    assert [p.exists() for p in old] == [False] * 3 + [True] * 3 and new.exists()
    assert [p.exists() for p in locks] == [False] * 3 + [True] * 3  # each removed file's lock with it
    assert other.exists() and outside.exists() and (tmp_path / "link.xlaexec").is_symlink()
    assert (tmp_path / "dir.jaxexport").is_dir()


def test_the_file_just_written_stays_and_a_missing_directory_is_no_error(tmp_path):
    a = _file(tmp_path / "a.jaxexport", 500, 10)
    b = _file(tmp_path / "b.jaxexport", 500, 100)
    assert cache_size.prune(tmp_path, max_bytes=100, keep=b) == [a]
    assert b.exists()
    assert cache_size.prune(tmp_path / "missing", max_bytes=1) == []


def test_a_program_read_back_counts_as_used_and_outlives_one_that_was_not(tmp_path, monkeypatch):
    pytest.importorskip("jax")
    import jax
    import jax.numpy as jnp

    # constants of this run's own: JAX's compilation cache (the suite's, kept between runs) cannot answer
    # the compiles, whose executables are then written (only a fresh compile is: exported.executable)
    c = [float(x) for x in np.random.default_rng().uniform(1.0, 2.0, 4)]
    prev = exported.cache_dir()
    exported.set_cache_dir(tmp_path)
    try:
        args = (np.arange(4, dtype=np.float32),)
        for i in range(3):  # three programs, each traced, exported and compiled: entry and executable
            exported.kept(f"p{i}", "t-size-1", i, lambda i=i: jax.jit(lambda x: jnp.sin(x) * c[i]), args)
        files = {p.name: p for p in tmp_path.iterdir() if p.suffix in cache_size.KEPT_SUFFIXES}
        assert len(files) == 6
        for p in files.values():  # all written long ago, the first program's the longest
            t = 1_700_000_000 - (1000 if p.name.startswith("p0-") else 500)
            os.utime(p, (t, t))
        exported._KEPT.clear()  # as a new process: read from the directory
        got = exported.kept("p0", "t-size-1", 0, lambda: pytest.fail("p0 was traced again"), args)
        np.testing.assert_allclose(np.asarray(got(*args)), np.sin(args[0]) * np.float32(c[0]), rtol=1e-6)
        # a fourth program written into a directory held to about three programs' files
        monkeypatch.setattr(cache_size, "MAX_KEPT_BYTES", int(sum(p.stat().st_size for p in files.values()) * 0.9))
        exported.kept("p3", "t-size-1", 3, lambda: jax.jit(lambda x: jnp.cos(x) * c[3]), args)
        left = {p.name.split("-")[0] for p in tmp_path.iterdir() if p.suffix in cache_size.KEPT_SUFFIXES}
        assert "p0" in left and "p3" in left  # p0 was read back (used), p1 and p2 were not
        assert not {"p1", "p2"} <= left
    finally:
        exported.set_cache_dir(prev)
        exported._KEPT.clear()


@pytest.mark.slow  # processes of their own, each importing JAX (CONTRIBUTING.md, "Fast or slow")
def test_jax_cache_gets_a_bound_unless_the_user_set_one_and_an_unbounded_cache_stays_writable(tmp_path):
    # a cache JAX filled without a bound: entries without use times, which its eviction reads
    (tmp_path / "jit_old-0123-cache").write_bytes(b"an entry of an earlier run")
    script = ("import sys, jax, jax.numpy as jnp\nfrom eol_cal.analysis.fit.cache import enable_compile_cache\n"
              "enable_compile_cache(sys.argv[1])\n"
              "jax.block_until_ready(jax.jit(lambda x: jnp.sin(x) * float(sys.argv[2]))(jnp.ones(3)))\n"
              "print(jax.config.jax_compilation_cache_max_size)\n")
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_MAX_SIZE"}

    def run(c: float) -> tuple[int, str]:
        done = subprocess.run([sys.executable, "-W", "always", "-c", script, str(tmp_path), str(c)], env=env,
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        return int(done.stdout.split()[-1]), done.stderr

    bound, err = run(1.5)
    assert bound == cache_size.MAX_JAX_CACHE_BYTES
    assert "Error writing persistent compilation cache entry" not in err, err[-2000:]
    assert (tmp_path / "jit_old-0123-atime").is_file()  # given its file's time as its use time
    assert any(p.name.startswith("jit__lambda-") and p.name.endswith("-cache") for p in tmp_path.iterdir())
    env["JAX_COMPILATION_CACHE_MAX_SIZE"] = "-1"  # the user's own setting (JAX's variable): no bound
    assert run(2.5)[0] == -1
