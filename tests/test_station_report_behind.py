"""The report after the next scan (issue 37, item 6: verdict -> next scan): an operator loop's run
returns at its verdict with the record durable in the spool; the report and the database write
follow on the report thread (eol_cal/station/report_behind.py). A report still in flight when a
signal comes is finished before the signal is raised; a report that fails is recorded against the
run, which is not lost.

In-process on the refused configuration (its cycle needs no simulator: it ends at the pre-flight,
then runs the verdict, report and record steps as every run does); the report step is held on an
event, so what is checked is the order of things, not how fast they are.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import threading
from pathlib import Path

import pytest

from _station_configs import settings_refused_config
from eol_cal.errors import Interrupted
from eol_cal.infra import interrupts
from eol_cal.records.query import query_records
from eol_cal.station.cycle import run_motor
from eol_cal.station.report_behind import ReportsBehind
from eol_cal.station.steps import write_report

#: a hang guard: the report thread's work here is milliseconds; 60 s holds on any loaded machine
HANG_S = 60.0


@pytest.fixture
def held_report(monkeypatch):
    """The report step waits until the test releases it (then draws the real page)."""
    release, started = threading.Event(), threading.Event()
    real = write_report.run

    def held(ctx):
        started.set()
        assert release.wait(HANG_S), "the test never released the report"
        return real(ctx)

    monkeypatch.setattr(write_report, "run", held)
    return started, release


def _spooled(spool: Path) -> list[dict]:
    return [json.loads(p.read_text())["record"] for p in sorted(spool.glob("*.json"))]


def test_the_record_is_durable_when_the_next_scan_is_asked_for_and_the_report_follows(tmp_path, held_report):
    started, release = held_report
    cfg = settings_refused_config(tmp_path)
    shown: list = []
    behind = ReportsBehind()
    try:
        out = run_motor(cfg, on_verdict=lambda rec, spooled: shown.append(rec), behind=behind)
        # returned at the verdict, the report still in flight: the record is in the spool (written
        # atomically, fsync'd), the same one the screen showed; the database does not have it yet
        assert started.wait(HANG_S) and out.pending is not None and not out.pending.done()
        assert behind.in_flight == 1
        (spooled,) = _spooled(tmp_path / "spool")
        assert spooled["run_id"] == out.record.run_id == shown[0].run_id
        assert (spooled["verdict"], out.saved.where, out.saved.path) == (
            "error", "spool", str(tmp_path / "spool" / f"{out.record.run_id}.json"))
        assert not (tmp_path / "r.sqlite").exists()
        assert not (out.record.report_dir and (Path(out.record.report_dir) / "report.html").exists())
        release.set()
        final = out.final()
    finally:
        release.set()
        behind.close()
    # then: the page, the record with its report step, in the database, and the spool emptied
    assert final.saved.where == "db" and final.report_html is not None and final.report_html.is_file()
    assert [s.step for s in final.record.steps] == ["pre-flight", "report"]
    (row,) = query_records(tmp_path / "r.sqlite")
    assert row.run_id == out.record.run_id and [s.step for s in row.steps] == ["pre-flight", "report"]
    assert json.loads((final.report_html.parent / "report.json").read_text()) == final.record.to_json()
    assert _spooled(tmp_path / "spool") == []


def test_without_the_report_thread_the_run_returns_with_its_report_and_record_written(tmp_path):
    out = run_motor(settings_refused_config(tmp_path))
    assert out.pending is None and out.final() is out and out.saved.where == "db" and out.report_html.is_file()


def test_two_runs_in_flight_are_written_in_the_order_of_their_verdicts(tmp_path, held_report):
    started, release = held_report
    behind = ReportsBehind()
    try:
        first = run_motor(settings_refused_config(tmp_path / "a"), behind=behind)
        second = run_motor(settings_refused_config(tmp_path / "b"), behind=behind)
        assert started.wait(HANG_S) and behind.in_flight == 2 and behind.done() == []
        release.set()
        jobs = behind.finish()
    finally:
        release.set()
        behind.close()
    assert jobs == [first.pending, second.pending] and behind.in_flight == 0
    for out, where in ((first, "a"), (second, "b")):
        (row,) = query_records(tmp_path / where / "r.sqlite")
        assert row.run_id == out.record.run_id and out.final().report_html.is_file()


def test_a_failing_report_is_recorded_against_the_run_which_is_not_lost(tmp_path, monkeypatch):
    def broken(ctx):
        raise OSError("disk full while drawing")

    monkeypatch.setattr(write_report, "run", broken)
    behind = ReportsBehind()
    try:
        out = run_motor(settings_refused_config(tmp_path), behind=behind)
        final = out.final()
    finally:
        behind.close()
    assert final.report_html is None and final.record.report_error == "OSError: disk full while drawing"
    assert final.record.steps[-1].step == "report" and "disk full" in (final.record.steps[-1].error or "")
    (row,) = query_records(tmp_path / "r.sqlite")
    assert (row.run_id, row.report_error) == (out.record.run_id, "OSError: disk full while drawing")
    assert _spooled(tmp_path / "spool") == []


def test_a_signal_while_a_report_is_in_flight_waits_until_it_is_written(tmp_path, held_report):
    """SIGTERM (as the CLI delivers it) while the session waits for its last report: the report
    and the record are written first, then the signal is raised."""
    started, release = held_report
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: interrupts.deliver("SIGTERM", frame))
    interrupts.reset()
    behind = ReportsBehind()
    try:
        out = run_motor(settings_refused_config(tmp_path), behind=behind)
        assert started.wait(HANG_S)

        def signal_then_release() -> None:
            os.kill(os.getpid(), signal.SIGTERM)
            release.set()

        threading.Timer(0.2, signal_then_release).start()
        with pytest.raises(Interrupted):
            behind.finish()
        # raised only once the run was written: the page whole, the record in the database
        assert out.pending.done() and out.final().report_html.is_file()
        (row,) = query_records(tmp_path / "r.sqlite")
        assert row.run_id == out.record.run_id and _spooled(tmp_path / "spool") == []
    finally:
        release.set()
        behind.close()
        signal.signal(signal.SIGTERM, previous)
        interrupts.reset()


def test_a_page_the_station_never_wrote_is_rebuilt_from_the_record_when_the_spool_is_flushed(tmp_path):
    """A station killed (SIGKILL, a power cut) while the report thread drew the page: the journal is
    in the spool, the run's directory has no page; `records --flush` writes the record into the
    database and the page from it (no plots, a note says why). A spooled record naming a directory
    that is not its run's own gets nothing written there."""
    from click.testing import CliRunner

    from cli.main import cli
    from eol_cal.records.spool import spool_record
    from eol_cal.station.report_files import REBUILT_NOTE

    out = run_motor(settings_refused_config(tmp_path))
    run_dir = Path(out.record.report_dir)
    (run_dir / "report.html").unlink()
    (run_dir / "report.json").unlink()
    spool = tmp_path / "kept"
    db = tmp_path / "other.sqlite"
    spool_record(out.record, db, spool, "written at the verdict")
    foreign = tmp_path / "elsewhere"
    foreign.mkdir()
    stranger = run_motor(settings_refused_config(tmp_path / "s")).record
    spool_record(dataclasses.replace(stranger, report_dir=str(foreign)), db, spool, "crafted")
    res = CliRunner().invoke(cli, ["records", "--db", str(db), "--flush", "--spool-dir", str(spool), "--json"])
    assert res.exit_code == 0, res.output
    assert {r.run_id for r in query_records(db)} == {out.record.run_id, stranger.run_id}
    page = (run_dir / "report.html").read_text()
    assert REBUILT_NOTE in page and out.record.serial in page and page.rstrip().endswith("</html>")
    assert json.loads((run_dir / "report.json").read_text()) == out.record.to_json()
    assert list(foreign.iterdir()) == []


def test_a_spool_that_cannot_take_the_record_is_not_called_safe_and_the_record_is_written_at_once(tmp_path):
    from cli.operator import _show_verdict, console

    blocked = tmp_path / "spool-is-a-file"
    blocked.write_text("not a directory")
    cfg = dataclasses.replace(settings_refused_config(tmp_path), spool_dir=blocked)
    shown: list = []
    behind = ReportsBehind()
    try:
        out = run_motor(cfg, on_verdict=lambda rec, spooled: shown.append((rec, spooled)), behind=behind)
    finally:
        behind.finish()
    # the screen was told the record was not in the spool, and the run did not go behind: the
    # record is in the database before the next serial
    assert [spooled for _, spooled in shown] == [False]
    assert out.pending is None and out.saved.where == "db"
    assert [r.run_id for r in query_records(cfg.db)] == [out.record.run_id]
    with console.capture() as cap:
        _show_verdict(shown[0][0], False)
    text = " ".join(cap.get().split())
    assert "NOT in the spool" in text and "safe in the spool" not in text


def test_a_flush_from_another_process_leaves_a_record_whose_report_is_in_flight(tmp_path, held_report):
    """`records --flush` (another process, the kernel's lock between them) while the report thread
    draws the page: the journal is left for the station, whose final record (with its report step)
    is the one the database keeps; once the station has let go, a flush takes what is left."""
    import subprocess
    import sys

    started, release = held_report
    cfg = settings_refused_config(tmp_path)
    behind = ReportsBehind()
    flush = [sys.executable, "-m", "cli.main", "records", "--db", str(cfg.db), "--flush",
             "--spool-dir", str(tmp_path / "spool"), "--json"]
    made = subprocess.run([sys.executable, "-m", "cli.main", "records", "migrate", "--db", str(cfg.db)],
                          capture_output=True, text=True, timeout=300, check=False)
    assert made.returncode == 0, made.stderr
    try:
        out = run_motor(cfg, behind=behind)
        assert started.wait(HANG_S)
        res = subprocess.run(flush, capture_output=True, text=True, timeout=300, check=False)
        assert res.returncode == 0, res.stderr
        assert "1 still being written by a running station" in " ".join(res.stderr.split())
        assert len(_spooled(tmp_path / "spool")) == 1
        assert query_records(cfg.db) == []
        release.set()
        final = out.final()
    finally:
        release.set()
        behind.close()
    (row,) = query_records(cfg.db)
    assert row.run_id == final.record.run_id and [s.step for s in row.steps] == ["pre-flight", "report"]
    assert _spooled(tmp_path / "spool") == [] and not any((tmp_path / "spool" / ".in-flight").iterdir())


def test_a_journal_whose_process_was_killed_is_flushed(tmp_path):
    """The lock is the kernel's: a journal left by a process that no longer runs (its lock file
    still there, nobody holding it) is not in flight."""
    from eol_cal.records.spool import IN_FLIGHT_DIR, flush_spool, in_flight, spool_record

    rec = run_motor(settings_refused_config(tmp_path / "a")).record
    spool, db = tmp_path / "spool", tmp_path / "r.sqlite"
    path = spool_record(rec, db, spool, "written at the verdict")
    (spool / IN_FLIGHT_DIR).mkdir()
    (spool / IN_FLIGHT_DIR / f"{rec.run_id}.lock").write_text("")  # what a SIGKILL leaves
    assert not in_flight(path)
    res = flush_spool(db, spool)
    assert (res.inserted, res.in_flight) == (1, 0) and [r.run_id for r in query_records(db)] == [rec.run_id]


def test_a_lock_file_that_is_no_regular_file_holds_no_journal(tmp_path):
    """A FIFO named as a run's lock (an open() of it waits for a writer) is no station's lock: the
    flush takes the journal at once."""
    import threading

    from eol_cal.records.spool import IN_FLIGHT_DIR, flush_spool, spool_record

    rec = run_motor(settings_refused_config(tmp_path / "a")).record
    spool, db = tmp_path / "spool", tmp_path / "r.sqlite"
    spool_record(rec, db, spool, "written at the verdict")
    (spool / IN_FLIGHT_DIR).mkdir()
    os.mkfifo(spool / IN_FLIGHT_DIR / f"{rec.run_id}.lock")
    got: dict = {}
    flusher = threading.Thread(target=lambda: got.update(res=flush_spool(db, spool)), daemon=True)
    flusher.start()
    flusher.join(HANG_S)
    assert not flusher.is_alive() and (got["res"].inserted, got["res"].in_flight) == (1, 0)
