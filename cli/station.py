"""``eol-cal run`` (the end-of-line cycle for one motor) and ``eol-cal demo``."""

from __future__ import annotations

import threading
from importlib import resources
from pathlib import Path

import click

from cli.common import (RECORDS_DB, CommandExit, console, err_console, estimator_option, exchange_log_options,
                        handle_errors, print_json, loop_kernels, styled)
from cli.dyno import load_map, realtime_option, register_map_option
from cli.ecu import key_algo_option
from cli.paths import check_io, check_more, io_paths

# what `demo` writes to DIR/limits.toml and judges against (fixtures/limits.toml has more variants)
DEMO_LIMITS = resources.files("eol_cal.station").joinpath("demo-limits.toml").read_text(encoding="utf-8")


def quiet_logs() -> None:
    from eol_cal.infra.exchange_log import quiet

    # pymodbus, can-isotp, udsoncan log every retry and timeout; the run reports failures itself
    # (--verbose/--log-file open the exchange loggers again)
    quiet(("pymodbus", "isotp", "UdsClient", "Connection", "can", "can_remote"))


class StepProgress:
    """The cycle's steps as a rich progress display (one line per step, with its time)."""

    def __init__(self, serial: str, enabled: bool = True) -> None:
        from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

        from rich.markup import escape

        self.serial = escape(serial)  # the step lines are markup (their marks); the serial is not
        self.progress = Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                                 console=err_console, transient=True, disable=not enabled)
        self.tasks: dict[str, int] = {}

    def __enter__(self) -> StepProgress:
        self.progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.__exit__(*exc)

    def __call__(self, step: str, state: str) -> None:
        if state == "start":
            self.tasks[step] = self.progress.add_task(f"{self.serial}: {step}", total=1)
        elif step in self.tasks:
            mark = {"done": "[green]ok[/green]", "failed": "[red]failed[/red]"}.get(state, state)
            self.progress.update(self.tasks[step], completed=1, description=f"{self.serial}: {step} {mark}")
            self.progress.stop_task(self.tasks[step])


def _fmt(x, digits: int = 3, scale: float = 1.0) -> str:
    import math

    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x * scale:.{digits}g}"


def results_table(records: list, title: str):
    """The runs as a table: serial, kind and verdict, k6 (display unit), p-p before/after,
    improvement, wall time, start."""
    from rich import box
    from rich.table import Table

    from eol_cal.rendering.display import display_unit

    k6_unit, k6_scale = display_unit("N*m/A")
    table = Table(title=title, box=box.SIMPLE_HEAD, padding=(0, 1), pad_edge=False, show_edge=False)
    for col, just in (("serial", "left"), ("verdict", "left"), (f"k6\n{k6_unit}", "right"), ("p-p %\nbefore", "right"),
                      ("p-p %\nafter", "right"), ("impr.\n%", "right"), ("wall\ns", "right"), ("started\nUTC", "left")):
        table.add_column(col, justify=just, no_wrap=True)
    colour = {"pass": "green", "fail": "yellow", "error": "red"}
    for r in records:
        verdict = styled((r.verdict, colour.get(r.verdict, "white")))
        if r.kind == "refusal":
            verdict = styled(("refused", "red"), f" ({', '.join(r.refusal_codes)})")
        elif r.kind != "production":
            verdict = styled(f"{r.kind}: ", (r.verdict, colour.get(r.verdict, "white")))
        table.add_row(r.serial, verdict, _fmt(r.value("k6"), 4, k6_scale), _fmt(r.value("pp_before_pct")),
                      _fmt(r.value("pp_after_pct")), _fmt(r.value("improvement_pct")), f"{r.total_s:.1f}",
                      r.started_at[5:19].replace("T", " "))
    return table


#: the ``schema`` of ``eol-cal run --json``
RUN_SCHEMA = "eol-cal/run/1"


def _print_verdict(rec, spooled: bool = True) -> None:
    """The verdict as soon as the cycle knows it (the report and the database come after)."""
    if rec.kind == "refusal":  # only a refusal can be the gate's (its module loads the database: 0.2 s)
        from eol_cal.msa.gate import gate_refusal

        if gate_refusal(rec) is not None:  # the master gate refused at once: its one line follows
            return
    what = "REFUSED" if rec.kind == "refusal" else rec.verdict.upper()
    colour = {"pass": "green", "fail": "yellow"}.get(rec.verdict, "red")
    # the console takes no markup (a serial or reason is printed as it is): the colour is a style
    console.print(styled((f"{rec.serial}: {what}", f"bold {colour}"),
                         f" ({'; '.join(rec.reasons)})" if rec.reasons else ""))


def _print_outcome(out, as_json: bool) -> None:
    rec = out.record
    if as_json:
        print_json({"schema": RUN_SCHEMA, "record": rec.to_json(),
                    "saved": {"where": out.saved.where, "path": out.saved.path, "why": out.saved.why},
                    "report": str(out.report_html) if out.report_html else None, "exit_code": out.exit_code})
        return
    from eol_cal.msa.gate import gate_refusal

    if (line := gate_refusal(rec)) is not None:  # the master gate: one line, nothing else happened
        console.print(line)
        return
    console.print(results_table([rec], f"eol-cal run: {rec.serial} ({rec.limits.variant if rec.limits else '-'})"))
    for reason in rec.reasons:
        console.print(f"  {'refused' if rec.kind == 'refusal' else rec.verdict}: {reason}")
    if rec.kind == "refusal":
        console.print("  nothing was written to the ECU: the run is kept as a refusal, not as the motor's result")
    if rec.safe_state:
        console.print(f"  dyno safe state: {rec.safe_state}")
    if rec.ecu_active.block == "uncompensated":
        console.print(f"  ECU: the uncompensated block is active (sequence {rec.ecu_active.sequence}): "
                      "the motor is not calibrated")
    steps = ", ".join(f"{s.step} {s.seconds:.2f} s" for s in rec.steps if s.seconds is not None)
    console.print(f"  steps: {steps}")
    if out.report_html:
        console.print(f"  report: {out.report_html}")
    where = f"database {out.saved.path}" if out.saved.where == "db" else f"SPOOL {out.saved.path} ({out.saved.why})"
    console.print(f"  record {rec.run_id} -> {where}")


def rebuilt_pages(records) -> None:
    """The pages of flushed runs whose station ended before it wrote them, rebuilt from their records."""
    from eol_cal.station.report_files import rebuild_missing

    for page in rebuild_missing(records):
        err_console.print(f"report rebuilt from its record (no plots): {page}")


def flush_first(db: Path, spool_dir: Path | None, timeout: float) -> None:
    from eol_cal.records.connect import db_shown
    from eol_cal.records.spool import flush_spool

    res = flush_spool(db, spool_dir, timeout)
    rebuilt_pages(res.records)
    for bad in res.bad_files:
        err_console.print(styled((f"spool: {bad}; left alone", "yellow")))
    if res.in_flight:
        err_console.print(f"{res.in_flight} spooled record(s) still being written by a running station: left for it")
    if res.flushed_files:
        err_console.print(f"flushed {res.flushed_files} spooled record(s) into {db_shown(db)}")
    elif res.remaining:
        err_console.print(styled((f"{res.remaining} spooled record(s) still waiting for {db_shown(db)}: {res.error}",
                                  "yellow")))


def write_demo_limits(path: Path) -> None:
    """The demo's limits file (atomically: no output replaces an input or a database)."""
    from eol_cal.infra.atomic import atomic_write
    from eol_cal.errors import InputError, WriteError

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, DEMO_LIMITS)
    except (OSError, WriteError) as exc:
        raise InputError(str(path.parent), None, f"cannot write: {exc}") from None


#: each `run` option's settings key (eol_cal.station.settings.KEYS); an option given on the command
#: line overrides the settings file and the environment
OPTION_KEYS = {
    "address": "dyno.address", "interface": "can.interface", "channel": "can.channel", "bitrate": "can.bitrate",
    "can_config": "can.config", "limits_file": "limits", "variant": "variant", "db": "db", "profile": "profile",
    "verify": "verify", "key_file": "key_file", "key_algo": "key_algo", "report_dir": "report_dir", "spool_dir": "spool_dir",
    "db_timeout": "db_timeout_s", "rate_hz": "rate_hz", "dyno_timeout": "dyno.timeout_s", "motor_file": "motor",
    "bench_name": "bench", "station_id": "station_id", "register_map": "dyno.register_map",
    "estimator": "estimator", "read_back": "flash.read_back", "lead_in": "dyno.lead_in",
}
#: what `run` without --station needs, by option, for its one-line refusal
REQUIRED_OPTIONS = {"address": "--dyno HOST:PORT", "limits_file": "--limits FILE", "db": "--db PATH|URL",
                    "key_file": "--key-file FILE"}


def given_options(ctx: click.Context, values: dict, keys: dict[str, str]) -> dict[str, object]:
    """The options typed on the command line, by settings key (defaults and unset ones left out)."""
    from click.core import ParameterSource

    out: dict[str, object] = {}
    for name, key in keys.items():
        value = values.get(name)
        if value is None or ctx.get_parameter_source(name) is not ParameterSource.COMMANDLINE:
            continue
        out[key] = value if isinstance(value, (int, float)) else str(value)
    return out


def load_station(ctx: click.Context, station_file: str | None, values: dict, keys: dict[str, str]):
    """The checked settings: the file (``--station``), the environment, and the options given (highest)."""
    import os

    from eol_cal.errors import InputError
    from eol_cal.station.settings import env_name, load_settings

    given = given_options(ctx, values, keys)
    if station_file is None:
        # without a settings file, `run` needs its options (or their variables) as it always did
        for name, option in REQUIRED_OPTIONS.items():
            key = keys[name]
            if key == "key_file" and ("key_algo" in given or os.environ.get(env_name("key_algo"))):
                continue  # the OEM's algorithm may need no secret
            if key not in given and not os.environ.get(env_name(key)):
                raise InputError(None, option.split()[0][2:], f"required: give {option} (or set ${env_name(key)}), "
                                                              "or a settings file with --station")
    return load_settings(station_file, given=given, optional=() if station_file else ("station_id",))


@click.command("run")
@click.option("--station", "station_file", type=click.Path(dir_okay=False), default=None,
              help="Station settings TOML (docs/station.md, First real station); options given here override it.")
@click.option("--dyno", "address", default=None, metavar="HOST[:PORT]",
              help="Modbus TCP address of the dyno (port 502 when none is given).")
@click.option("--interface", "-i", default=None,
              help="python-can interface of the ECU's bus (socketcan, pcan, vector, remote...).")
@click.option("--channel", "-c", default=None, help="python-can channel (can0, PCAN_USBBUS1, ws://127.0.0.1:54701/...).")
@click.option("--bitrate", type=int, default=None, help="CAN bit rate (bit/s).")
@click.option("--can-config", type=click.Path(dir_okay=False), help="python-can configuration file; options given here win.")
@click.option("--limits", "limits_file", default=None, type=click.Path(dir_okay=False),
              help="Limits TOML ([variant.NAME] tables).")
@click.option("--variant", default=None, help="Product variant in the limits file (default: its default_variant or only one).")
@click.option("--db", default=None, type=RECORDS_DB, help="Records database: a SQLite file (WAL) or postgresql://user@host:port/db.")
@click.option("--serial", required=True, help="Serial of the motor on the dyno (1-16 ASCII characters).")
@click.option("--station-id", default=None, help="Station id for the record (settings key station_id).")
@click.option("--operator", default=None, help="Operator for the record.")
@click.option("--profile", default="eol-default", show_default=True, help="Built-in test profile or a TOML profile file.")
@click.option("--verify", type=click.Choice(["point", "full"]), default="point", show_default=True,
              help="Compensated acquisition: the profile's segments at the operating point (both directions), "
                   "or the full profile.")
@click.option("--key-file", type=click.Path(dir_okay=False),
              help="ECU security secret, 16 bytes hex (or $EOL_CAL_KEY_FILE).")
@key_algo_option
@click.option("--report-dir", default="reports", show_default=True, type=click.Path(file_okay=False, path_type=Path),
              help="Each run gets a directory here: captures, fit, block, plots, report.html/json.")
@click.option("--spool-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Where records wait when the database cannot be written "
                   "[default: $EOL_CAL_SPOOL or ~/.local/state/eol-cal/spool].")
@click.option("--db-timeout", type=click.FloatRange(0.0, 600.0), default=5.0, show_default=True,
              help="Seconds to wait for a database lock before spooling.")
@click.option("--rate", "rate_hz", type=click.IntRange(1, 1_000_000), default=10000, show_default=True,
              help="Capture sample rate (Hz).")
@click.option("--dyno-timeout", type=click.FloatRange(0.01, 60.0), default=1.0, show_default=True,
              help="Per-request Modbus timeout (s).")
@click.option("--motor", "motor_file", type=click.Path(dir_okay=False),
              help="Motor TOML overriding the paper preset (poles, N_enc, f_pwm, current_bw_hz, ...): the motor type on "
                   "the station.")
@click.option("--bench", "bench_name", default="paper", show_default=True, metavar="NAME|FILE.toml",
              help="The dyno bench (eol_cal/benches/NAME.toml or a TOML file) whose response the fit divides out; "
                   "'none' = rigid.")
@estimator_option("both blocks of the cycle carry them [default: the variant's, limits key estimator].",
                  default=None)
@click.option("--read-back", type=click.Choice(["before-crc", "off"]), default=None,
              help="Read each flashed block back before its CRC is written [default: before-crc, settings key "
                   "flash.read_back]; off leaves the check to the ECU's CRC routine (docs/station.md).")
@click.option("--lead-in", type=click.Choice(["settle", "at-point", "off"]), default=None,
              help="Turn the shaft for the ECU's settling after each reset before its capture counts [default: "
                   "settle, settings key dyno.lead_in: an identifying ECU at 200 rpm first]; at-point turns it all "
                   "at the capture's first point; off captures at once (docs/station.md, \"Lead-in\").")
@click.option("--json", "as_json", is_flag=True, help="Print the run record as JSON.")
@register_map_option
@click.pass_context
@handle_errors
@exchange_log_options
@io_paths(inputs=("station_file", "can_config", "limits_file", "key_file", "motor_file", "profile"),
          output_dirs=("report_dir", "spool_dir"), databases=("db",))
def run_cmd(ctx, station_file, serial, operator, as_json, **options) -> None:
    """Calibrate one motor: acquire, fit, table, flash, acquire compensated, judge, record, report.

    Settings come from the options, else their environment variables (EOL_CAL_DYNO_ADDRESS,
    EOL_CAL_LIMITS, ...), else the --station file. Exit 0 pass, 1 fail (limits), 2 error (the
    dyno is left stopped and disabled; the record is written all the same). When the database
    cannot be written the record goes to the spool and the next run (or `eol-cal records
    --flush`) writes it in.
    """
    loop_kernels()
    from eol_cal.analysis.fit.cache import default_cache_dir
    from eol_cal.station.configure import for_motor, station_config
    from eol_cal.station.cycle import run_motor
    from eol_cal.station.settings import settings_paths

    settings = load_station(ctx, station_file, options, OPTION_KEYS)
    check_more(*settings_paths(settings))  # the settings' paths against the options' (--log-file too)
    # switched on by the helper thread: importing JAX costs a second
    cfg = for_motor(station_config(settings, operator=operator, cache_dir=default_cache_dir()), serial)
    quiet_logs()
    # Records spooled earlier go into the database beside the cycle, not before it: the database
    # library loads and the inserts run while the cycle waits on the dyno and the ECU. (The
    # spool is listed as the flush starts: this run's record, spooled at its verdict, is not
    # among them.)
    flush = threading.Thread(target=flush_first, args=(cfg.db, cfg.spool_dir, cfg.db_timeout_s),
                             name="spool-flush", daemon=True)
    flush.start()
    try:
        with StepProgress(serial, enabled=not as_json) as progress:
            out = run_motor(cfg, progress, on_verdict=None if as_json else _print_verdict)
    except KeyboardInterrupt:
        # run_motor has recorded the run as an error and commanded the dyno's safe state
        err_console.print("interrupted: the dyno was sent to its safe state and the run recorded (an error, unless it had ended)")
        raise CommandExit(2) from None
    flush.join()
    _print_outcome(out, as_json)
    raise CommandExit(out.exit_code)


@click.command("demo")
@click.option("--motors", type=click.IntRange(1, 100), default=3, show_default=True, help="Motors to calibrate.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=Path("eol-cal-demo"),
              show_default=True, help="Directory for the database, reports, captures and flash images.")
@click.option("--profile", default="eol-default", show_default=True, help="Test profile.")
@click.option("--seed", type=int, default=1, show_default=True, help="Seed of the first motor (the next ones count up).")
@click.option("--db", default=None, type=RECORDS_DB,
              help="Records database (file or postgresql://user@host:port/db) [default: OUT/results.sqlite].")
@realtime_option
@register_map_option
@handle_errors
@exchange_log_options
@io_paths(inputs=("profile", "register_map"), output_dirs=("out_dir",), databases=("db",))
def demo_cmd(motors, out_dir, profile, seed, db, realtime, register_map) -> None:
    """Run the end-of-line line on simulators: no hardware, no arguments needed.

    Per motor it starts an ECU simulator (UDS over ISO-TP, served on 127.0.0.1 through
    python-can-remote) and a dyno simulator (Modbus TCP on 127.0.0.1, the built-in plant, reading
    the ECU's flash to know the compensation), runs `eol-cal run`'s cycle, and stops both.
    Then it prints the results table and where the reports are.
    """
    import time

    loop_kernels()  # the plant (in this process) and the fit's frame
    from cli.fit import enable_jax_cache
    from eol_cal.ecu import protocol as P
    from eol_cal.ecu.client import hmac_seed_to_key
    from eol_cal.sim.loopback import loopback_station
    from eol_cal.records.limits import load_limits
    from eol_cal.station.cycle import run_motor
    from eol_cal.station.run import StationConfig

    limits_path = out_dir / "limits.toml"
    db = out_dir / "results.sqlite" if db is None else db
    # what the demo writes by default (its limits: written, then read), against its database, given
    # or its own, before anything is written
    check_io((), (limits_path, out_dir / "lot.html"), (out_dir / "reports", out_dir / "spool", out_dir / "sim"), (db,))
    check_more(databases=(db,))
    write_demo_limits(limits_path)
    limits = load_limits(limits_path)
    regmap = load_map(register_map)
    quiet_logs()
    cache_dir = enable_jax_cache()
    t0 = time.perf_counter()
    err_console.print(f"eol-cal demo: {motors} motor(s), profile {profile}, limits {limits_path} ({limits.variant}); "
                      "the first motor also compiles the plant and the fit (cached for later runs)")
    outcomes = []
    for k in range(motors):
        serial = f"DEMO-{seed + k:04d}"
        with loopback_station(serial, seed + k, out_dir / "sim", register_map=regmap, realtime=realtime,
                              prepare=limits.estimator_options) as st:
            err_console.print(f"{serial}: dyno simulator on {st.dyno_address}, ECU simulator on {st.can_channel}")
            cfg = StationConfig(
                serial=serial, dyno=st.dyno_config(regmap),
                open_bus=st.open_bus, ecu_timing=st.ecu_timing,
                seed_to_key=hmac_seed_to_key(P.DEV_SECRET), limits=limits, db=db, report_dir=out_dir / "reports",
                profile=profile, spool_dir=out_dir / "spool", cache_dir=cache_dir,
                station={"dyno": st.dyno_address, "can": {"interface": "remote", "channel": st.can_channel}, "demo": True},
            )
            with StepProgress(serial) as progress:
                out = run_motor(cfg, progress)
        outcomes.append(out)
        rec = out.record
        err_console.print(f"{serial}: {rec.verdict}" + (f" ({'; '.join(rec.reasons)})" if rec.reasons else ""))
    wall = time.perf_counter() - t0
    console.print(results_table([o.record for o in outcomes], f"eol-cal demo: {motors} motor(s) in {wall:.1f} s"))
    from eol_cal.lot.lot_page import write_lot_page
    from eol_cal.records.connect import db_label, db_shown
    from eol_cal.records.query import query_records

    lot_page = write_lot_page(query_records(db), out_dir / "lot.html", title=f"{db_label(db)} (eol-cal demo)",
                              filters={"variant": None, "since": None, "until": None, "station": None})
    console.print("per-motor reports (one self-contained file each; open in a browser):")
    for o in outcomes:
        console.print(f"  {o.record.serial}: {o.report_html}")
    shown = db_shown(db)
    console.print(f"lot page: {lot_page} (eol-cal lot report --db {shown} -o lot.html)")
    console.print(f"records: {shown} (eol-cal records --db {shown}); limits: {limits_path}")
    console.print("the same cycle on a real station: eol-cal run --dyno HOST:PORT --interface I --channel C "
                  f"--limits {limits_path} --db results.sqlite --serial S --key-file KEY")
    raise CommandExit(max(o.exit_code for o in outcomes))


COMMANDS = [run_cmd, demo_cmd]
