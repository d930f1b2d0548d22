"""Records at plant scale: concurrent writers into PostgreSQL and SQLite, and `lot stats` over a
large lot in PostgreSQL, two ways.

    python bench/bench_records.py [--pg-url postgresql://USER@127.0.0.1:PORT/DB] [--writers 4 --per-writer 500]
        [--stats-records 100000] [--repeat 3] [--repeat-records 1]

Without --pg-url the bench starts its own PostgreSQL server with eol_cal/sim/postgres.py (the
machine's server binaries, a temporary directory, 127.0.0.1 on a free port, fsync off) and stops
it at the end. The records are realistic: the real record of an `eol-cal demo` motor
(fixtures/run_record_demo.json, about 9 kB of record JSON plus its 6 kB fit as stored) with
values, verdicts, stations and times varied per run, 3 % of the runs refusals (eol_cal/sim/lot_records.py).

Each writer is a process that writes its records one transaction each (as stations do), through
`eol_cal.records.write.insert_records`; afterwards the count and the set of run ids are
compared with what was sent (zero lost, zero duplicated). `lot stats` is timed end to end on a
table of --stats-records runs, on the same table both ways:

- columns: what `eol-cal lot stats` does (`read_lots`: the columns it needs of the production
  runs and of the refusals, the kinds filtered in SQL, no record JSON; `lot_summary`);
- records: the alternative, reading and parsing every run's record JSON (streamed, as
  `query_records` parses it, into RunRecord), then the same statistics.

The two documents are compared (they must be equal).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import functools
import os
import statistics
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any
from collections.abc import Callable

import sqlalchemy as sa

from eol_cal.sim.lot_records import lot_record


def _writer(args: tuple) -> list[str]:
    import dataclasses

    from eol_cal.records.write import insert_records

    db, w, n = args
    ids = []
    for i in range(n):
        r = lot_record(i, n)
        r = dataclasses.replace(r, serial=f"W{w}-{i:05d}", station=dataclasses.replace(r.station, id=f"EOL-{w}"))
        insert_records(db, [r], timeout_s=30.0)
        ids.append(r.run_id)
    return ids


def concurrent(db, writers: int, per: int) -> tuple[float, int, int, int]:
    from eol_cal.records.migrations import migrate
    from eol_cal.records.query import query_records

    migrate(db)
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(writers) as pool:
        sent = [i for ids in pool.map(_writer, [(db, w, per) for w in range(writers)]) for i in ids]
    dt = time.perf_counter() - t0
    got = [r.run_id for r in query_records(db)]
    lost = len(set(sent) - set(got))
    dup = len(got) - len(set(got))
    return len(sent) / dt, len(got), lost, dup


def fill(db, n: int, batch: int = 2000) -> tuple[float, float, int]:
    """Insert a lot of ``n`` realistic runs (95 % as many motors: the rest are re-tests; 3 %
    refusals); returns (seconds, mean bytes of record_json + fit_json per row, production runs)."""
    from eol_cal.records.connect import engine
    from eol_cal.records.rows import row_of
    from eol_cal.records.tables import runs
    from eol_cal.records.write import insert_records

    insert_records(db, [])
    eng = engine(db)
    t0 = time.perf_counter()
    size = production = 0
    with eng.begin() as con:
        for k in range(0, n, batch):
            recs = [lot_record(k + i, n - n // 20, refusals=True) for i in range(min(batch, n - k))]
            production += sum(r.kind == "production" for r in recs)
            rows = [row_of(r) for r in recs]
            size += sum(len(r["record_json"]) + len(r["fit_json"] or "") for r in rows)
            con.execute(runs.insert(), rows)
    return time.perf_counter() - t0, size / max(1, n), production


def by_columns(db, variant: str | None) -> dict[str, Any]:
    """`eol-cal lot stats`: the columns of the production runs and the refusals, no record JSON."""
    from eol_cal.lot.runs import read_lots
    from eol_cal.lot.summary import lot_summary

    return lot_summary(*read_lots(db, variant=variant, also=("refusal",)))


def by_records(db, variant: str | None) -> dict[str, Any]:
    """The alternative: read and parse every run's record JSON, then the same statistics."""
    from eol_cal.lot.runs import from_records
    from eol_cal.lot.summary import lot_summary
    from eol_cal.records.connect import engine
    from eol_cal.records.rows import parse_record
    from eol_cal.records.tables import runs
    from eol_cal.records.query import select_runs

    q = select_runs(variant=variant).with_only_columns(runs.c.run_id, runs.c.record_json)
    recs = []
    with engine(db, readonly=True).connect() as con:
        for run_id, text in con.execution_options(yield_per=2000).execute(q):
            recs.append(parse_record(db, run_id, text))
    return lot_summary(from_records([r for r in recs if r.kind == "production"]),
                       from_records([r for r in recs if r.kind == "refusal"]))


def timed(fn: Callable[[], dict[str, Any]], repeat: int) -> tuple[list[float], dict[str, Any]]:
    times, doc = [], {}
    for _ in range(repeat):
        t0 = time.perf_counter()
        doc = fn()
        times.append(time.perf_counter() - t0)
    return times, doc


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pg-url", default=None, help="an EMPTY PostgreSQL server database's admin URL "
                    "(default: start a server of its own with eol_cal/sim/postgres.py)")
    ap.add_argument("--writers", type=int, default=4, help="writer processes (0: no writers section)")
    ap.add_argument("--per-writer", type=int, default=500)
    ap.add_argument("--stats-records", type=int, default=100_000)
    ap.add_argument("--repeat", type=int, default=3, help="timings of `lot stats` by columns")
    ap.add_argument("--repeat-records", type=int, default=1, help="timings of the path that parses every record")
    a = ap.parse_args()
    server = None
    if a.pg_url is None:
        from eol_cal.sim.postgres import PostgresServer

        server = PostgresServer().start()
        a.pg_url = server.url()
    try:
        run(a)
    finally:
        if server is not None:
            server.stop()


def run(a: argparse.Namespace) -> None:
    import psycopg

    def fresh(name: str) -> str:
        with psycopg.connect(a.pg_url, autocommit=True) as con:
            con.execute(f'CREATE DATABASE "{name}"')
        return sa.engine.make_url(a.pg_url).set(database=name).render_as_string(hide_password=False)

    tag = uuid.uuid4().hex[:8]
    print(f"load average {_load()} on {os.cpu_count()} cores")
    if a.writers > 0:
        print(f"{a.writers} writers x {a.per_writer} records, one transaction each")
        print(f"{'backend':<12}{'records/s':>12}{'rows':>8}{'lost':>6}{'dup':>6}")
        with tempfile.TemporaryDirectory() as d:
            for name, db in (("postgresql", fresh(f"w{tag}")), ("sqlite", Path(d) / "r.sqlite")):
                rate, rows, lost, dup = concurrent(db, a.writers, a.per_writer)
                print(f"{name:<12}{rate:>12.0f}{rows:>8}{lost:>6}{dup:>6}")
    db = fresh(f"s{tag}")
    n = a.stats_records
    seconds, size, production = fill(db, n)
    print(f"{n} runs ({production} production, the rest refusals) inserted in {seconds:.1f} s, "
          f"{size / 1e3:.1f} kB of record + fit JSON per run")
    print(f"lot stats over {n} records in PostgreSQL (query + statistics; load average {_load()}):")
    docs = {}
    for name, fn, repeat in (("columns", by_columns, a.repeat), ("records", by_records, a.repeat_records)):
        if repeat < 1:
            continue
        times, docs[name] = timed(functools.partial(fn, db, "EPS-STD"), repeat)
        if docs[name]["runs"] != production or docs[name]["refusals"]["runs"] != n - production:
            raise SystemExit(f"{name}: {docs[name]['runs']} runs, expected {production}")
        print(f"  {name:<8} median {statistics.median(times):6.2f} s, best {min(times):6.2f} s  "
              f"({', '.join(f'{t:.2f}' for t in times)}; load average {_load()})")
    if len(docs) == 2:
        print("same figures both ways:", docs["columns"] == docs["records"])


if __name__ == "__main__":
    main()
