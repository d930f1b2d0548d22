"""A what-if lot's batch runs its motors' cycles in threads of their own
(eol_cal/station/whatif.py simulate_batch): a motor's record does not depend on its batch (the
motors beside it, their number, the threads' order), to the same-record test's tolerance."""

from __future__ import annotations

from pathlib import Path

import pytest

from eol_cal.records.record import RunRecord
from eol_cal.sim.plant_instruments import plant_instruments
from eol_cal.station import whatif
from eol_cal.station.whatif import simulate_batch
from eol_cal.station.whatif_plan import LotPlan
from test_lot_simulate import LIMITS, PROFILE
from test_whatif_same_record import _mismatches

# The Dask workers inherit the suite's JAX cache (tests/conftest.py: its own directory, never ~/.cache),
# so they load the programs other tests compiled instead of compiling them again


@pytest.mark.slow  # five station cycles on the plant (a batch of 4 in threads, one alone)
def test_a_motor_in_a_batch_of_one_and_of_four_gives_the_same_record(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(whatif, "MOTOR_THREADS", 3)  # the threaded path, whatever the default
    (tmp_path / "short.toml").write_text(PROFILE)
    plan = LotPlan("B", "default", str(LIMITS), "EPS-STD", 4, seed=21, profile=str(tmp_path / "short.toml"), batch=4)
    four = simulate_batch(plan, [0, 1, 2, 3], plant_instruments)
    (alone,) = simulate_batch(plan, [2], plant_instruments)
    recs = [RunRecord.from_json(d) for d in four]
    assert [r.serial for r in recs] == [plan.serial(i) for i in range(4)]
    assert len({r.value("k6") for r in recs}) == 4  # four motors, not one four times
    assert all(r.verdict in ("pass", "fail") for r in recs)
    # the same motor: its run id, station and every figure but the runs' times and paths
    assert alone["run_id"] == four[2]["run_id"] and alone["station"] == four[2]["station"]
    assert _mismatches(alone, four[2]) == []


def _failing_second_motor(serial: str, *args, **kw):
    """plant_instruments, but motor 1's dyno fails at its first acquisition."""
    cm = plant_instruments(serial, *args, **kw)
    if not serial.endswith("-000001"):
        return cm

    class Failing:
        def __enter__(self):
            inst = cm.__enter__()

            def acquire(*a, **k):
                raise OSError("dyno gone")

            inst.acquire = acquire
            return inst

        def __exit__(self, *exc):
            return cm.__exit__(*exc)

    return Failing()


@pytest.mark.slow  # two station cycles on the plant
def test_a_motor_that_errs_leaves_the_others_of_its_batch_as_they_are(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(whatif, "MOTOR_THREADS", 2)
    (tmp_path / "short.toml").write_text(PROFILE)
    plan = LotPlan("E", "default", str(LIMITS), "EPS-STD", 2, seed=21, profile=str(tmp_path / "short.toml"), batch=2)
    ok, failed = (RunRecord.from_json(d) for d in simulate_batch(plan, [0, 1], _failing_second_motor))
    assert failed.verdict == "error" and failed.error is not None and "dyno gone" in failed.error.message
    assert failed.error.step == "acquire" and {s.step: s.ok for s in failed.steps}["acquire"] is False
    assert ok.verdict in ("pass", "fail") and ok.fit is not None and ok.metrics is not None
