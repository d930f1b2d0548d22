"""Threads that ask for the same program at once share one: a what-if batch's motor threads each
traced and compiled their own plant prime before (three compiles of ~0.7 CPU s where one would do,
each slower beside the others; 2026-12-02). One jitted function compiles once however many threads
call it first (JAX waits); two jitted functions of the same program compile twice."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from eol_cal.analysis.fit import solver
from eol_cal.plant import simulate as S

THREADS = 3


def _at_once(ask: Callable[[], object]) -> list[object]:
    got: list[object] = []
    start = threading.Barrier(THREADS)

    def one() -> None:
        start.wait()
        got.append(ask())

    threads = [threading.Thread(target=one) for _ in range(THREADS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return got


@pytest.mark.parametrize("which", ["prime", "chunk"])
def test_threads_asking_for_one_plant_program_at_once_build_it_once(monkeypatch, which):
    built = []

    def slow_build(*key):
        built.append(key)
        time.sleep(0.2)  # a trace's time: the other threads ask while the first builds
        return object()

    monkeypatch.setattr(S, "_COMPILED", {})
    if which == "prime":
        monkeypatch.setattr(S, "_build_prime", slow_build)
        got = _at_once(lambda: S._prime_fn("cfg", "p_pack", "i_pack"))
    else:
        monkeypatch.setattr(S, "_build_chunk", slow_build)
        got = _at_once(lambda: S._chunk_fn("cfg", 4000, 1, "p_pack", "c_pack"))
    assert len(built) == 1
    assert len(got) == THREADS and all(g is got[0] for g in got)


def test_threads_asking_for_one_fit_solver_at_once_get_one_jitted_function(monkeypatch):
    def slow_build(spec, S_):
        time.sleep(0.2)
        return lambda comp, grid, steps: comp

    monkeypatch.setattr(solver, "_SOLVERS", {})
    monkeypatch.setattr(solver, "build_solver", slow_build)
    got = _at_once(lambda: solver.cached_solver("spec", 6, "one"))
    assert len(got) == THREADS and all(g is got[0] for g in got)
