"""The station cycle as steps and one executor (issue 39, item 1): one module per step, in the
cycle's order, each a function of the context; the executor's events of a run, start and end of
every step, and an observer that fails costs neither the run nor its record. (A passing run's
events on the loopback station: tests/test_station_run.py.)"""

from __future__ import annotations

import importlib
import json
import pkgutil
import subprocess
import sys

from _station_configs import settings_refused_config
from eol_cal.records.query import query_records
from eol_cal.station import steps
from eol_cal.station.cycle import run_motor

#: the record's steps of a passing run on a station without a gate, in order
RECORDED = ("pre-flight", "prepare ECU", "acquire", "fit", "table", "flash", "acquire compensated", "metrics", "report")


def test_one_module_per_step_in_the_cycles_order():
    modules = [importlib.import_module(f"eol_cal.station.steps.{m.name}") for m in pkgutil.iter_modules(steps.__path__)]
    names = [m.NAME for m in modules]
    assert len(set(names)) == len(names) == 13 and all(callable(m.run) for m in modules)
    assert [name for name, _ in steps.MEASURING] == list(RECORDED[:-1])
    assert [fn.__module__.rsplit(".", 1)[1] for _, fn in steps.MEASURING] == [
        "check_ready", "prepare_ecu", "acquire_before", "fit_capture", "make_table", "flash_calibrated",
        "acquire_after", "measure_ripple"]


def test_a_refused_run_emits_each_steps_start_and_end_and_a_failing_observer_costs_nothing(tmp_path):
    """A motor refused at its pre-flight (estimator options that cannot be flashed: a library
    caller's settings): the pre-flight's start and failure, then the verdict, the report and the
    record, each from its step's module; an observer that raises on every event changes nothing."""
    cfg = settings_refused_config(tmp_path)
    events: list = []
    progress: list = []

    def broken(_event):
        raise RuntimeError("the panel is gone")

    out = run_motor(cfg, lambda step, what: progress.append((step, what)), observers=[broken, events.append])
    rec = out.record
    assert (rec.kind, rec.verdict, rec.refusal_codes, out.exit_code) == ("refusal", "error", ("settings",), 2)
    assert [(e.step, e.what, e.module.rsplit(".", 1)[1]) for e in events] == [
        ("pre-flight", "start", "check_ready"), ("pre-flight", "failed", "check_ready"),
        ("verdict", "start", "decide_verdict"), ("verdict", "done", "decide_verdict"),
        ("report", "start", "write_report"), ("report", "done", "write_report"),
        ("record", "start", "save_record"), ("record", "done", "save_record")]
    assert progress == [(e.step, e.what) for e in events]  # the command's progress lines: one more observer
    assert {(e.run_id, e.serial) for e in events} == {(rec.run_id, "S-1")}
    assert [s.step for s in rec.steps] == ["pre-flight", "report"]
    assert [r.run_id for r in query_records(tmp_path / "r.sqlite")] == [rec.run_id]


def test_an_ecu_restore_runs_its_one_step_through_the_executor(tmp_path):
    """`ecu restore` with a database: its one step, ``restore``, timed and announced by the same
    executor, its record (kind restore) built by the station's one record builder."""
    from eol_cal.sim.virtual_rig import example_block
    from eol_cal.ecu import protocol as P
    from eol_cal.ecu.client import hmac_seed_to_key
    from eol_cal.sim.remote_ecu import serve_remote
    from eol_cal.ecu.session import ClientTiming
    from eol_cal.ecu.sim_ecu import SimConfig
    from eol_cal.ecu.transport import open_bus
    from eol_cal.domain.motor_params import load_motor
    from eol_cal.records.record import RestoredFrom, StationInfo
    from eol_cal.station.restore import restore_run

    data = example_block(seed=2)
    server = serve_remote(tmp_path / "ecu.flash", config=SimConfig(serial="SIM-0001"))
    events: list = []
    try:
        report, rec, saved, failure = restore_run(
            lambda: open_bus("remote", server.url, None, None), data, serial="SIM-0001", report_dir=tmp_path / "runs",
            seed_to_key=hmac_seed_to_key(P.DEV_SECRET), timing=ClientTiming(), motor=load_motor("paper"),
            source="b.bin", restored_from=RestoredFrom(None, "b.bin", None, None, None), station=StationInfo(),
            db=tmp_path / "r.sqlite", spool_dir=tmp_path / "spool", observers=[events.append])
    finally:
        server.close()
    assert failure is None and report is not None and saved.where == "db", rec.reasons
    assert (rec.kind, rec.verdict, rec.ecu_active.block, rec.ecu_active.sequence) == (
        "restore", "pass", "restored", report.sequence)
    assert [(s.step, s.ok) for s in rec.steps] == [("restore", True)] and rec.blocks[-1].role == "restore"
    assert [(e.step, e.what, e.module) for e in events] == [
        ("restore", what, "eol_cal.station.steps.restore_block") for what in ("start", "done")]
    assert events[-1].elapsed_s == rec.steps[0].seconds and events[-1].run_id == rec.run_id
    assert [r.run_id for r in query_records(tmp_path / "r.sqlite")] == [rec.run_id]


def test_the_acquisitions_preload_imports_what_the_analysis_uses_and_nothing_it_does_not():
    """While the shaft ramps, the cycle's helper imports the scipy the windows' work and the fit
    import inside their functions (linalg, special), not signal, interpolate, ndimage or stats:
    the analysis has numpy's own filter, PCHIP and median, and those cost ~1.5 CPU s of every
    cycle beside the capture's stream (a whole station session loads linalg and special alone)."""
    code = ("import json, sys; from eol_cal.station.steps.acquire_before import preload_analysis; "
            "before = set(sys.modules); preload_analysis(); "
            "print(json.dumps(sorted({m.split('.')[1] for m in set(sys.modules) - before "
            "if m.startswith('scipy.') and sys.modules[m] is not None and not m.split('.')[1].startswith('_')})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    loaded = set(json.loads(out.stdout))
    assert {"linalg", "special"} <= loaded
    assert loaded.isdisjoint({"signal", "interpolate", "ndimage", "stats", "optimize"}), loaded


def test_the_acquire_step_starts_the_shaft_without_importing_scipy_or_jax():
    """The cycle's step modules (the package imports every one) and the windows' early work the
    acquire steps start with (:mod:`eol_cal.station.early`, named too: older steps imported it inside
    ``run``) load neither scipy nor JAX: `eol-cal run`'s shaft started ~0.25 s later while the
    fingerprint's fit imported scipy.linalg at its top there; the helper thread imports them beside
    the stream (the preload above)."""
    code = ("import json, sys; import eol_cal.station.steps; from eol_cal.station.early import EarlyWindows; "
            "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules} & {'scipy', 'jax', 'jaxlib'})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert json.loads(out.stdout) == []
