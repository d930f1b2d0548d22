"""``eol-cal station --panel``: the operator loop served as a page; ``eol-cal line``: the line's view.

The panel is the terminal loop's session (cli/operator.py: the same settings, ``run_one`` and
records) with its serials scanned into a page instead of a prompt; the cycle stays in the main
thread, the web server runs on a thread (eol_cal/panel/serve.py). The line view reads the records
database and nothing else.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import click

from cli.common import RECORDS_DB, console, handle_errors
from eol_cal.infra import interrupts


def _alarm_lines(cfg, baseline) -> list[str]:
    """The baseline's rules broken by the station's latest run (none without a baseline)."""
    from eol_cal.panel.line import station_alarms

    return station_alarms(cfg.db, cfg.station.get("id"), baseline, timeout_s=cfg.db_timeout_s)


def _where(out) -> str:
    """Where a run's record went, in the panel's words."""
    return f"database {out.saved.path}" if out.saved.where == "db" else f"SPOOL {out.saved.path} ({out.saved.why})"


def _panel_loop(cfg, state, controls, demo_dir: Path | None, tally, baseline, run_one, ended_by_operator) -> bool:
    """Motors until the session ends from the page (or a signal); True when a signal interrupted a motor.
    ``run_one`` and ``ended_by_operator``: the terminal loop's (cli/operator.py).

    As at the terminal, the next scan is taken once a motor's record is in the spool (its verdict);
    its report and database write follow on the report thread, the page shows them as they are
    written, and the session waits for them before it ends."""
    from eol_cal.msa.gate import gate_status
    from eol_cal.station.report_behind import ReportsBehind

    def refresh() -> None:
        state.gate(gate_status(cfg.db, cfg.station.get("id"), cfg.master, timeout_s=cfg.db_timeout_s))
        state.alarms(_alarm_lines(cfg, baseline))

    def shown_when_written(job) -> None:  # on the report thread: the page
        if job.exception() is not None:
            state.message("error", f"the record could not be written: {job.exception()}")
            return
        out = job.result()
        state.written(out.record, str(out.report_html) if out.report_html else None, _where(out))
        with contextlib.suppress(Exception):  # the alarms read the database, which has the run now
            state.alarms(_alarm_lines(cfg, baseline))

    def take_written(jobs) -> None:  # in the main thread: the session's tally
        for job in jobs:
            out = job.result()  # a record neither the database nor the spool took ends the session, as at once
            tally.written(out.record, str(out.report_html) if out.report_html else None)
        if jobs:
            state.update(counts=tally.counts())

    behind = ReportsBehind()
    refresh()
    try:
        while True:
            scan = None
            try:
                take_written(behind.done())
                scan = controls.next_scan()
                if scan is None:
                    return False
                controls.started(scan)
                out = run_one(cfg, scan.serial, scan.operator, demo_dir, on_verdict=state.verdict_known,
                              observers=[state.observe], behind=behind)
                tally.add(out.record, str(out.report_html) if out.report_html else None)
                if out.pending is None:
                    state.finished(out.record, str(out.report_html) if out.report_html else None, _where(out),
                                   tally.counts())
                else:
                    state.finished(out.record, None, "being written (safe in the spool; the report and the database follow)",
                                   tally.counts())
                    out.pending.add_done_callback(shown_when_written)
                refresh()
            except KeyboardInterrupt:
                if controls.took_stop():  # the stop button: the motor is recorded, the session goes on
                    interrupts.handled()
                    if scan is not None and state.get("phase") != "idle":
                        tally.interrupted.append(scan.serial)
                        state.interrupted(scan.serial, "stopped from the panel", tally.counts())
                    continue
                if scan is None or state.get("phase") == "idle":  # a signal between motors: as at the prompt
                    ended_by_operator()
                    return False
                tally.interrupted.append(scan.serial)
                state.interrupted(scan.serial, f"interrupted by {interrupts.received() or 'a signal'}", tally.counts())
                return True
    finally:
        with interrupts.shielded():  # the reports in flight finished, as at the terminal
            take_written(behind.finish())


def panel_session(cfg, demo_dir: Path | None, operator: str | None, bind: str, credentials_file: str | None,
                  baseline_name: str | None, run_one, ended_by_operator):
    """Serve the panel of ``cfg``'s station until the session ends; the session's tally and whether
    a signal interrupted a motor. ``run_one``, ``ended_by_operator``: the terminal loop's, so both
    loops run one cycle the same way."""
    import threading

    from eol_cal.panel.app import panel_app
    from eol_cal.panel.controls import Controls
    from eol_cal.panel.serve import listening_socket, load_credentials, parse_bind, served, station_lock, url_of
    from eol_cal.panel.state import PanelState
    from eol_cal.station.operator_session import SessionTally, operator_name

    credentials = load_credentials(credentials_file) if credentials_file is not None else None
    host, port = parse_bind(bind, credentials)
    baseline = None
    if baseline_name is not None:
        from eol_cal.lot.baseline import load

        baseline = load(cfg.db, baseline_name)
    state = PanelState(cfg.station.get("id"), operator_name(operator) if operator is not None else None,
                       demo=demo_dir is not None)
    controls = Controls(state)
    tally = SessionTally()
    closing = threading.Event()
    sock = listening_socket(host, port)
    with station_lock(cfg.spool_dir, cfg.station.get("id"), url_of(sock)):
        app = panel_app(controls, closing.is_set, credentials)
        with served(app, sock, closing) as url:
            console.print(f"panel: {url} (station {cfg.station.get('id')}; the session ends from the page, or Ctrl-C "
                          "between motors)", highlight=False)
            interrupted = _panel_loop(cfg, state, controls, demo_dir, tally, baseline, run_one, ended_by_operator)
    return tally, interrupted


@click.command("line")
@click.option("--db", required=True, type=RECORDS_DB, help="The line's records database (SQLite file or postgresql:// URL).")
@click.option("--bind", default="127.0.0.1:8090", show_default=True,
              help="HOST:PORT to serve on (port 0: a free one); another host than this machine needs --credentials.")
@click.option("--credentials", "credentials_file", type=click.Path(dir_okay=False), default=None,
              help="TOML file with user and password (mode 600): every request needs them.")
@click.option("--baseline", "baseline_name", default=None, metavar="NAME",
              help="A stored baseline (eol-cal lot baseline): a station whose latest run breaks one of its rules shows an alarm.")
@click.option("--shifts", default="06:00,14:00,22:00", show_default=True, help="Shift start times (UTC) for the yield per shift.")
@click.option("--poll", "poll_s", type=click.FloatRange(0.2, 600), default=2.0, show_default=True,
              help="Seconds between two reads of the database.")
@handle_errors
def line_cmd(db, bind, credentials_file, baseline_name, shifts, poll_s) -> None:
    """A read-only view of the line from its records database: each station's state and last motors,
    first-pass yield and yield per shift, the alarms (master check due or failed, a baseline's rule
    broken), updating live. It never writes to the database."""
    import threading

    from eol_cal.msa.master import parse_shifts
    from eol_cal.panel.app import line_app
    from eol_cal.panel.line import LineWatch
    from eol_cal.panel.serve import listening_socket, load_credentials, parse_bind, served

    credentials = load_credentials(credentials_file) if credentials_file is not None else None
    host, port = parse_bind(bind, credentials)
    shift_starts = parse_shifts(shifts, None, "--shifts")
    baseline = None
    if baseline_name is not None:
        from eol_cal.lot.baseline import load

        baseline = load(db, baseline_name)
    closing = threading.Event()
    watch = LineWatch(db, shift_starts, baseline, poll_s)
    sock = listening_socket(host, port)
    with watch.running(closing), served(line_app(watch, closing.is_set, credentials), sock, closing) as url:
        console.print(f"line view: {url} (database read every {poll_s:g} s; Ctrl-C ends it)", highlight=False)
        try:
            while not closing.wait(0.5):
                pass
        except KeyboardInterrupt:
            interrupts.handled()  # Ctrl-C is how the view ends: exit 0


COMMANDS = [line_cmd]
