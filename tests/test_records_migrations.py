"""One version and one migration for every table of the records database (issue 39, item 2): a
database written by eol-cal up to schema version 4, its baseline and gate tables each with their
own version table, is brought to version 5 by `eol-cal records migrate` in one transaction, on
SQLite and on a real PostgreSQL server; every writer refuses it until then."""

from __future__ import annotations

import sqlalchemy as sa
from click.testing import CliRunner

import pytest
from eol_cal.sim.run_records import make_record
from cli.main import cli
from eol_cal.errors import InputError
from eol_cal.lot.baseline import load
from eol_cal.msa.rules import current, history
from eol_cal.records.connect import SchemaError, engine
from eol_cal.records.migrations import LOCK_ID, SCHEMA_VERSION, migrate, version_of
from eol_cal.records.query import query_records
from eol_cal.records.rows import row_of
from eol_cal.records.tables import baseline_lines, gate_rules, metadata, runs
from eol_cal.records.write import insert_records

RULES = ('{"serial": "M-MASTER", "reference": {"k6": 0.62}, "tolerance": {"k6": 0.05}, "every_h": 8, '
         '"shifts": null, "timezone": "UTC"}')


def _version_4_database(db, baseline_layout: int = 1, gate_layout: int = 1) -> list:
    """The records database eol-cal wrote up to version 4: ``runs`` at version 4 in
    ``schema_version``; ``baselines`` at its own layout (1: before ``kind`` and ``stations``) in
    ``baseline_schema_version``; ``gate_rules`` in ``gate_schema_version``; a row in each."""
    recs = [make_record(f"S-{i}", started=f"2026-11-02T08:{i:02d}:00.000+00:00", station="EOL-1") for i in range(3)]
    eng = engine(db)
    with eng.begin() as con:
        runs.create(con)
        con.exec_driver_sql("CREATE TABLE schema_version (version INTEGER NOT NULL)")
        con.exec_driver_sql("INSERT INTO schema_version (version) VALUES (4)")
        later = "" if baseline_layout == 1 else ", kind TEXT, stations TEXT"
        con.exec_driver_sql("CREATE TABLE baselines (name TEXT PRIMARY KEY, created_at TEXT NOT NULL, since TEXT, "
                            "until TEXT, variant TEXT, station TEXT, min_n INTEGER NOT NULL, runs INTEGER NOT NULL, "
                            f"tool_version TEXT{later})")
        baseline_lines.create(con)  # after baselines: its foreign key
        gate_rules.create(con)
        con.exec_driver_sql("CREATE TABLE baseline_schema_version (version INTEGER NOT NULL)")
        con.exec_driver_sql(f"INSERT INTO baseline_schema_version (version) VALUES ({baseline_layout})")
        con.exec_driver_sql("CREATE TABLE gate_schema_version (version INTEGER NOT NULL)")
        con.exec_driver_sql(f"INSERT INTO gate_schema_version (version) VALUES ({gate_layout})")
        con.execute(runs.insert(), [row_of(r) for r in recs])
        con.exec_driver_sql("INSERT INTO baselines (name, created_at, station, min_n, runs) "
                            "VALUES ('b', '2026-11-02T09:00:00.000+00:00', 'EOL-1', 2, 3)")
        con.execute(baseline_lines.insert().values(name="b", quantity="k6", variant="EPS-STD", station="EOL-1",
                                                   circular=False, n=3, center=6.2e-4, sigma=1e-5, mr_center=1.1e-5))
        con.execute(gate_rules.insert().values(station="EOL-1", seq=1, set_at="2026-11-02T07:00:00.000+00:00",
                                               set_by="qe", action="set", rules_json=RULES, tool_version="x"))
    if "://" not in str(db):
        eng.dispose()
    return recs


def _tables(db) -> set[str]:
    eng = engine(db, readonly=True)
    with eng.connect() as con:
        names = set(sa.inspect(con).get_table_names())
        v = version_of(con)
    if "://" not in str(db):
        eng.dispose()
    return names | {f"version {v}"}


def test_a_version_4_database_migrates_every_table_at_once(records_db):
    recs = _version_4_database(records_db)
    # every writer refuses it until it is migrated: a station's record, a baseline, a gate change
    with pytest.raises(SchemaError, match="schema version 4.*migrate it first"):
        insert_records(records_db, [make_record("S-new")])
    with pytest.raises(InputError, match="schema version 4.*migrate it first"):
        load(records_db, "b")
    res = CliRunner().invoke(cli, ["gate", "set", "--db", str(records_db), "--station", "EOL-2", "--by", "qe", "--serial", "M-2",
                                   "--reference", "k6=0.62", "--tolerance", "k6=0.05", "--every-h", "8"])
    assert res.exit_code == 2 and "migrate it first" in res.output, res.output
    res = CliRunner().invoke(cli, ["records", "migrate", "--db", str(records_db)])
    assert res.exit_code == 0 and f"migrated from version 4 to schema version {SCHEMA_VERSION}" in res.output, res.output
    # one version table: the baselines' and the gate's own are gone
    assert _tables(records_db) == {"runs", "baselines", "baseline_lines", "gate_rules", "schema_version",
                                   f"version {SCHEMA_VERSION}"}
    # the rows are all there, as they meant: a layout-1 baseline was of production runs of its one station
    assert sorted(r.run_id for r in query_records(records_db)) == sorted(r.run_id for r in recs)
    b = load(records_db, "b")
    assert b.filters["kind"] == "production" and b.filters["stations"] == ["EOL-1"]
    assert b.line("k6", "EPS-STD", "EOL-1").center == pytest.approx(6.2e-4)
    assert current(records_db, "EOL-1").master.serial == "M-MASTER" and len(history(records_db)) == 1
    # and every writer takes it now; a second migration finds it at the version
    assert insert_records(records_db, [make_record("S-new")]) == 1
    res = CliRunner().invoke(cli, ["gate", "set", "--db", str(records_db), "--station", "EOL-1", "--by", "qe", "--serial", "M-2",
                                   "--reference", "k6=0.62", "--tolerance", "k6=0.05", "--every-h", "8"])
    assert res.exit_code == 0 and current(records_db, "EOL-1").seq == 2, res.output
    assert migrate(records_db) == (SCHEMA_VERSION, SCHEMA_VERSION)


@pytest.mark.parametrize(("baseline_layout", "gate_layout", "named"), [(3, 1, "baseline_schema_version holds layout 3"),
                                                                       (2, 2, "gate_schema_version holds layout 2")])
def test_a_newer_table_refuses_the_migration_and_changes_nothing(records_db, baseline_layout, gate_layout, named):
    _version_4_database(records_db, baseline_layout, gate_layout)
    before = _tables(records_db)
    res = CliRunner().invoke(cli, ["records", "migrate", "--db", str(records_db)])
    assert res.exit_code == 2 and named in res.output and "Traceback" not in res.output, res.output
    assert _tables(records_db) == before and "version 4" in before  # one transaction: nothing half done


def test_a_new_database_gets_every_table_from_its_first_writer(records_db):
    insert_records(records_db, [make_record("S-1")])
    assert _tables(records_db) == set(metadata.tables) | {f"version {SCHEMA_VERSION}"}
    assert LOCK_ID == 7413001  # the one advisory lock, the one the runs table always took
