"""Two lots side by side (:func:`eol_cal.lot.compare.compare_lots`, `eol-cal lot diff --lot A --lot
B`) on records made in the test: the motors matched by serial (or by their number in a simulated
lot), those whose verdict or failed limits changed listed, a lot with no runs refused with the
field. In-process on SQLite: the fast loop's test (two lots simulated on a Dask cluster are in
test_lot_simulate.py)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from eol_cal.sim.run_records import make_record
from cli.main import cli
from eol_cal.errors import InputError
from eol_cal.lot.compare import compare_lots, motor_key
from eol_cal.schemas import validator
from eol_cal.records.write import insert_records


def _lot(station: str, failing: set[str], *, serials: tuple[str, ...] = ("M-1", "M-2", "M-3")) -> list:
    return [make_record(s, station=station, kind="simulated", started=f"2026-11-22T10:00:0{i}.000+00:00",
                        pp_after=50.0 if s in failing else None) for i, s in enumerate(serials)]


@pytest.fixture
def db(tmp_path: Path) -> Path:
    path = tmp_path / "r.sqlite"
    # lot B: M-2 fails the compensated ripple that passed in lot A; M-4 only in B
    insert_records(path, _lot("sim:A", set()) + _lot("sim:B", {"M-2"}, serials=("M-1", "M-2", "M-3", "M-4")))
    return path


def test_the_motors_whose_verdict_changed_are_listed(db: Path):
    doc = compare_lots(db, ["sim:A", "sim:B"])
    assert doc["compared"] == 3 and doc["only_in_one"] == 1
    assert [c["motor"] for c in doc["changes"]] == ["M-2"]
    change = doc["changes"][0]
    assert change["verdicts"] == ["pass", "fail"] and change["no_longer_failing"] == []
    assert change["newly_failing"] and change["pp_after_pct"][1] == pytest.approx(50.0)
    assert [lot["runs"] for lot in doc["lots"]] == [3, 4]


def test_cli_lot_diff_of_two_lots_validates_and_refuses_an_empty_lot(db: Path):
    runner = CliRunner()
    res = runner.invoke(cli, ["lot", "diff", "--db", str(db), "--lot", "sim:A", "--lot", "sim:B", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    validator("lot-compare").validate(doc)
    assert doc["compared"] == 3
    with pytest.raises(InputError, match="no simulated runs of station 'sim:C'"):
        compare_lots(db, ["sim:A", "sim:C"])
    with pytest.raises(InputError, match="give two lots"):
        compare_lots(db, ["sim:A"])
    res = runner.invoke(cli, ["lot", "diff", "--db", str(db), "--lot", "sim:A", "--lot", "sim:C"])
    assert res.exit_code == 2 and "sim:C" in res.output


def test_a_simulated_motor_is_matched_by_its_number_not_its_serial():
    rec = make_record("A-000007", kind="simulated")
    drawn = dataclasses.replace(rec, station=dataclasses.replace(rec.station, extra={"simulated": {"spread_seed": 12}}))
    assert motor_key(rec) == "A-000007" and motor_key(drawn) == "seed 12"
