"""``eol-cal station``: the operator loop (scan a serial, run the cycle, show the verdict, next motor)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import click

from cli.common import (RECORDS_DB, CommandExit, console, err_console, exchange_log_options, handle_errors,
                        loop_kernels, styled)
from cli.ecu import key_algo_option
from cli.paths import check_io, check_more, io_paths
from cli.station import StepProgress, flush_first, given_options, quiet_logs, results_table, write_demo_limits
from eol_cal.infra import interrupts

#: `station` options by settings key (as `run`'s); given ones override the file and the environment
STATION_OPTION_KEYS = {"limits_file": "limits", "variant": "variant", "db": "db", "report_dir": "report_dir",
                       "station_id": "station_id", "key_algo": "key_algo"}
#: keys the demo fills itself (the simulators' dyno and bus, the contract's development key)
DEMO_OWN_KEYS = ("dyno.address", "key_file", "can.interface")
DEMO_STATION_ID = "DEMO"
COLOUR = {"pass": "green", "fail": "yellow", "error": "red"}
END_WORDS = ("", "q", "quit")

# 5-row block letters for the verdict, readable from across the station
_FONT = {
    "P": ["████ ", "█   █", "████ ", "█    ", "█    "],
    "A": [" ███ ", "█   █", "█████", "█   █", "█   █"],
    "S": [" ████", "█    ", " ███ ", "    █", "████ "],
    "F": ["█████", "█    ", "████ ", "█    ", "█    "],
    "I": ["█████", "  █  ", "  █  ", "  █  ", "█████"],
    "L": ["█    ", "█    ", "█    ", "█    ", "█████"],
    "E": ["█████", "█    ", "████ ", "█    ", "█████"],
    "R": ["████ ", "█   █", "████ ", "█  █ ", "█   █"],
    "O": [" ███ ", "█   █", "█   █", "█   █", " ███ "],
}


def big_word(word: str) -> str:
    """``word`` (letters of PASS, FAIL, ERROR) in 5-row block letters."""
    return "\n".join("  ".join(_FONT[ch][row] for ch in word) for row in range(5))


def verdict_panel(serial: str, verdict: str, lines: list[str]):
    """The large verdict of one motor, with its reasons and where its report is."""
    from rich.align import Align
    from rich.console import Group
    from rich.panel import Panel
    from rich.text import Text

    colour = COLOUR.get(verdict, "white")
    # centred as one block: centring each row alone would shift the letters' rows apart
    body = [Align.center(Text(big_word(verdict.upper()), style=f"bold {colour}", no_wrap=True)), Text("")]
    body += [Text(line) for line in lines]
    return Panel(Group(*body), title=Text(f"{serial}: {verdict.upper()}"), border_style=colour, expand=True)


def _ask(prompt: str) -> str | None:
    """One line from the operator (a scanner types the code and Enter); None at end of input.

    On a terminal, what was typed before the prompt is dropped first: a code scanned while the
    previous motor ran (that motor is not on the dyno yet), or the second half of a scanner's
    CR LF, which would otherwise read as an empty line and end the session.
    """
    import sys
    import termios

    if sys.stdin.isatty():
        termios.tcflush(sys.stdin.fileno(), termios.TCIFLUSH)
    # the bytes as the scanner sent them, not input(): its line editing (GNU readline) swallowed
    # a NUL and glued the line's two halves together ("M\0q" was calibrated as serial "Mq");
    # bytes that are not UTF-8 stay as surrogates, which no serial or name check lets through
    sys.stdout.write(prompt)
    sys.stdout.flush()
    line = sys.stdin.buffer.readline()
    if not line:
        return None
    return line.decode("utf-8", "surrogateescape").rstrip("\r\n")


def _ask_operator() -> str | None:
    from eol_cal.errors import InputError
    from eol_cal.station.operator_session import operator_name

    while True:
        line = _ask("Operator: ")
        if line is None or not line.strip():
            return None
        try:
            return operator_name(line)
        except InputError as exc:
            console.print(styled((str(exc), "red"), "; type your name again"))


def _next_serial() -> str | None:
    """The next motor's serial, re-asked until it is one; None ends the session."""
    from eol_cal.errors import InputError
    from eol_cal.station.operator_session import scanned_serial

    while True:
        line = _ask("Scan serial (Enter or q ends the session): ")
        if line is None or line.strip().lower() in END_WORDS:
            return None
        try:
            return scanned_serial(line)
        except InputError as exc:
            console.print(styled((f"not a serial: {exc.reason}", "red"), "; scan again"))


def _settings(ctx: click.Context, station_file: str | None, demo: bool, out_dir: Path | None, lot_file: Path | None,
              options: dict):
    """The session's settings: file, environment, options; the demo's own where it runs on simulators."""
    from eol_cal.station.settings import load_settings

    given = given_options(ctx, options, STATION_OPTION_KEYS)
    if not demo:
        return load_settings(station_file, given=given)
    limits = out_dir / "limits.toml"
    # simulated motors never go into a station's database: records and reports stay in the demo's
    # directory unless given, and the station's EOL_CAL_* variables are not read
    given = {"db": str(out_dir / "results.sqlite"), "report_dir": str(out_dir / "reports"),
             "spool_dir": str(out_dir / "spool"), **given}
    # the demo's own files (its limits: written, then read) against its database, given or its own,
    # before the limits are written; the database against the outputs given (--lot, --log-file)
    check_io((), (limits,) if lot_file is not None else (limits, out_dir / "lot.html"), databases=(given["db"],))
    check_more(databases=(given["db"],))
    write_demo_limits(limits)
    return load_settings(station_file, environ={}, given=given, optional=DEMO_OWN_KEYS,
                         fallbacks={"limits": str(limits), "station_id": DEMO_STATION_ID})


def run_one(cfg, serial: str, operator: str, demo_dir: Path | None, on_verdict=None, observers=(), behind=None):
    """The cycle of one motor (on its own loopback simulators in the demo); the verdict is shown
    as soon as the cycle knows it (``on_verdict``, default the terminal's large verdict), the report
    and the record's place after them; ``observers`` (the operator panel's) get each step's events.
    ``behind`` (:class:`~eol_cal.station.report_behind.ReportsBehind`): the report and the database
    follow on its thread, the outcome is the verdict's (``pending``)."""
    from eol_cal.station.configure import for_motor
    from eol_cal.station.cycle import run_motor

    station = dict(cfg.station, operator=operator)
    on_verdict = on_verdict or _show_verdict
    if demo_dir is None:
        with StepProgress(serial) as progress:
            return run_motor(for_motor(cfg, serial, station=station), progress, on_verdict, observers, behind)
    from eol_cal.sim.loopback import loopback_station
    from eol_cal.station.operator_session import demo_seed

    regmap = cfg.dyno.regmap  # the settings' map: the demo's dyno simulator serves the same one
    with loopback_station(serial, demo_seed(serial), demo_dir / "sim", register_map=regmap,
                          prepare=cfg.estimator_options) as st:
        station.update(dyno=st.dyno_address, can={"interface": "remote", "channel": st.can_channel}, demo=True)
        sim = st.dyno_config()
        dyno = dataclasses.replace(cfg.dyno, host=sim.host, port=sim.port, timeout=sim.timeout, watchdog_ms=sim.watchdog_ms)
        mcfg = for_motor(cfg, serial, dyno=dyno, open_bus=st.open_bus, ecu_timing=st.ecu_timing, station=station)
        with StepProgress(serial) as progress:
            return run_motor(mcfg, progress, on_verdict, observers, behind)


def _show_verdict(rec, spooled: bool = True) -> None:
    """The large verdict, the moment the cycle knows it (``spooled``: the record is already safe in
    the spool; otherwise it is written before the next serial, and where it went is shown then)."""
    if rec.kind == "refusal":  # only a refusal can be the gate's (its module loads the database)
        from eol_cal.msa.gate import gate_refusal

        if (line := gate_refusal(rec)) is not None:  # the master gate: one line
            console.print(verdict_panel(rec.serial, rec.verdict, [line]))
            return
    lines = [f"{rec.verdict}: {r}" for r in rec.reasons]
    if rec.kind == "refusal":
        lines.append(f"refused ({', '.join(rec.refusal_codes)}): nothing was written to the ECU; not the motor's result")
    if rec.safe_state:
        lines.append(f"dyno safe state: {rec.safe_state}")
    if rec.ecu_active.block == "uncompensated":
        lines.append("ECU: the uncompensated block is active: the motor is not calibrated")
    if not spooled:
        lines.append("record: NOT in the spool (it could not be written there): being written now, before the next serial")
    else:
        lines.append("record: safe in the spool; the report and the database follow" + (
            " before the next serial" if rec.kind == "master" else " while the next motor runs"))
    console.print(verdict_panel(rec.serial, rec.verdict, lines))


def _show(out) -> None:
    """Where the report and the record went, once they are written."""
    rec = out.record
    where = f"database {out.saved.path}" if out.saved.where == "db" else f"SPOOL {out.saved.path} ({out.saved.why})"
    report = f"report: {out.report_html}" if out.report_html else "report: none (see the record)"
    if rec.report_error:
        report += f" ({rec.report_error})"
    console.print(f"  {rec.serial} {report}\n  {rec.serial} record {rec.run_id} -> {where}")
    if rec.verdict == "error" and rec.report_error:  # the report failed after the verdict was shown
        console.print(verdict_panel(rec.serial, rec.verdict, [f"{rec.verdict}: {r}" for r in rec.reasons]))


def _master_status(cfg) -> str | None:
    """One line: the station's master gate (its settings' or the records database's rules) and
    whether production may run now; None for a station without a gate."""
    from eol_cal.msa.gate import gate_status

    status = gate_status(cfg.db, cfg.station.get("id"), cfg.master, timeout_s=cfg.db_timeout_s)
    return None if status is None else status.line


def ended_by_operator() -> None:
    """A signal at a prompt: Ctrl-C (SIGINT) is the operator ending the session (exit 0); SIGTERM
    or SIGHUP (the station shut down, its terminal closed) stays an interruption (exit 2)."""
    if interrupts.received() in (None, "SIGINT"):
        interrupts.handled()


def _written(jobs, tally) -> None:
    """Runs whose report and record are written (:mod:`eol_cal.station.report_behind`): into the
    session's tally, and where they went on screen."""
    for job in jobs:
        out = job.result()  # a record that neither the database nor the spool took: said, as at once
        tally.written(out.record, str(out.report_html) if out.report_html else None)
        _show(out)


def _loop(cfg, operator: str, demo_dir: Path | None, tally) -> bool:
    """Motors until the operator ends the session; True when a motor was interrupted.

    The next serial is asked for once a motor's record is in the spool (its verdict); its report
    and its database write follow on the report thread while the next motor runs, and are shown
    when they are written. The session waits for them before it ends, whatever ends it."""
    from eol_cal.station.report_behind import ReportsBehind

    behind = ReportsBehind()
    try:
        while True:
            try:
                _written(behind.done(), tally)
                serial = _next_serial()
            except KeyboardInterrupt:
                ended_by_operator()  # Ctrl-C: the session's way to end, with exit 0
                console.print("\nCtrl-C between motors: the session ends")
                return False
            if serial is None:
                return False
            try:
                out = run_one(cfg, serial, operator, demo_dir, behind=behind)
            except KeyboardInterrupt:
                # the cycle has commanded the dyno's safe state and recorded the run as an error
                tally.interrupted.append(serial)
                console.print(verdict_panel(serial, "error", [
                    "interrupted: the dyno was sent to its safe state and the run recorded (an error, unless it had ended)",
                    f"report: under {cfg.report_dir}"]))
                return True
            tally.add(out.record, str(out.report_html) if out.report_html else None)  # the verdict's, in order
            if out.pending is None:  # written at once (a master run; a spool that could not take the record)
                try:
                    _show(out)
                except KeyboardInterrupt:
                    ended_by_operator()
                    return False
    finally:
        # the reports still in flight are finished, signals held off (one that comes meanwhile is
        # raised once they are in the tally): nothing is left half-written
        with interrupts.shielded():
            _written(behind.finish(), tally)


def finish_session(cfg, tally, lot_file: Path | None, min_n: int) -> None:
    """The session's summary, the per-motor reports, and the lot page."""
    from eol_cal.lot.lot_page import select_records, write_lot_page
    from eol_cal.records.connect import db_label, db_shown
    from eol_cal.records.query import query_records

    station_id = cfg.station.get("id")
    if tally.records:
        console.print(results_table(tally.records, f"eol-cal station {station_id}: this session"))
    console.print(f"session: {tally.summary()}")
    for rec, report in zip(tally.records, tally.reports, strict=True):
        what = f"refused ({', '.join(rec.refusal_codes)})" if rec.kind == "refusal" else rec.verdict
        console.print(f"  {rec.serial}: {what}, report {report or '-'}")
    for serial in tally.interrupted:
        console.print(f"  {serial}: interrupted (error), its run directory is under {cfg.report_dir}")
    hint = f"eol-cal lot report --db {db_shown(cfg.db)} --station {station_id} -o lot.html"
    if lot_file is None or not (tally.records or tally.interrupted):
        console.print(f"lot page: {hint}")
        return
    records = select_records(query_records(cfg.db), station=station_id)
    page = write_lot_page(records, lot_file, title=f"{db_label(cfg.db)}, station {station_id}",
                          filters={"variant": None, "since": None, "until": None, "station": station_id}, min_n=min_n)
    console.print(f"lot page: {page} ({len(records)} runs of station {station_id}; again: {hint})")


@click.command("station")
@click.option("--station", "station_file", type=click.Path(dir_okay=False), default=None,
              help="Station settings TOML (docs/station.md, First real station) [default: the EOL_CAL_* variables].")
@click.option("--demo", is_flag=True, help="Loopback ECU and dyno simulators per motor; the scanned serial is the motor.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Demo: directory for limits, database, reports, flash images [default: a new temporary directory].")
@click.option("--operator", default=None, help="Operator for the records [default: asked at the start].")
@click.option("--station-id", default=None, help="Station id for the records (settings key station_id).")
@click.option("--limits", "limits_file", default=None, type=click.Path(dir_okay=False),
              help="Limits TOML (overrides the settings).")
@click.option("--variant", default=None, help="Product variant in the limits file (overrides the settings).")
@click.option("--db", default=None, type=RECORDS_DB, help="Records database (overrides the settings; demo: OUT/results.sqlite).")
@click.option("--report-dir", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Reports (overrides the settings).")
@key_algo_option
@click.option("--lot", "lot_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write the station's lot page here at the end [demo default: OUT/lot.html].")
@click.option("--panel", is_flag=True, help="Serve the session as a page (the operator panel, docs/station.md), not a prompt.")
@click.option("--bind", default=None, metavar="HOST:PORT",
              help="Panel: where to listen [default: 127.0.0.1:8080; port 0: a free one]; another host needs --credentials.")
@click.option("--credentials", "credentials_file", type=click.Path(dir_okay=False), default=None,
              help="Panel: TOML file with user and password (mode 600); every request needs them.")
@click.option("--baseline", "baseline_name", default=None, metavar="NAME",
              help="Panel: a stored baseline (eol-cal lot baseline); an alarm when the latest run breaks its rules.")
@click.pass_context
@handle_errors
@exchange_log_options
@io_paths(inputs=("station_file", "limits_file"), outputs=("lot_file",), output_dirs=("out_dir", "report_dir"),
          databases=("db",))
def station_cmd(ctx, station_file, demo, out_dir, operator, lot_file, panel, bind, credentials_file, baseline_name,
                **options: Any) -> None:
    """The operator loop: scan a motor's serial, run the cycle, read the verdict, next motor.

    Every setting is checked before the first motor. An empty line, q or end of input ends the
    session (exit 0), as does Ctrl-C between motors; Ctrl-C during a motor leaves the dyno in its
    safe state, records the run as an error and ends the session with exit 2. At the end: the
    session's summary, each motor's report, and the station's lot page. With --panel the same session
    is served as a page (scan field, steps, verdict, stop button) on --bind.
    """
    import tempfile

    if not panel and (bind, credentials_file, baseline_name) != (None, None, None):
        from eol_cal.errors import InputError

        given = next(o for o, v in (("--bind", bind), ("--credentials", credentials_file), ("--baseline", baseline_name))
                     if v is not None)
        raise InputError(None, given, "an option of the operator panel: give --panel too")

    loop_kernels()  # the fit's frame, and the demo's plant (in this process)
    from cli.fit import enable_jax_cache
    from eol_cal.ecu import protocol as P
    from eol_cal.ecu.client import hmac_seed_to_key
    from eol_cal.station.configure import station_config
    from eol_cal.records.connect import db_shown
    from eol_cal.station.operator_session import SessionTally, operator_name

    if demo and out_dir is None:
        out_dir = Path(tempfile.mkdtemp(prefix="eol-cal-station-"))
    settings = _settings(ctx, station_file, demo, out_dir, lot_file, options)
    from eol_cal.station.settings import settings_paths

    check_more(*settings_paths(settings))  # --lot and --log-file against the settings' database and files
    cfg = station_config(settings, cache_dir=enable_jax_cache(),
                         seed_to_key=hmac_seed_to_key(P.DEV_SECRET) if demo else None)
    if demo and lot_file is None:
        lot_file = out_dir / "lot.html"
    quiet_logs()
    what = f"demo in {out_dir} (simulated ECU and dyno per motor)" if demo else f"settings {settings.source}"
    console.print(f"eol-cal station {cfg.station['id']}: {what}\n  limits {cfg.limits.source} ({cfg.limits.variant}), "
                  f"records {db_shown(cfg.db)}, reports {cfg.report_dir}")
    if panel:
        from cli.panel import panel_session
        from eol_cal.panel.serve import DEFAULT_BIND

        if not demo:
            flush_first(cfg.db, cfg.spool_dir, cfg.db_timeout_s)
        tally, interrupted = panel_session(cfg, out_dir if demo else None, operator, bind or DEFAULT_BIND, credentials_file,
                                           baseline_name, run_one, ended_by_operator)
        finish_session(cfg, tally, lot_file, int(settings["min_n"]))
        if interrupted:
            raise CommandExit(2)
        return
    try:
        operator = operator_name(operator) if operator is not None else _ask_operator()
    except KeyboardInterrupt:
        ended_by_operator()
        operator = None
    if operator is None:
        console.print("no operator: the session ends")
        return
    if not demo:
        flush_first(cfg.db, cfg.spool_dir, cfg.db_timeout_s)
    if (status := _master_status(cfg)) is not None:  # the database's rules too, not only [master]
        console.print(status)
    err_console.print(f"operator {operator}; each motor takes about a quarter of a minute")
    tally = SessionTally()
    interrupted = False
    try:
        interrupted = _loop(cfg, operator, out_dir if demo else None, tally)
    finally:
        finish_session(cfg, tally, lot_file, int(settings["min_n"]))
    if interrupted:
        raise CommandExit(2)


COMMANDS = [station_cmd]
