"""The spool: run records that the database could not take, kept on the station's disk.

A record that cannot be inserted (database locked beyond the timeout, its share not mounted,
the server down, read-only, corrupt) is written as one JSON file into the spool directory,
atomically, and inserted later by :func:`flush_spool`. The insert is keyed by the record's
``run_id`` (:func:`eol_cal.records.write.insert_records`), so a flush interrupted between the
insert and the file's removal inserts nothing twice.

A record journaled at the verdict while its report is still being written (the operator loop's
report thread) is *in flight*: its process holds a lock on ``.in-flight/RUN_ID.lock`` beside it
until the final record is written, and a flush leaves it alone (an early insert would keep the
verdict's version and refuse the final one, the same ``run_id``). The lock is the kernel's
(``flock``): a process that is killed lets go of it, and the next flush takes its journal.
"""

from __future__ import annotations

import fcntl
import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from eol_cal.infra.atomic import atomic_write
from eol_cal.errors import InputError
from eol_cal.infra.inputs import load_json
from eol_cal.infra.jsonsafe import json_safe
from eol_cal.infra.lockfile import open_lock_file
from eol_cal.records.record import RunRecord
from eol_cal.records.connect import DEFAULT_LOCK_TIMEOUT_S, RecordError, db_key, db_shown, one_line
from eol_cal.records.write import insert_records

SPOOL_SCHEMA = "eol-cal/spooled-record/1"
#: largest spool file read back (one run record: ~20 KiB)
MAX_SPOOL_FILE_BYTES = 16 << 20


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



IN_FLIGHT_DIR = ".in-flight"


class InFlight:
    """The lock that keeps a flush off a journaled record until its process has written the final
    one (:func:`hold_in_flight`); :meth:`release` when it has (into the database or the spool)."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path, self._fd = path, fd

    def release(self) -> None:
        if self._fd < 0:
            return
        self.path.unlink(missing_ok=True)  # before the descriptor: a flush then finds no lock file
        os.close(self._fd)
        self._fd = -1


def hold_in_flight(spool_dir: str | Path, run_id: str) -> InFlight:
    """Take the in-flight lock of ``run_id``'s spool file (before the file is written, so a flush
    never sees the journal unlocked while its process lives)."""
    lock_dir = Path(spool_dir) / IN_FLIGHT_DIR
    lock_dir.mkdir(parents=True, exist_ok=True)
    path = lock_dir / f"{run_id}.lock"
    # OSError for a link, a FIFO or anything else at the path (the caller journals without the lock)
    fd = open_lock_file(path)
    fcntl.flock(fd, fcntl.LOCK_EX)  # a run id is new: nobody else holds it
    return InFlight(path, fd)


def in_flight(spool_file: Path) -> bool:
    """Whether a live process still holds ``spool_file``'s in-flight lock; a lock file that nobody
    holds (its process was killed) is removed."""
    path = spool_file.parent / IN_FLIGHT_DIR / f"{spool_file.stem}.lock"
    try:  # non-blocking: an open() of a FIFO waits for a writer
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:  # none: not in flight (a missing file, or anything else that is not a lock file)
        return False
    try:
        if stat.S_ISREG(os.fstat(fd).st_mode):  # anything else is no station's lock
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    path.unlink(missing_ok=True)
    return False


def spool_record(record: RunRecord, db: str | Path, spool_dir: str | Path, why: str) -> Path:
    """Write ``record`` into the spool directory (atomically); returns the file."""
    spool_dir = Path(spool_dir)
    spool_dir.mkdir(parents=True, exist_ok=True)
    doc = {"schema": SPOOL_SCHEMA, "db": db_key(db), "why": why, "record": json_safe(record.to_json())}
    path = spool_dir / f"{record.run_id}.json"
    atomic_write(path, json.dumps(doc, indent=1, allow_nan=False) + "\n")
    return path


@dataclass(frozen=True)
class SaveResult:
    """Where a record went: ``"db"`` or ``"spool"`` (with the spool file and why)."""

    where: str
    path: str
    why: str | None = None


def save_record(record: RunRecord, db: str | Path, spool_dir: str | Path | None = None,
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
        return SaveResult("db", db_shown(db))
    except Exception as exc:  # noqa: BLE001 - whatever keeps the record out of the database, it is spooled
        why = f"{type(exc).__name__}: {one_line(exc)}"
    try:
        path = spool_record(record, db, spool_dir, why)
    except Exception as exc:  # a full disk, or anything else: said with the database's reason
        raise RecordError(f"record {record.run_id} could not be written: database {db_shown(db)}: {why}; "
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
    #: the records written into the database (their pages may be missing: a station killed at its verdict)
    records: tuple[RunRecord, ...] = ()
    #: journaled records whose process is still writing their final version: left for it
    in_flight: int = 0


def _spooled(spool_dir: Path) -> tuple[list[tuple[Path, str, RunRecord]], list[str]]:
    """Readable spooled records ``(file, database, record)``, and ``"file: reason"`` for every file
    that is not one (a record that does not read as one included: it is left alone, not lost)."""
    out, bad = [], []
    for path in sorted(spool_dir.glob("*.json")):
        try:  # the bounded loader: a FIFO, a 5000-digit number or deep nesting is one bad file
            doc = load_json(path, max_bytes=MAX_SPOOL_FILE_BYTES)
        except InputError as exc:
            bad.append(f"{path}: unreadable ({exc.reason})")
            continue
        if not isinstance(doc, dict) or doc.get("schema") != SPOOL_SCHEMA or not isinstance(doc.get("record"), dict):
            bad.append(f"{path}: not a spooled record ({SPOOL_SCHEMA})")
            continue
        try:
            out.append((path, str(doc.get("db")), RunRecord.from_json(doc["record"], str(path))))
        except InputError as exc:
            bad.append(f"{path}: {exc}")
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
    target = db_key(db)
    mine, others, busy = [], 0, 0
    spooled, bad = _spooled(spool_dir)
    for path, where, record in spooled:
        if where != target:
            others += 1
        elif in_flight(path):
            busy += 1
        else:
            mine.append((path, record))
    if not mine:
        return FlushResult(0, 0, 0, others, bad_files=tuple(bad), in_flight=busy)
    try:
        n = insert_records(db, [r for _p, r in mine], timeout_s)
    except Exception as exc:  # noqa: BLE001 - still not writable, however: the records wait in the spool
        return FlushResult(0, 0, len(mine), others, f"{type(exc).__name__}: {one_line(exc)}", tuple(bad),
                           in_flight=busy)
    for path, _r in mine:
        path.unlink(missing_ok=True)
    return FlushResult(n, len(mine), 0, others, bad_files=tuple(bad), records=tuple(r for _p, r in mine),
                       in_flight=busy)
