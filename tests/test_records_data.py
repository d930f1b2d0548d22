"""The database is data (issue 36, class 3) and statistics that mean what they say (class 4).

Class 3: a records database holding stored objects eol-cal did not create (a trigger, a view)
is refused by every read, write and migration, naming them, on SQLite and PostgreSQL; stored
baseline rows are checked like any input (sigma 0 or text: a refusal, not a traceback) and a
newer baseline layout is refused on read as the docs say.

Class 4: `lot baseline` by kind, station(s) and instants; a phase spread round the circle gets no
limits; an amplitude's LCL stops at its natural zero and says so.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import sqlalchemy as sa
from click.testing import CliRunner

from eol_cal.sim.run_records import make_record
from cli.main import cli
from eol_cal.lot.spc import freeze_line
from eol_cal.records.connect import engine
from eol_cal.records.migrations import migrate
from eol_cal.records.write import insert_records


def _exec(db, *statements: str) -> None:
    eng = engine(db)
    with eng.begin() as con:
        for s in statements:
            con.execute(sa.text(s))
    eng.dispose()


def _lot(db, n: int = 30, station: str = "EOL-1", kind: str = "production", day: str = "2026-11-02") -> list:
    rng = np.random.default_rng(3)
    recs = [make_record(f"S-{station}-{kind}-{i}", started=f"{day}T{8 + i // 60:02d}:{i % 60:02d}:00.000+00:00",
                        station=station, kind=kind, k6=float(6.2e-4 + 1e-5 * rng.standard_normal()))
            for i in range(n)]
    insert_records(db, recs)
    return recs


def _trigger(db) -> str:
    if "://" in str(db):
        _exec(db, "CREATE FUNCTION evil() RETURNS trigger AS $$ BEGIN RETURN NEW; END $$ LANGUAGE plpgsql",
              "CREATE TRIGGER sneaky AFTER INSERT ON runs FOR EACH ROW EXECUTE FUNCTION evil()")
        return "trigger sneaky on runs"
    _exec(db, "CREATE TRIGGER sneaky AFTER INSERT ON runs BEGIN DELETE FROM runs; END")
    return "trigger sneaky"


@pytest.mark.parametrize("what", ["trigger", "view"])
def test_a_database_with_foreign_objects_is_refused_by_reads_writes_and_migrations(records_db, tmp_path, what):
    recs = _lot(records_db, 5)
    if what == "trigger":
        named = _trigger(records_db)
    else:
        _exec(records_db, "CREATE VIEW peek AS SELECT serial FROM runs")
        named = "view peek"
    for args in (["records", "--db", str(records_db)], ["lot", "stats", "--db", str(records_db)],
                 ["records", "migrate", "--db", str(records_db)], ["gate", "history", "--db", str(records_db)],
                 ["lot", "baseline", "--db", str(records_db), "--name", "b", "--min-n", "2"],
                 ["msa", "type1", "--db", str(records_db), "--serial", recs[0].serial]):
        res = CliRunner().invoke(cli, args)
        assert res.exit_code == 2, (args, res.output)
        assert named in res.output and "did not create" in res.output and "Traceback" not in res.output, res.output
    # a station's write is not made into it (its trigger would run): the record goes to the spool
    from eol_cal.records.spool import save_record

    saved = save_record(make_record("S-new"), records_db, tmp_path / "spool")
    assert saved.where == "spool"
    with pytest.raises(Exception, match="did not create"):
        migrate(records_db)


@pytest.mark.parametrize(("column", "value", "named"), [
    ("sigma", "0", "sigma"), ("sigma", "'abc'", "sigma"), ("center", "'x'", "center"), ("quantity", "'volts'", "quantity"),
    ("n", "-3", "'n'"),
])
def test_stored_baseline_rows_are_checked_like_any_input(tmp_path, column, value, named):
    db = tmp_path / "r.sqlite"
    _lot(db, 30)
    assert CliRunner().invoke(cli, ["lot", "baseline", "--db", str(db), "--name", "b"]).exit_code == 0
    _exec(db, f"UPDATE baseline_lines SET {column} = {value} WHERE quantity = 'k6'")
    res = CliRunner().invoke(cli, ["lot", "stats", "--db", str(db), "--baseline", "b"])
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    assert "baseline 'b'" in res.output and named in res.output


def test_a_newer_layout_is_refused_on_reading_a_baseline(records_db):
    _lot(records_db, 30)
    assert CliRunner().invoke(cli, ["lot", "baseline", "--db", str(records_db), "--name", "b"]).exit_code == 0
    _exec(records_db, "UPDATE schema_version SET version = 7")
    res = CliRunner().invoke(cli, ["lot", "stats", "--db", str(records_db), "--baseline", "b"])
    assert res.exit_code == 2 and "schema version 7 is newer than this tool" in res.output, res.output


def test_lot_baseline_by_kind_stations_and_instants(records_db):
    _lot(records_db, 30, "EOL-1")
    _lot(records_db, 30, "EOL-2")
    _lot(records_db, 30, "EOL-3")
    _lot(records_db, 30, "sim:W", kind="simulated")
    run = CliRunner().invoke
    res = run(cli, ["lot", "baseline", "--db", str(records_db), "--name", "two", "--station", "EOL-1", "--station",
                    "EOL-2", "--json"])
    doc = json.loads(res.stdout)
    assert res.exit_code == 0 and doc["runs"] == 60 and doc["filters"]["stations"] == ["EOL-1", "EOL-2"]
    assert {line["station"] for line in doc["lines"]} == {"EOL-1", "EOL-2"}
    res = run(cli, ["lot", "baseline", "--db", str(records_db), "--name", "what-if", "--kind", "simulated", "--json"])
    doc = json.loads(res.stdout)
    assert res.exit_code == 0 and doc["runs"] == 30 and doc["filters"]["kind"] == "simulated"
    # instants: 08:00-08:24:59 UTC is 25 runs a station; the same instant in another offset selects the same runs
    res = run(cli, ["lot", "baseline", "--db", str(records_db), "--name", "morning", "--station", "EOL-3",
                    "--since", "2026-11-02T09:00+01:00", "--until", "2026-11-02T08:25:00Z", "--json"])
    doc = json.loads(res.stdout)
    assert res.exit_code == 0 and doc["runs"] == 25, res.output
    assert doc["filters"]["since"] == "2026-11-02T08:00:00+00:00"
    # a wall time without its offset is not an instant; until before since is refused
    for args in (["--since", "2026-11-02T08:00"], ["--since", "2026-11-03", "--until", "2026-11-02"]):
        res = run(cli, ["lot", "baseline", "--db", str(records_db), "--name", "x", *args])
        assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    # the stats of the simulated lot judged against its own kind's baseline
    res = run(cli, ["lot", "stats", "--db", str(records_db), "--kind", "simulated", "--baseline", "what-if", "--json"])
    judged = {j["quantity"]: j for j in json.loads(res.stdout)["judged"]}
    assert res.exit_code in (0, 1) and judged["k6"]["station"] == "sim:W" and judged["k6"]["center"] is not None


def test_no_control_limits_for_a_phase_spread_round_the_circle():
    """A baseline of phase_c6 spread round the circle (R = 0.25) got -170 to +322 deg."""
    rng = np.random.default_rng(5)
    spread = rng.uniform(-math.pi, math.pi, 60)
    line = freeze_line(spread, circular=True, min_n=25)
    assert line.center is None and line.ucl is None and "spread round the circle" in str(line.reason)
    tight = 0.3 + 0.05 * rng.standard_normal(60)
    line = freeze_line(tight, circular=True, min_n=25)
    assert line.center is not None and line.ucl - line.lcl < 2 * math.pi


def test_an_amplitudes_lcl_stops_at_the_natural_zero_and_says_so():
    rng = np.random.default_rng(6)
    c6 = np.abs(2e-4 + 2e-4 * rng.standard_normal(40))  # an amplitude near zero: mean - 3 sigma < 0
    line = freeze_line(c6, min_n=25, lower_bound=0.0)
    assert line.center - 3 * line.sigma < 0 and line.lcl == 0.0 and "natural zero" in str(line.note)
    free = freeze_line(c6, min_n=25)  # a quantity without a natural bound keeps its LCL
    assert free.lcl < 0 and free.note is None


def test_imr_charts_by_run_order_with_zone_lines_and_a_pareto_of_runs():
    """The I-MR chart was drawn against clock time (runs close together stacked) without the
    zones rules 5 and 6 count in; the Pareto counted codes on a fractional axis."""
    from eol_cal.lot.lot_page import control_figure, pareto_figure
    from eol_cal.lot.stats import pareto_of

    rng = np.random.default_rng(8)
    # 30 runs within one second, then one a day later: by run order each is one step
    times = [f"2026-11-02T08:00:00.{i:03d}+00:00" for i in range(30)] + ["2026-11-03T08:00:00.000+00:00"]
    recs = [make_record(f"S-{i}", started=t, k6=float(6.2e-4 + 1e-5 * rng.standard_normal()))
            for i, t in enumerate(times)]
    fig, _titles = control_figure(recs, "EOL-1", None, min_n=25)
    ax_i = fig.axes[0]
    (points,) = [c for c in ax_i.collections if c.get_gid() == "i-k6"]
    assert points.get_offsets()[:, 0].tolist() == list(range(1, 32))
    gids = {line.get_gid() for line in ax_i.lines}
    assert {"zone-k6-1+", "zone-k6-1-", "zone-k6-2+", "zone-k6-2-", "cl-k6-center", "cl-k6-ucl"} <= gids
    # an amplitude whose centre - 3 sigma is below zero: the LCL at zero, said so, no zone below it
    low = [make_record(f"L-{i}", started=t, pp_after=float(abs(0.05 + 0.08 * rng.standard_normal())) + 1e-3)
           for i, t in enumerate(times)]
    fig, _titles = control_figure(low, "EOL-1", None, min_n=25)
    ax_pp = fig.axes[1]
    lcl = [line.get_ydata()[0] for line in ax_pp.lines if line.get_gid() == "cl-pp_after_pct-lcl"]
    assert lcl == [0.0] and any(t.get_gid() == "lcl-floor-pp_after_pct" for t in ax_pp.texts)
    # Pareto by runs: a run naming two codes counts once in the cumulative share; whole runs on the axis
    causes = pareto_of([["wrong_serial", "key_refused"], ["wrong_serial"], ["dyno_fault"]])
    assert causes == [("wrong_serial", 2, pytest.approx(2 / 3)), ("dyno_fault", 1, pytest.approx(1.0)),
                      ("key_refused", 1, pytest.approx(1.0))]
    fig = pareto_figure(causes)
    fig.canvas.draw()
    ticks = [t for t in fig.axes[0].get_xticks() if t >= 0]
    assert ticks and all(float(t).is_integer() for t in ticks)


def test_statistics_of_a_database_without_the_tables_are_refused_in_one_line(records_db, tmp_path):
    """On PostgreSQL `lot baseline` of an empty database gave a psycopg traceback (SQLite: one line)."""
    if "://" not in str(records_db):
        import sqlite3

        sqlite3.connect(records_db).close()  # an empty file
    for args in (["lot", "baseline", "--name", "b"], ["lot", "stats"], ["msa", "type1", "--serial", "M"]):
        res = CliRunner().invoke(cli, [*args[:2], "--db", str(records_db), *args[2:]])
        assert res.exit_code == 2 and isinstance(res.exception, SystemExit), res.output
        assert "Traceback" not in res.output and "no runs table" in res.output, res.output
