"""A record is never lost to its database (issue 23, class 3): the address is checked before
the cycle (tests/test_refused_inputs.py), and whatever keeps the record out of the database at
the end (a driver that is not installed, an address that does not parse, any other failure),
the record goes to the spool, its password masked."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from eol_cal.records import spool as spool_module
from eol_cal.records.record import RunRecord
from eol_cal.records.spool import flush_spool, save_record

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


@pytest.fixture
def record() -> RunRecord:
    return RunRecord.from_json(json.loads((FIXTURES / "run_record_demo.json").read_text()))


@pytest.mark.parametrize("db", [
    "postgresql+psycopg2://eol:secret@127.0.0.1:1/eol",  # a driver that is not installed
    "mysql://eol:secret@127.0.0.1:1/eol",
    "postgresql://eol:secret@127.0.0.1:port/eol",  # does not parse
    "sqlite:///x.sqlite",
])
def test_a_database_address_that_cannot_take_the_record_spools_it(tmp_path, record, db):
    saved = save_record(record, db, tmp_path / "spool", timeout_s=1.0)
    assert saved.where == "spool", saved
    doc = json.loads(Path(saved.path).read_text())
    assert doc["record"]["run_id"] == record.run_id
    assert "secret" not in json.dumps(doc) and "secret" not in saved.why
    res = flush_spool(db, tmp_path / "spool", timeout_s=1.0)  # still not writable: kept, no traceback
    assert res.inserted == 0 and Path(saved.path).exists()


def test_any_failure_of_the_insert_spools_the_record(tmp_path, record, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("a failure no one foresaw")

    monkeypatch.setattr(spool_module, "insert_records", broken)
    saved = save_record(record, tmp_path / "r.sqlite", tmp_path / "spool")
    assert saved.where == "spool" and "a failure no one foresaw" in saved.why
    assert Path(saved.path).exists()
