"""The operator loop's first line names the station's master gate wherever its rules live: the
records database's rules count as the settings' do (a station whose gate was set with `eol-cal
gate set` showed no line, though every run was gated)."""

from __future__ import annotations

from types import SimpleNamespace

from cli.operator import _master_status
from eol_cal.msa.master import MasterSettings
from eol_cal.msa.rules import change

RULES = MasterSettings("M-MASTER", {"k6": 0.62}, {"k6": 0.05}, every_h=8.0, source="test")


def _cfg(db, station: str | None, master: MasterSettings | None = None):
    return SimpleNamespace(db=str(db), station={} if station is None else {"id": station}, master=master,
                           db_timeout_s=5.0)


def test_rules_only_in_the_database_are_shown_with_the_gate_closed(tmp_path):
    db = tmp_path / "r.sqlite"
    change(db, "EOL-7", RULES, set_by="qe")
    line = _master_status(_cfg(db, "EOL-7"))
    assert line is not None and line.startswith("master M-MASTER (every 8 h): ") and "master check due" in line


def test_a_station_without_rules_shows_no_line_and_another_stations_rules_do_not_count(tmp_path):
    db = tmp_path / "r.sqlite"
    change(db, "EOL-8", RULES, set_by="qe")
    assert _master_status(_cfg(db, "EOL-7")) is None
    assert _master_status(_cfg(tmp_path / "none.sqlite", None)) is None


def test_settings_that_differ_from_the_database_rules_are_named_on_the_line(tmp_path):
    db = tmp_path / "r.sqlite"
    change(db, "EOL-7", RULES, set_by="qe")
    other = MasterSettings("M-OTHER", {"k6": 0.62}, {"k6": 0.05}, every_h=8.0, source="station.toml")
    line = _master_status(_cfg(db, "EOL-7", other))
    assert line is not None and line.startswith("master gate: ") and "station.toml" in line
