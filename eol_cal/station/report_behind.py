"""The report and the record's database write after the verdict, on a thread of their own, while
the next motor is scanned and measured (issue 37, the takt: verdict -> next scan).

At the verdict the record is already durable: :mod:`eol_cal.station.steps.decide_verdict` wrote it
into the spool (atomically, fsync'd) before it was shown. An operator loop that hands the
executor a :class:`ReportsBehind` asks for the next serial from there; the report (the fit's plots,
the HTML page) and the record's final version (``report.json``, the database; the journal then
leaves the spool) follow on the one report thread, one run after the other in the order of their
verdicts, with the same steps and the same record as a run that waits for them.

A process that ends meanwhile finishes them first (:meth:`ReportsBehind.finish`, signals held off;
the thread is joined before the interpreter's exit as well). A process killed outright (SIGKILL, a
power cut) leaves the journal in the spool: the next start or ``eol-cal records --flush`` writes it
into the database and rebuilds the missing page from the record
(:func:`eol_cal.station.report_files.rebuild_missing`). Nothing is ever half-written: every file
is replaced atomically.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

from eol_cal.infra.interrupts import shielded
from eol_cal.station.run import RunOutcome


class ReportsBehind:
    """The runs whose report and record are still being written, on one thread, in order."""

    def __init__(self) -> None:
        self._pool: ThreadPoolExecutor | None = None
        self._pending: list[Future[RunOutcome]] = []

    def submit(self, close: Callable[[], RunOutcome]) -> Future[RunOutcome]:
        """Run ``close`` (a run's report and record) after every run submitted before it."""
        if self._pool is None:
            # started on the first motor: a worker thread of a ThreadPoolExecutor is joined before
            # the interpreter exits (its atexit), so a report in flight is finished even then
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="eol-cal-report")
        job = self._pool.submit(close)
        self._pending.append(job)
        return job

    @property
    def in_flight(self) -> int:
        """Runs whose report or record is not written yet."""
        return sum(not job.done() for job in self._pending)

    def done(self) -> list[Future[RunOutcome]]:
        """The runs finished since the last call, in the order of their verdicts (a finished one
        behind an unfinished one waits for it: the screen keeps the motors' order)."""
        out: list[Future[RunOutcome]] = []
        while self._pending and self._pending[0].done():
            out.append(self._pending.pop(0))
        return out

    def finish(self) -> list[Future[RunOutcome]]:
        """Wait for every run in flight (a signal meanwhile is held off until they are written:
        the session's end, Ctrl-C, SIGTERM); returns them all, in order."""
        with shielded():
            for job in list(self._pending):
                job.exception()  # waits; the outcome or the error stays in the future
            out, self._pending = self._pending, []
        return out

    def close(self) -> None:
        """:meth:`finish`, then stop the thread."""
        self.finish()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
