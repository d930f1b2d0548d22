"""Records at plant scale: concurrent writers into PostgreSQL and SQLite, and `lot stats` over a
large lot in PostgreSQL.

    python bench/bench_records.py --pg-url postgresql://USER@127.0.0.1:PORT/DB [--writers 4 --per-writer 500]
        [--stats-records 100000]

Each writer is a process that writes its records one transaction each (as stations do), through
`eol_cal.station.records.insert_records`; afterwards the count and the set of run ids are
compared with what was sent (zero lost, zero duplicated). `lot stats` is timed end to end
(query + statistics) on a table of --stats-records runs.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import tempfile
import time
import uuid
from pathlib import Path

import sqlalchemy as sa


def _record(serial: str, i: int, station: str) -> dict:
    t = f"2026-11-{1 + i % 28:02d}T{i % 24:02d}:{i % 60:02d}:00.000+00:00"
    k6 = 1.0e-3 + 1e-5 * ((i * 7919) % 100)
    return {"schema": "eol-cal/run-record/1", "run_id": uuid.uuid4().hex, "serial": serial, "started_at": t,
            "ended_at": t, "verdict": "pass" if i % 17 else "fail",
            "reasons": [] if i % 17 else ["p-p after = 2.5 % exceeds max_pp_after_pct = 2"],
            "station": {"id": station}, "limits": {"variant": "EPS-STD", "max_k6": 2e-3, "max_pp_after_pct": 2.0,
                                                    "min_improvement_pct": 50.0, "max_pp_before_pct": 40.0},
            "fit": {"k6": {"value": k6}, "phase_k6": {"value": 0.3}, "c6": {"value": 0.004}},
            "metrics": {"pp_before_pct": 10.0 + (i % 5), "pp_after_pct": 0.5 + 0.01 * (i % 50),
                        "improvement_pct": 90.0}}


def _writer(args: tuple) -> list[str]:
    from eol_cal.station.records import insert_records

    db, w, n = args
    ids = []
    for i in range(n):
        r = _record(f"W{w}-{i:05d}", i, f"EOL-{w}")
        insert_records(db, [r], timeout_s=30.0)
        ids.append(r["run_id"])
    return ids


def concurrent(db, writers: int, per: int) -> tuple[float, int, int, int]:
    from eol_cal.station.records import migrate, query_records

    migrate(db)
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(writers) as pool:
        sent = [i for ids in pool.map(_writer, [(db, w, per) for w in range(writers)]) for i in ids]
    dt = time.perf_counter() - t0
    got = [r["run_id"] for r in query_records(db)]
    lost = len(set(sent) - set(got))
    dup = len(got) - len(set(got))
    return len(sent) / dt, len(got), lost, dup


def stats_time(db, n: int) -> float:
    from eol_cal.lot.summary import lot_summary
    from eol_cal.station.records import _row, engine, insert_records, query_rows, runs

    insert_records(db, [])
    eng = engine(db)
    batch = 5000
    with eng.begin() as con:
        for k in range(0, n, batch):
            con.execute(runs.insert(), [_row(_record(f"S{k + i:06d}", k + i, f"EOL-{(k + i) % 6}"))
                                        for i in range(min(batch, n - k))])
    t0 = time.perf_counter()
    rows = query_rows(db, variant="EPS-STD")
    doc = lot_summary([r["record"] for r in rows])
    dt = time.perf_counter() - t0
    assert doc["runs"] == n, doc["runs"]
    return dt


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pg-url", required=True, help="an EMPTY PostgreSQL server database's admin URL")
    ap.add_argument("--writers", type=int, default=4)
    ap.add_argument("--per-writer", type=int, default=500)
    ap.add_argument("--stats-records", type=int, default=100_000)
    a = ap.parse_args()
    import psycopg

    def fresh(name: str) -> str:
        with psycopg.connect(a.pg_url, autocommit=True) as con:
            con.execute(f'CREATE DATABASE "{name}"')
        return sa.engine.make_url(a.pg_url).set(database=name).render_as_string(hide_password=False)

    tag = uuid.uuid4().hex[:8]
    print(f"{a.writers} writers x {a.per_writer} records, one transaction each")
    print(f"{'backend':<12}{'records/s':>12}{'rows':>8}{'lost':>6}{'dup':>6}")
    with tempfile.TemporaryDirectory() as d:
        for name, db in (("postgresql", fresh(f"w{tag}")), ("sqlite", Path(d) / "r.sqlite")):
            rate, rows, lost, dup = concurrent(db, a.writers, a.per_writer)
            print(f"{name:<12}{rate:>12.0f}{rows:>8}{lost:>6}{dup:>6}")
    dt = stats_time(fresh(f"s{tag}"), a.stats_records)
    print(f"lot stats over {a.stats_records} records in PostgreSQL: {dt:.2f} s (query + statistics)")


if __name__ == "__main__":
    main()
