"""Run records: SQLite in WAL mode, with a local spool so that no record is ever lost.

One row per motor run in table ``runs`` (columns in ``docs/station.md``): serial, variant,
start/end times (UTC ISO 8601), capture paths and SHA-256, the fit record (JSON), the block's
CRC and sequence, tool and layout versions, verdict and reasons, plus the whole record as JSON.

When the database cannot be written - locked beyond the timeout, its directory missing (a share
not mounted), read-only, corrupt - the record is written as one JSON file into the spool
directory (atomically: temp file, fsync, rename) and inserted later by :func:`flush_spool`
(the next run does it first; ``eol-cal records --flush`` does it by hand). The insert is keyed by
the record's ``run_id``, so a flush interrupted between the insert and the spool file's removal
inserts nothing twice.
"""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from eol_cal.errors import EolCalError, InputError

RECORD_SCHEMA = "eol-cal/run-record/1"
SPOOL_SCHEMA = "eol-cal/spooled-record/1"
#: seconds a write waits for another connection's lock before the record goes to the spool
DEFAULT_LOCK_TIMEOUT_S = 5.0

_COLUMNS = (
    ("run_id", "TEXT PRIMARY KEY"),
    ("serial", "TEXT NOT NULL"),
    ("variant", "TEXT"),
    ("started_at", "TEXT NOT NULL"),
    ("ended_at", "TEXT"),
    ("verdict", "TEXT NOT NULL CHECK (verdict IN ('pass', 'fail', 'error'))"),
    ("reasons", "TEXT NOT NULL"),
    ("k6", "REAL"),
    ("phase_k6", "REAL"),
    ("c6", "REAL"),
    ("pp_before_pct", "REAL"),
    ("pp_after_pct", "REAL"),
    ("improvement_pct", "REAL"),
    ("capture_before", "TEXT"),
    ("sha256_before", "TEXT"),
    ("capture_after", "TEXT"),
    ("sha256_after", "TEXT"),
    ("fit_json", "TEXT"),
    ("block_crc32", "TEXT"),
    ("block_sequence", "INTEGER"),
    ("tool_version", "TEXT"),
    ("layout_version", "INTEGER"),
    ("report_dir", "TEXT"),
    ("record_json", "TEXT NOT NULL"),
)
COLUMN_NAMES = tuple(c for c, _ in _COLUMNS)
_CREATE = (
    f"CREATE TABLE IF NOT EXISTS runs ({', '.join(f'{c} {t}' for c, t in _COLUMNS)});"
    "CREATE INDEX IF NOT EXISTS runs_serial ON runs (serial);"
    "CREATE INDEX IF NOT EXISTS runs_started ON runs (started_at);"
)


class RecordError(EolCalError):
    """Neither the database nor the spool could take a record (exit code 2)."""


def default_spool_dir() -> Path:
    """``$EOL_CAL_SPOOL``, else ``$XDG_STATE_HOME/eol-cal/spool`` (``~/.local/state/...``).

    Deliberately on the station's local disk, not next to the database: the database may be
    on a share that is the very thing that is down.
    """
    env = os.environ.get("EOL_CAL_SPOOL")
    if env:
        return Path(env)
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(state) / "eol-cal" / "spool"


def _row(record: dict[str, Any]) -> tuple:
    def get(*keys: str) -> Any:
        x: Any = record
        for k in keys:
            if not isinstance(x, dict) or x.get(k) is None:
                return None
            x = x[k]
        return x

    fit = record.get("fit")
    values = {
        "run_id": record["run_id"],
        "serial": record["serial"],
        "variant": get("limits", "variant"),
        "started_at": record["started_at"],
        "ended_at": record.get("ended_at"),
        "verdict": record["verdict"],
        "reasons": json.dumps(record.get("reasons") or []),
        "k6": get("fit", "k6", "value"),
        "phase_k6": get("fit", "phase_k6", "value"),
        "c6": get("fit", "c6", "value"),
        "pp_before_pct": get("metrics", "pp_before_pct"),
        "pp_after_pct": get("metrics", "pp_after_pct"),
        "improvement_pct": get("metrics", "improvement_pct"),
        "capture_before": get("captures", "before", "path"),
        "sha256_before": get("captures", "before", "sha256"),
        "capture_after": get("captures", "after", "path"),
        "sha256_after": get("captures", "after", "sha256"),
        "fit_json": json.dumps(fit, allow_nan=False) if fit is not None else None,
        "block_crc32": get("block", "crc32"),
        "block_sequence": get("block", "sequence"),
        "tool_version": record.get("tool_version"),
        "layout_version": record.get("layout_version"),
        "report_dir": record.get("report_dir"),
        "record_json": json.dumps(record, allow_nan=False),
    }
    return tuple(values[c] for c in COLUMN_NAMES)


@contextlib.contextmanager
def _connect(db: Path, timeout_s: float, readonly: bool = False) -> Iterator[sqlite3.Connection]:
    # isolation_level=None: transactions are explicit (BEGIN IMMEDIATE takes the write lock up
    # front, so a locked database fails here after the timeout, not half-way through)
    if readonly:
        con = sqlite3.connect(f"{db.resolve().as_uri()}?mode=ro", uri=True, timeout=timeout_s, isolation_level=None)
    else:
        con = sqlite3.connect(str(db), timeout=timeout_s, isolation_level=None)
    try:
        yield con
    finally:
        con.close()


def _prepare(con: sqlite3.Connection) -> None:
    mode = con.execute("PRAGMA journal_mode=WAL").fetchone()[0]
    if str(mode).lower() != "wal":
        raise sqlite3.OperationalError(f"cannot switch the database to WAL mode (journal_mode={mode})")
    con.execute("PRAGMA synchronous=FULL")
    con.executescript(_CREATE)


def insert_records(db: str | Path, records: list[dict[str, Any]], timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> int:
    """Insert records in one transaction; an existing ``run_id`` is left as it is.

    Returns the number of rows inserted. Raises :class:`sqlite3.Error` (or :class:`OSError`)
    when the database cannot be written; the caller decides to spool.
    """
    db = Path(db)
    if not db.parent.is_dir():
        # sqlite would say "unable to open database file"; say which directory is missing
        raise sqlite3.OperationalError(f"directory {db.parent} does not exist")
    with _connect(db, timeout_s) as con:
        con.execute(f"PRAGMA busy_timeout={int(timeout_s * 1000)}")
        _prepare(con)
        con.execute("BEGIN IMMEDIATE")
        try:
            before = con.total_changes
            con.executemany(f"INSERT OR IGNORE INTO runs ({', '.join(COLUMN_NAMES)}) VALUES "
                            f"({', '.join('?' * len(COLUMN_NAMES))})", [_row(r) for r in records])
            n = con.total_changes - before
            con.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                con.execute("ROLLBACK")
            raise
    return n


def spool_record(record: dict[str, Any], db: str | Path, spool_dir: str | Path, why: str) -> Path:
    """Write ``record`` into the spool directory (atomically); returns the file."""
    from eol_cal.atomic import atomic_write

    spool_dir = Path(spool_dir)
    spool_dir.mkdir(parents=True, exist_ok=True)
    doc = {"schema": SPOOL_SCHEMA, "db": str(Path(db).resolve()), "why": why, "record": record}
    path = spool_dir / f"{record['run_id']}.json"
    atomic_write(path, json.dumps(doc, indent=1, allow_nan=False) + "\n")
    return path


@dataclass(frozen=True)
class SaveResult:
    """Where a record went: ``"db"`` or ``"spool"`` (with the spool file and why)."""

    where: str
    path: str
    why: str | None = None


def save_record(record: dict[str, Any], db: str | Path, spool_dir: str | Path | None = None,
                timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> SaveResult:
    """Write a run record into the database, or into the spool when the database fails.

    Raises
    ------
    RecordError
        Neither worked (the message says both reasons; the caller should print the record).
    """
    spool_dir = Path(spool_dir) if spool_dir is not None else default_spool_dir()
    try:
        insert_records(db, [record], timeout_s)
        return SaveResult("db", str(db))
    except (sqlite3.Error, OSError) as exc:
        why = f"{type(exc).__name__}: {exc}"
    try:
        path = spool_record(record, db, spool_dir, why)
    except OSError as exc:
        raise RecordError(f"record {record['run_id']} could not be written: database {db}: {why}; "
                          f"spool {spool_dir}: {exc}") from exc
    return SaveResult("spool", str(path), why)


@dataclass(frozen=True)
class FlushResult:
    """Outcome of :func:`flush_spool`."""

    inserted: int
    flushed_files: int
    remaining: int
    other_db: int
    error: str | None = None
    bad_files: tuple[str, ...] = ()


def _spooled(spool_dir: Path) -> tuple[list[tuple[Path, dict[str, Any]]], list[str]]:
    """Readable spooled records, and ``"file: reason"`` for every file that is not one."""
    out, bad = [], []
    for path in sorted(spool_dir.glob("*.json")):
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
            bad.append(f"{path}: unreadable ({exc})")
            continue
        if not isinstance(doc, dict) or doc.get("schema") != SPOOL_SCHEMA or not isinstance(doc.get("record"), dict):
            bad.append(f"{path}: not a spooled record ({SPOOL_SCHEMA})")
            continue
        out.append((path, doc))
    return out, bad


def flush_spool(db: str | Path, spool_dir: str | Path | None = None,
                timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> FlushResult:
    """Insert every spooled record meant for ``db`` and remove its spool file.

    Records spooled for another database stay. When the database still cannot be written
    nothing is removed and ``error`` says why. Files in the spool that are not spooled records
    are left alone and listed in ``bad_files`` (one stray file must not stop the line).
    """
    spool_dir = Path(spool_dir) if spool_dir is not None else default_spool_dir()
    if not spool_dir.is_dir():
        return FlushResult(0, 0, 0, 0)
    target = str(Path(db).resolve())
    mine, others = [], 0
    spooled, bad = _spooled(spool_dir)
    for path, doc in spooled:
        if doc.get("db") == target:
            mine.append((path, doc["record"]))
        else:
            others += 1
    if not mine:
        return FlushResult(0, 0, 0, others, bad_files=tuple(bad))
    try:
        n = insert_records(db, [r for _p, r in mine], timeout_s)
    except (sqlite3.Error, OSError, KeyError) as exc:
        return FlushResult(0, 0, len(mine), others, f"{type(exc).__name__}: {exc}", tuple(bad))
    for path, _r in mine:
        path.unlink(missing_ok=True)
    return FlushResult(n, len(mine), 0, others, bad_files=tuple(bad))


def query_records(db: str | Path, serial: str | None = None, day: str | None = None,
                  timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> list[dict[str, Any]]:
    """Records (the stored JSON documents) by serial and/or UTC day ``YYYY-MM-DD``, oldest first."""
    db = Path(db)
    if not db.exists():
        raise InputError(str(db), None, "database not found")
    where, args = [], []
    if serial is not None:
        where.append("serial = ?")
        args.append(serial)
    if day is not None:
        where.append("substr(started_at, 1, 10) = ?")
        args.append(day)
    sql = "SELECT record_json FROM runs" + (f" WHERE {' AND '.join(where)}" if where else "") + " ORDER BY started_at, run_id"
    try:
        with _connect(db, timeout_s, readonly=True) as con:
            rows = con.execute(sql, args).fetchall()
    except sqlite3.Error as exc:
        raise InputError(str(db), None, f"cannot read the records: {exc}") from None
    return [json.loads(r[0]) for r in rows]


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Counts and pass rate of a set of records.

    ``pass_rate`` is pass / (pass + fail): the motors' yield, with station errors (which say
    nothing about the motor) counted apart; None without a judged run. ``motors_pass`` counts
    the motors whose latest run passed.
    """
    counts = {v: sum(1 for r in records if r.get("verdict") == v) for v in ("pass", "fail", "error")}
    judged = counts["pass"] + counts["fail"]
    latest: dict[str, str] = {}
    for r in sorted(records, key=lambda r: r.get("started_at", "")):
        latest[r["serial"]] = r.get("verdict")
    return {
        "runs": len(records), **counts,
        "pass_rate": counts["pass"] / judged if judged else None,
        "motors": len(latest), "motors_pass": sum(1 for v in latest.values() if v == "pass"),
    }
