"""The golden vector file format: one CSV per vector set, floats as binary32 bit patterns.

Shared by the generators (:mod:`eol_cal.firmware.golden`, :mod:`eol_cal.firmware.estimator_golden`)
and the consumers (tests, firmware engineers' scripts).
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from typing import Any
from collections.abc import Callable, Iterable, Sequence

import numpy as np

Rows = list[list[str]]


@dataclasses.dataclass(frozen=True)
class VectorSet:
    """One CSV file: its columns, rows (strings as written), a description, its tolerance, and its
    tolerance classes: ``ulp`` gives a float column the units in the last place a target may differ
    by (its division and square root approximations, measured on the twin); a column not named
    there is exact (the harness checks both, contract section 4, "Floating point")."""

    columns: tuple[str, ...]
    rows: Rows
    description: str = ""
    tolerance: dict[str, Any] | str = "exact"
    ulp: dict[str, int] = dataclasses.field(default_factory=dict)


def scenario_rows_in_parallel(rows_of: Callable[[str], Rows], names: Sequence[str],
                              seconds: Callable[[str], float]) -> dict[str, Rows]:
    """``{name: rows_of(name)}``, the scenarios computed in spawned processes, one a core.

    The tick-by-tick references are independent per scenario and run for seconds each: the
    longest (``seconds``, the scenario's simulated time) are handed out first so both cores end
    together. ``rows_of`` must be a module-level function (it is pickled by name). One core:
    computed here, one after the other.
    """
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    workers = min(cores, len(names))
    try:
        pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) if workers > 1 else None
    except (OSError, NotImplementedError):  # no process semaphores here (a sandbox): the same rows, serially
        pool = None
    if pool is None:
        return {n: rows_of(n) for n in names}
    order = sorted(names, key=seconds, reverse=True)
    with pool:
        done = dict(zip(order, pool.map(rows_of, order), strict=True))
    return {n: done[n] for n in names}


def f32hex(x: float) -> str:
    """Bit pattern of ``x`` rounded to binary32: 8 lower-case hex digits (``1.0 -> 3f800000``)."""
    return f"{int(np.asarray(x, dtype=np.float32).view(np.uint32)):08x}"


def hex_f32(s: str) -> np.float32:
    """Inverse of :func:`f32hex`."""
    return np.array([int(s, 16)], dtype=np.uint32).view(np.float32)[0]


def csv_text(vs: VectorSet) -> str:
    """The CSV file of a set: header row, then one line per row, ``\\n`` line ends, no quoting."""
    lines = [",".join(vs.columns)]
    for r in vs.rows:
        if len(r) != len(vs.columns):
            raise ValueError(f"row {r[:3]}... has {len(r)} fields for {len(vs.columns)} columns")
        if any("," in c or "\n" in c or '"' in c for c in r):
            raise ValueError(f"row {r[:3]}... has a field with a comma, quote or newline")
        lines.append(",".join(r))
    return "\n".join(lines) + "\n"


def iter_rows(text: str) -> Iterable[dict[str, str]]:
    """Rows of a golden CSV as dicts (for consumers and tests)."""
    lines = text.splitlines()
    cols = lines[0].split(",")
    for line in lines[1:]:
        yield dict(zip(cols, line.split(","), strict=True))
