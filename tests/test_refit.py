"""`eol-cal refit` on a real distributed.LocalCluster (2 worker processes): the same rows as the
fit in this process, a capture that cannot be read reported per capture, a killed worker loses
no capture, and `lot diff` against the records."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.capture.io import write_capture
from eol_cal.capture.synthetic import synthetic_capture
from eol_cal.lot.cluster import RefitWorkerSetup, local_cluster
from eol_cal.lot import refit as refit_mod
from eol_cal.lot.refit import find_captures, read_rows, refit_capture, refit_in_process, refit_lot, refit_serials
from eol_cal.records.write import insert_records

SERIALS = ("R-1", "R-2", "R-3")
# two speeds, two loads, and reverse: the delay, c6 and k6 are all identifiable
POINTS = [(120.0, 20.0), (120.0, 65.0), (240.0, 20.0), (240.0, 65.0), (-120.0, -20.0), (-120.0, -65.0)]


# The Dask workers inherit the suite's JAX cache (tests/conftest.py: its own directory, never ~/.cache),
# so they load the programs other tests compiled instead of compiling them again


@pytest.fixture(scope="module")
def lot(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("refit")
    for i, s in enumerate(SERIALS):  # a directory per motor; the points of tests/test_fit_cli.py
        (d / s).mkdir()
        for j, (rpm, iq) in enumerate(POINTS):
            c = synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=10 * i + j, theta_r0=0.7 * j,
                                  k6=0.0006 + 0.0001 * i, serial=s)
            write_capture(c, d / s / f"c{j}.mf4")
    return d


@pytest.mark.slow
def test_refit_on_two_workers_equals_the_fit_here_and_reports_a_bad_capture(lot: Path, tmp_path: Path):
    (tmp_path / "X").mkdir()
    bad = tmp_path / "X" / "bad.mf4"
    bad.write_bytes(b"not an mdf file")
    out = tmp_path / "r.jsonl"
    res = CliRunner().invoke(cli, ["refit", str(lot), str(bad), "--workers", "2", "--bench", "none", "-o", str(out)])
    assert res.exit_code == 1, res.output  # one capture failed: reported, the lot went on
    rows = {r["capture"]: r for r in read_rows(out)}
    assert len(rows) == 4 and "bad.mf4" in rows[str(bad.resolve())]["error"]
    for group in find_captures([str(lot)]):
        here = refit_capture(group, bench="none")
        there = rows[str(group[0])]
        assert there["serial"] == here["serial"] and there["error"] is None
        assert there["k6"] == pytest.approx(here["k6"], rel=1e-9) and there["c6"] == pytest.approx(here["c6"], rel=1e-9)
        # the workers run the estimator's tick loop in one kernel (eol_cal.numerics.xla), this process does
        # not: float32 rounding of the firmware frame, nothing more
        assert there["phase_k6"] == pytest.approx(here["phase_k6"], abs=1e-6)
        assert there["r2"] == pytest.approx(here["r2"], rel=1e-9) and there["rms"] == pytest.approx(here["rms"], rel=1e-9)
    k6 = {r["serial"]: r["k6"] for r in rows.values() if r["serial"]}
    assert k6["R-3"] > k6["R-1"]
    from eol_cal.lot.refit import write_rows
    pq = write_rows(tmp_path / "r.parquet", list(rows.values()))
    assert {r["capture"]: r["k6"] for r in read_rows(pq)} == {c: r["k6"] for c, r in rows.items()}


@pytest.mark.slow  # a Dask cluster
def test_a_batch_of_serials_gives_each_serials_row_and_isolates_a_bad_one(lot: Path, tmp_path: Path):
    """Many serials in one task (their firmware frames in one batched estimator run): each row is
    the row of that serial refitted alone, bit for bit, and a bad capture spoils only its own row."""
    bad = tmp_path / "X" / "bad.mf4"
    bad.parent.mkdir()
    bad.write_bytes(b"not an mdf file")
    short = tmp_path / "S" / "short.mf4"  # readable, but no steady segment: fails at the segments
    short.parent.mkdir()
    write_capture(synthetic_capture(rpm=120.0, i_qo=20.0, seconds=0.2, seed=1, serial="R-9"), short)
    groups = find_captures([str(lot)])
    mixed = [groups[0], [bad], groups[1], [short], groups[2]]
    rows = refit_serials(mixed, bench="none")
    assert [r["serial"] for r in rows] == ["R-1", None, "R-2", "R-9", "R-3"]
    assert "bad.mf4" in rows[1]["error"] and "segment" in rows[3]["error"]
    assert rows[1]["verdict"] == rows[3]["verdict"] == "error"
    for group, row in zip(mixed, rows, strict=True):
        assert row == refit_capture(group, bench="none")


def _mixed(lot: Path, tmp_path: Path) -> tuple[list, list]:
    """The lot's groups, and five groups in batches of two: a motor, an unreadable file, two motors,
    the first motor again."""
    bad = tmp_path / "X" / "bad.mf4"
    bad.parent.mkdir()
    bad.write_bytes(b"not an mdf file")
    groups = find_captures([str(lot)])
    return groups, [groups[0], [bad], groups[1], groups[2], groups[0]]


def test_a_refit_in_threads_gives_the_rows_of_one_batch_after_the_other_and_isolates_a_failed_task(
        lot: Path, tmp_path: Path, monkeypatch):
    """Two threads of this process, a batch each (:func:`refit_in_process`): each row bit for bit
    the row of its batch refitted alone, in the order of the groups; a bad capture spoils its own
    row, a task that raises its own batch's rows (the other batches' rows are whole)."""
    groups, mixed = _mixed(lot, tmp_path)
    done: list[dict] = []
    rows = refit_in_process(mixed, bench="none", threads=2, batch=2, on_done=done.append)
    assert done == rows and [r["serial"] for r in rows] == ["R-1", None, "R-2", "R-3", "R-1"]
    assert "bad.mf4" in rows[1]["error"] and rows[1]["verdict"] == "error"
    assert rows == [row for k in range(0, len(mixed), 2) for row in refit_serials(mixed[k:k + 2], bench="none")]

    real = refit_mod.refit_serials

    def broken_second_batch(groups, *args, **kw):
        if groups[0] == mixed[2]:
            raise RuntimeError("a worker's bug")
        return real(groups, *args, **kw)

    monkeypatch.setattr(refit_mod, "refit_serials", broken_second_batch)
    again = refit_in_process(mixed, bench="none", threads=2, batch=2)
    assert [r["error"] for r in again[2:4]] == ["RuntimeError: a worker's bug"] * 2
    assert [r["capture"] for r in again[2:4]] == [str(groups[1][0]), str(groups[2][0])]
    assert again[:2] + again[4:] == rows[:2] + rows[4:]


def test_one_thread_starts_each_batchs_estimator_before_fitting_the_batch_ahead_the_same_rows(
        lot: Path, tmp_path: Path, monkeypatch):
    """One thread (:func:`refit_in_process`'s default, :func:`refit_batches`): a batch is read and
    its firmware frames' estimator runs started (once, then taken by the frames) before the batch
    ahead of it is fitted; each row bit for bit the row of its batch refitted alone; a batch that
    raises, when started or when finished, gives its own groups error rows, the others are whole."""
    from eol_cal.firmware import estimator as est

    groups, mixed = _mixed(lot, tmp_path)
    events: list[str] = []
    real_start, real_finish, real_run = refit_mod._start, refit_mod._finish, est.start_jax_batch

    def start(setup, batch):
        events.append(f"start {len(batch)}")
        return real_start(setup, batch)

    def finish(setup, batch):
        events.append(f"finish {len(batch.rows)}")
        return real_finish(setup, batch)

    def run(*args, **kw):
        events.append("estimator")
        return real_run(*args, **kw)

    monkeypatch.setattr(refit_mod, "_start", start)
    monkeypatch.setattr(refit_mod, "_finish", finish)
    monkeypatch.setattr(est, "start_jax_batch", run)
    done: list[dict] = []
    rows = refit_in_process(mixed, bench="none", batch=2, on_done=done.append)
    assert events == ["start 2", "estimator", "start 2", "estimator", "finish 2",
                      "start 1", "estimator", "finish 2", "finish 1"]
    monkeypatch.undo()
    assert done == rows and [r["serial"] for r in rows] == ["R-1", None, "R-2", "R-3", "R-1"]
    assert rows == [row for k in range(0, len(mixed), 2) for row in refit_serials(mixed[k:k + 2], bench="none")]

    for broken in ("_start", "_finish"):
        real = getattr(refit_mod, broken)

        def fails_on_the_second_batch(setup, batch, real=real, broken=broken):
            first = batch[0] if broken == "_start" else batch.rows[0]["capture"]
            if first in (mixed[2], str(mixed[2][0])):
                raise RuntimeError("a bug")
            return real(setup, batch)

        monkeypatch.setattr(refit_mod, broken, fails_on_the_second_batch)
        again = refit_in_process(mixed, bench="none", batch=2)
        monkeypatch.undo()
        assert [r["error"] for r in again[2:4]] == ["RuntimeError: a bug"] * 2, broken
        assert again[:2] + again[4:] == rows[:2] + rows[4:]


def _worker_state() -> tuple[int, bool, int, str | None]:
    import gc

    import dask

    return (os.getpid(), dask.config.get("distributed.worker.profile.enabled"), gc.get_freeze_count(),
            os.environ.get("MALLOC_TRIM_THRESHOLD_"))


@pytest.mark.slow  # two clusters of one worker process each
def test_two_refit_clusters_side_by_side_listen_on_loopback_only_without_a_port_clash():
    import warnings

    import psutil

    def listening() -> set[tuple[str, int]]:
        return {c.laddr[:2] for c in psutil.Process().net_connections(kind="inet") if c.status == psutil.CONN_LISTEN}

    before = listening()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with local_cluster(1), local_cluster(1):
            opened = listening() - before
    # each cluster's scheduler: its TCP address and its HTTP server (health, metrics), both on 127.0.0.1;
    # distributed's default 8787 would have gone to the first and made the second warn and move
    assert len(opened) >= 4 and {host for host, _ in opened} == {"127.0.0.1"}, opened
    assert 8787 not in {port for _, port in opened}
    assert not [w for w in caught if "already in use" in str(w.message)], [str(w.message) for w in caught]


@pytest.mark.slow
def test_a_killed_worker_loses_no_capture(lot: Path):
    from distributed import Client

    paths = find_captures([str(lot)]) * 2
    with local_cluster(2) as cluster, Client(cluster) as client:  # the cluster `eol-cal refit` starts
        client.register_plugin(RefitWorkerSetup(None))
        pids = list(client.run(os.getpid).values())
        done = []

        def kill_once(row):
            done.append(row)
            if len(done) == 1:
                os.kill(pids[0], signal.SIGKILL)  # one worker process dies mid-lot

        # one serial per task: the worker dies with tasks still to come
        rows = refit_lot(paths, client, on_done=kill_once, retries=3, bench="none", batch=1)
        client.wait_for_workers(2, timeout=60)
        state = list(client.run(_worker_state).values())
    # the nanny restarted the killed worker: it runs the refit's settings and the plugin too
    assert len(state) == 2 and pids[0] not in [pid for pid, *_ in state]
    assert all(profiling is False and frozen > 10_000 for _, profiling, frozen, _ in state), state
    # no malloc trimming added by the nanny (it costs a refit ~20 % CPU): as in this process
    assert {trim for *_, trim in state} == {os.environ.get("MALLOC_TRIM_THRESHOLD_")}
    assert len(rows) == len(paths)
    assert all(r["error"] is None and r["k6"] is not None for r in rows), rows
    assert sorted(r["serial"] for r in rows) == sorted(SERIALS * 2)


def test_lot_diff_compares_the_fit_stage_checks_of_each_serials_latest_measured_run(records_db, tmp_path: Path):
    from eol_cal.sim.run_records import make_record

    t = "2026-11-22T{:02d}:00:00.000+00:00".format
    recs = [make_record("A", started=t(8)), make_record("B", started=t(8)),
            make_record("C", started=t(8), pp_after=2.5),  # failed on its ripple: a refit cannot judge that
            make_record("D", started=t(8)), make_record("D", started=t(9), refused=("dyno_unreachable",))]
    assert recs[2].verdict == "fail"
    insert_records(records_db, recs)
    out = tmp_path / "r.jsonl"
    rows = [("A", "pass", [], 0.9e-3), ("B", "fail", ["max_k6"], 1.3e-3), ("C", "pass", [], 0.7e-3),
            ("D", "pass", [], 0.6e-3), ("E", "pass", [], 0.6e-3)]
    out.write_text("".join(json.dumps({"serial": s, "verdict": v, "status": "ok", "k6": k6, "failed_checks": f,
                                       "reasons": [f"k6 over {x}" for x in f], "error": None}) + "\n"
                           for s, v, f, k6 in rows)
                   + json.dumps({"serial": None, "verdict": "error", "error": "OSError: x"}) + "\n")
    res = CliRunner().invoke(cli, ["lot", "diff", "--db", str(records_db), str(out), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    from eol_cal.schemas import validator

    validator("lot-diff").validate(doc)
    assert (doc["rows"], doc["compared"], doc["not_compared"], doc["errors"]) == (6, 4, 1, 1)
    (change,) = doc["changes"]
    assert (change["serial"], change["recorded"], change["refit"], change["newly_failing"]) == ("B", "pass", "fail",
                                                                                                 ["max_k6"])
    assert change["run_id"] == recs[1].run_id and change["k6_refit"] == pytest.approx(1.3) and doc["k6_unit"] == "mN*m/A"
    res = CliRunner().invoke(cli, ["lot", "diff", "--db", str(records_db), str(out)])
    assert res.exit_code == 0 and "1 of 4 compared" in res.output and "mN*m/A" in res.output


@pytest.mark.parametrize("flags, ecu_serial, words", [
    ("COMP_ENABLE|INTERP_ENABLE", None, "under compensation"),
    ("INTERP_ENABLE", "M-0001", "another motor's block"),
])
def test_a_capture_fit_would_refuse_is_an_error_row(tmp_path, flags, ecu_serial, words):
    """A refit refuses per serial what `eol-cal fit` refuses: under compensation, another motor's ECU."""
    import dataclasses

    from eol_cal.capture.ecu_state import EcuState, with_ecu_state

    c = synthetic_capture(rpm=60.0, i_qo=40.0, seconds=0.6, seed=3, serial="M-0007")
    state = EcuState(1, 4, "0badc0de", flags, ecu_serial)
    c = dataclasses.replace(c, metadata=with_ecu_state(c.metadata, state, state))
    path = tmp_path / "m.mf4"
    write_capture(c, path)
    row = refit_capture([path])
    assert row["verdict"] == "error" and words in row["error"] and str(path) in row["error"]
    assert row["k6"] is None


def test_refit_takes_the_production_runs_of_a_reports_directory_unless_asked(tmp_path: Path):
    """A station run directory whose record is of another kind (a master motor's check, a simulated
    motor) is no motor of the lot; --kind all takes it."""
    import dataclasses

    from eol_cal.sim.run_records import make_record

    for name, kind in (("A_run", "production"), ("B_run", "simulated"), ("C_run", None)):
        d = tmp_path / "reports" / name
        d.mkdir(parents=True)
        (d / "before.mf4").write_bytes(b"")
        if kind is not None:  # C: no record beside the capture (taken as it is)
            rec = dataclasses.replace(make_record(name[0]), kind=kind)
            (d / "report.json").write_text(json.dumps(rec.to_json()))
    names = lambda groups: [g[0].parent.name for g in groups]  # noqa: E731
    assert names(find_captures([str(tmp_path / "reports")])) == ["A_run", "C_run"]
    assert names(find_captures([str(tmp_path / "reports")], "all")) == ["A_run", "B_run", "C_run"]
    assert names(find_captures([str(tmp_path / "reports")], "simulated")) == ["B_run", "C_run"]


@pytest.mark.slow  # a Dask scheduler and worker processes: 24 s
def test_refit_on_a_running_scheduler_started_apart(lot: Path, tmp_path: Path):
    """`--scheduler`: a scheduler and a worker started as a plant would (the `dask` command line,
    their own processes, 127.0.0.1), not by eol-cal: the same rows as the local cluster's."""
    import shutil
    import subprocess
    import sys
    import time

    dask_cli = Path(sys.executable).with_name("dask")
    assert dask_cli.exists() or shutil.which("dask"), "distributed's `dask` command is installed with it"
    dask_cli = str(dask_cli if dask_cli.exists() else shutil.which("dask"))
    sched_file = tmp_path / "scheduler.json"
    env = {**os.environ, "EOL_CAL_JAX_CACHE": "off"}
    procs = [subprocess.Popen([dask_cli, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sched_file)], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        deadline = time.monotonic() + 120
        while not sched_file.exists() or not sched_file.read_text().strip():
            assert time.monotonic() < deadline, "the scheduler wrote no address"
            time.sleep(0.2)
        address = json.loads(sched_file.read_text())["address"]
        procs.append(subprocess.Popen([dask_cli, "worker", address, "--host", "127.0.0.1", "--nworkers", "1",
                                       "--nthreads", "1", "--no-dashboard"], env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        out = tmp_path / "apart.jsonl"
        res = CliRunner().invoke(cli, ["refit", str(lot), "--scheduler", address, "--bench", "none", "-o", str(out)])
        assert res.exit_code == 0, res.output
        rows = {r["capture"]: r for r in read_rows(out)}
        assert len(rows) == len(SERIALS)
        for group in find_captures([str(lot)]):
            here = refit_capture(group, bench="none")
            there = rows[str(group[0])]
            assert there["error"] is None and there["serial"] == here["serial"]
            assert there["k6"] == pytest.approx(here["k6"], rel=1e-9) and there["c6"] == pytest.approx(here["c6"], rel=1e-9)
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()


def test_a_refit_leaves_out_the_mechanical_result_which_changes_nothing_it_reports(lot: Path):
    """The refit skips the mechanical result (the fingerprint's margin and the block's orders,
    ~40 % of its CPU): a row reads only the fit stage. Fitted with and without it, a motor's result
    differs in ``mech`` alone, and the refit's row holds the same figures and verdict."""
    import dataclasses

    from eol_cal.analysis.fit.capture import measure_firmware_frames, segment_motors
    from eol_cal.analysis.fit.motors import FitOptions, fit_inputs
    from eol_cal.capture.io import read_capture

    group = find_captures([str(lot)])[0]
    results = {}
    for mech in (True, False):
        opts = FitOptions(batch="loop", capture_metrics=False, mechanics=None, mech=mech)
        (mi,) = segment_motors([read_capture(p) for p in group], opts.motor, settle_s=opts.settle_s,
                               min_revs=opts.min_revs, hall_angle=opts.hall_angle, mechanics=None)
        measure_firmware_frames([mi], [opts.estimator_options])
        (results[mech],) = fit_inputs([mi], opts).results
    assert results[True].mech is not None and results[True].mech.fingerprint  # measured when asked
    assert results[False].mech is None
    assert dataclasses.replace(results[True], mech=None) == results[False]
    row, e = refit_capture(group, bench="none"), results[True].estimates
    assert e is not None and row["status"] == str(results[True].status) and row["verdict"] is None
    assert (row["k6"], row["phase_k6"], row["c6"]) == (e.k6.value, e.phase_k6.value, e.c6.value)
    assert (row["r2"], row["rms"]) == (results[True].fit["r2"], results[True].fit["rms"])
