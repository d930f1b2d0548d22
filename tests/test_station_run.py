"""The end-of-line cycle on loopback: a real pymodbus dyno simulator on 127.0.0.1 backed by the
plant, a real ECU simulator reached over python-can-remote on 127.0.0.1 (ISO-TP, UDS), SQLite.

The full run uses a short profile (three load points, both directions) and a test variant whose
interval and p-p-before limits suit it; the fault tests use the dyno's analytic capture source
(no JAX plant) because they end before the ripple matters.
"""

from __future__ import annotations

import json
import math
import sqlite3
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.dyno.registers import SimFault
from eol_cal.dyno.sim_dyno import FaultPlan
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.ecu import protocol as P
from eol_cal.ecu.flash import active_block_from_file
from eol_cal.firmware import block as B
from eol_cal.plant.presets import paper
from eol_cal.plant.simulate import _COMPILED as plant_programs
from eol_cal.station import cycle
from eol_cal.station.cycle import run_motor
from eol_cal.sim.loopback import loopback_station
from eol_cal.records.limits import LIMIT_KEYS, Measured, load_limits, verdict
from eol_cal.records.record import RunRecord
from eol_cal.records.query import query_records
from eol_cal.station.run import sha256_file


PROFILE = """
name = "station-test"
description = "short end-of-line profile: two loads forward, one reverse"

[[segment]]
speed_rpm = 120.0
iq = 20.0
seconds = 0.8

[[segment]]
speed_rpm = 120.0
iq = 65.0
seconds = 1.1
ramp_s = 0.1

[[segment]]
speed_rpm = -120.0
iq = -65.0
seconds = 1.1
ramp_s = 0.3
"""

# TEST: the standard variant, with the c6 interval and p-p before that 2.4 s of capture at
# 120 rpm give; TIGHT: the same motor must fail it on the compensated ripple alone.
LIMITS = """
default_variant = "TEST"

[variant.TEST]
max_k6 = 0.0025
max_pp_before_pct = 25.0
max_pp_after_pct = 2.0
min_improvement_pct = 50.0
min_r2 = 0.3
max_rms_nm = 0.1
max_ci_k6_rel = 0.05
max_ci_phase_k6_deg = 3.0
max_ci_c6_nm = 0.01
max_hall_deviation_deg = 3.0

[variant.TIGHT]
max_k6 = 0.0025
max_pp_before_pct = 25.0
max_pp_after_pct = 0.05
min_improvement_pct = 99.9
min_r2 = 0.3
max_rms_nm = 0.1
max_ci_k6_rel = 0.05
max_ci_phase_k6_deg = 3.0
max_ci_c6_nm = 0.01
max_hall_deviation_deg = 3.0
"""

SERIAL = "T-0001"
SEED = 1
MOTOR = paper(SERIAL)  # the seed paper's bench: k6 = 0.62 mN*m/A, 12th-harmonic cogging, sensor errors


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("station")
    (d / "profile.toml").write_text(PROFILE)
    (d / "limits.toml").write_text(LIMITS)
    (d / "key.hex").write_text(P.DEV_SECRET.hex())
    return {"dir": d, "profile": d / "profile.toml", "limits": d / "limits.toml", "key": d / "key.hex"}


def run_args(files: dict[str, Path], st, serial: str, db: Path, report_dir: Path, *extra: str) -> list[str]:
    return ["run", "--dyno", st.dyno_address, "--interface", "remote", "--channel", st.can_channel,
            "--limits", str(files["limits"]), "--db", str(db), "--serial", serial, "--profile", str(files["profile"]),
            "--key-file", str(files["key"]), "--report-dir", str(report_dir), "--spool-dir", str(files["dir"] / "spool"),
            "--json", *extra]


def bank_bytes(flash_file: Path, bank: int, n: int) -> bytes:
    """The first ``n`` bytes of a bank of the ECU simulator's flash image."""
    from eol_cal.ecu.flash import NorFlash

    return NorFlash(flash_file).read(bank, 0, n)


def wait_stopped(sim, timeout: float = 3.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end and sim.speed != 0.0:
        time.sleep(0.02)


@pytest.fixture(scope="module")
def full_run(files):
    """``eol-cal run`` once, end to end, on the plant."""
    db = files["dir"] / "results.sqlite"
    events: list = []  # the executor's events of the run, as an operator panel would receive them

    def with_observer(cfg, progress=None, on_verdict=None):
        return run_motor(cfg, progress, on_verdict, observers=[events.append])

    options = load_limits(files["limits"]).estimator_options
    with (loopback_station(SERIAL, SEED, files["dir"] / "sim", spec_for=lambda req: MOTOR, prepare=options) as st,
          pytest.MonkeyPatch.context() as mp):
        prepared = set(plant_programs)
        mp.setattr(cycle, "run_motor", with_observer)
        res = CliRunner().invoke(cli, run_args(files, st, SERIAL, db, files["dir"] / "reports"))
        wait_stopped(st.dyno.sim)
        sim_state = (st.dyno.sim.enabled, st.dyno.sim.setpoint, st.dyno.sim.speed)
        flash = st.flash_file
    assert res.exit_code in (0, 1, 2), res.output
    doc = json.loads(res.stdout)
    return {"res": res, "doc": doc, "rec": doc["record"], "db": db, "sim_state": sim_state, "flash": flash,
            "events": events, "compiled_in_cycle": set(plant_programs) - prepared}


@pytest.mark.slow
def test_full_run_end_to_end(full_run):
    rec, doc = full_run["rec"], full_run["doc"]
    assert full_run["res"].exit_code == 0, (rec["verdict"], rec["reasons"], rec.get("error"))
    assert rec["verdict"] == "pass" and rec["reasons"] == []
    assert [s["step"] for s in rec["steps"]] == ["pre-flight", "prepare ECU", "acquire", "fit", "table", "flash",
                                                 "acquire compensated", "metrics", "report"]
    # the dyno simulator's plant compiled before it served (prepare): none of its captures compiled
    assert full_run["compiled_in_cycle"] == set()
    # the pre-flight found the blank ECU of this motor, the key accepted, the dyno ready
    pre = rec["preflight"]
    assert pre["problems"] == [] and pre["ecu"]["key_accepted"] is True and pre["ecu"]["state"]["bank"] is None
    assert rec["kind"] == "production" and rec["refusal_codes"] == []
    assert pre["ecu"]["state"]["serial"] == SERIAL and pre["dyno"]["dut_serial"] == SERIAL
    # the motor was measured under the uncompensated block (field estimator), flashed first
    blocks = {b["role"]: b for b in rec["blocks"]}
    prep = blocks["prepare"]
    # under the estimator options the calibrated block carries (the limits' default: best, all four)
    assert prep["flags"] == B.flag_names(B.FLAG_INTERP_ENABLE | B.FLAGS_ESTIMATOR) and prep["estimator"] == "best"
    assert prep["verified"] and prep["sequence"] == 1
    assert prep["previous"]["bank"] is None  # a blank ECU
    assert all(s["ok"] and s["seconds"] > 0 for s in rec["steps"])
    # the fit found the plant motor's ripple, on the bench file of the bench the dyno simulator says it ran
    assert abs(rec["fit"]["k6"]["value"] - MOTOR.k6) < 0.05 * MOTOR.k6
    assert rec["fit"]["model_check"]["bench"] == "simulated"
    # the compensation the ECU now runs took the 6th harmonic out and the p-p ripple down (what is
    # left is mostly the preset's 12th-harmonic cogging, which a 6th-harmonic table does not touch)
    m = rec["metrics"]
    assert m["after"]["amp6_nm"] < 0.2 * m["before"]["amp6_nm"]
    assert m["pp_after_pct"] < 0.5 * m["pp_before_pct"]
    assert m["improvement_pct"] > 50
    # the preset's rotor unbalance (7 mN*m, mechanical order 1): the calibrated block is layout 2 with
    # MECH_COMP_ENABLE (contract revision 1.2), the ECU identified the rotor's mechanical angle and
    # compensated it: little of it is left, and the p-p hardly changes when it is taken out
    cal = blocks["calibrated"]
    assert cal["layout_version"] == 2 and cal["mech"] == "on" and "MECH_COMP_ENABLE" in cal["flags"]
    assert rec["layout_version"] == 2 and rec["fit"]["mech"]["status"] == "ok"
    assert m["before"]["mech1_nm"] > 0.005 and m["after"]["mech1_nm"] < 0.3 * m["before"]["mech1_nm"]
    assert m["after"]["pp_no_mech1_pct"] == m["pp_after_no_mech1_pct"]
    assert abs(m["pp_after_no_mech1_pct"] - m["pp_after_pct"]) < 0.1
    # the block in the ECU's active bank is the one recorded, for this motor
    active = active_block_from_file(full_run["flash"])
    blk = B.unpack(active, "active")
    assert blk.serial == SERIAL and blk.flags & B.FLAG_COMP_ENABLE
    cal = blocks["calibrated"]
    assert cal["flags"] == B.flag_names(blk.flags) == ("COMP_ENABLE|INTERP_ENABLE|EST_CLAMP_TO_NEXT_EDGE|"
                                                       "EST_LEARN_GRID_OFFSET|EST_ACCEL_PREDICTION|"
                                                       "EST_LEARN_PITCH_ERRORS|MECH_COMP_ENABLE")
    assert cal["estimator"] == "best"
    assert rec["fit"]["model"]["frame_estimator"] == "best"
    # the calibration capture carries the ECU's q current: the fit takes its ripple out (issue 34)
    assert rec["fit"]["model"]["current_ripple"].startswith("taken out"), rec["fit"]["model"]["current_ripple"]
    assert f"{B.check(active).crc_stored:08x}" == cal["crc32"]
    assert blk.sequence == cal["sequence"] == 2 and cal["bank"] != prep["bank"]
    # the archive is the truth: each block in the run's directory is the bank's bytes as flashed
    # (sequence and CRC set), its SHA-256 in the record
    for b in (prep, cal):
        data = Path(b["path"]).read_bytes()
        assert data == bank_bytes(full_run["flash"], b["bank"], len(data)) and sha256_file(b["path"]) == b["sha256"]
        assert B.unpack(data, "archive").sequence == b["sequence"] and f"{B.check(data).crc_stored:08x}" == b["crc32"]
    assert Path(cal["path"]).name == "block.bin" and Path(prep["path"]).name == "block_uncompensated.bin"
    # every limit checked once, by the cycle, and carried in the record
    assert [c["key"] for c in rec["checks"]] == [k for k in LIMIT_KEYS if rec["limits"][k] is not None]
    assert all(c["pass"] is True for c in rec["checks"])
    # captures on disk with the recorded hashes, each with the block the ECU ran all along
    for which, ran in (("before", prep), ("after", cal)):
        c = rec["captures"][which]
        assert sha256_file(c["path"]) == c["sha256"]
        assert c["ecu_before"] == c["ecu_after"]
        assert (c["ecu_before"]["bank"], c["ecu_before"]["sequence"], c["ecu_before"]["crc32"],
                c["ecu_before"]["flags"]) == (ran["bank"], ran["sequence"], ran["crc32"], ran["flags"])
        from eol_cal.capture.ecu_state import trace_of
        from eol_cal.capture.io import read_capture

        assert trace_of(read_capture(c["path"]).metadata).to_dict() == {k: c[k] for k in ("ecu_before", "ecu_after")}
    # each flash reset the ECU: the shaft turned for its settling before the samples counted, the
    # calibrated block's mechanical identification at 200 rpm first (then 0.3 s at 120 rpm), the
    # uncompensated block's pitch learning at the capture's speed
    from eol_cal.firmware.settling import lead_in_plan

    for which, ran in (("before", prep), ("after", cal)):
        booted = B.unpack(Path(ran["path"]).read_bytes(), "archive")
        point_rpm, point_s, at_speed_s = lead_in_plan(booted, 120.0)
        assert rec["captures"][which]["lead_in_s"] == pytest.approx(at_speed_s, abs=1e-4)
        assert rec["captures"][which].get("lead_in_point", {}).get("speed_rpm") == point_rpm
    assert rec["captures"]["after"]["lead_in_s"] == pytest.approx(0.3, abs=1e-4)
    # 4 revolutions at 200 rpm, and the sample that closes the lead-in's capture
    assert rec["captures"]["after"]["lead_in_point"]["seconds"] == pytest.approx(1.2, abs=2e-4)
    assert rec["captures"]["before"]["lead_in_s"] == pytest.approx(0.75, abs=1e-4)  # 1.5 revolutions
    assert "lead_in_point" not in rec["captures"]["before"]
    # verification at the operating point only: 65 A at 120 rpm, forward and reverse
    assert rec["captures"]["before"]["segments"] == 3 and rec["captures"]["after"]["segments"] == 2
    assert rec["station"]["verify"] == "point"
    assert rec["station"]["motor"] == "paper" and rec["station"]["bench"] == "paper"
    # the ECU boots this run's block
    assert rec["ecu_active"] == {"block": "calibrated", "sequence": 2, "bank": cal["bank"]}
    assert abs(rec["fit"]["operating_point"]["i_qo_a"]) == 65.0
    # the record is in the database (WAL), identical to the report's JSON
    assert doc["saved"]["where"] == "db"
    (stored,) = query_records(full_run["db"], serial=SERIAL)
    assert stored.to_json() == rec
    assert RunRecord.from_json(rec).to_json() == rec  # the round trip is exact
    con = sqlite3.connect(full_run["db"])
    assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    con.close()
    run_dir = Path(rec["report_dir"])
    assert json.loads((run_dir / "report.json").read_text()) == rec
    html = (run_dir / "report.html").read_text()
    # one self-contained page: plots inline, nothing fetched from beside it
    assert html.count("<svg") >= 3 and "src=" not in html.replace("data:image/png;base64", "")
    assert not list(run_dir.glob("*.png"))
    assert "PASS" in html and SERIAL in html
    assert rec["tool_version"] and rec["layout_version"] == 2  # the calibrated block: layout 2 (revision 1.2)
    # the dyno is left stopped and disabled
    assert full_run["sim_state"] == (False, 0.0, 0.0)


@pytest.mark.slow
def test_one_serial_from_scan_to_record_runs_through_each_step_module_in_order(full_run):
    """The executor's events of the passing run: every step's start and end, in the cycle's order,
    each from its own module of eol_cal/station/steps, all of this serial's run."""
    rec = full_run["rec"]
    assert rec["verdict"] == "pass", rec["reasons"]
    events = full_run["events"]
    assert {(e.serial, e.run_id) for e in events} == {(SERIAL, rec["run_id"])}
    order = [("pre-flight", "check_ready"), ("prepare ECU", "prepare_ecu"), ("acquire", "acquire_before"),
             ("fit", "fit_capture"), ("table", "make_table"), ("flash", "flash_calibrated"),
             ("acquire compensated", "acquire_after"), ("metrics", "measure_ripple"), ("verdict", "decide_verdict"),
             ("report", "write_report"), ("record", "save_record")]
    assert [(e.step, e.what, e.module) for e in events] == [
        (step, what, f"eol_cal.station.steps.{module}") for step, module in order for what in ("start", "done")]
    # the timed steps' events carry the times the record keeps
    times = {e.step: e.elapsed_s for e in events if e.what == "done"}
    assert [times[s["step"]] for s in rec["steps"]] == [s["seconds"] for s in rec["steps"]]


@pytest.mark.slow
def test_full_run_passes_on_a_dyno_with_the_vendor_b_register_map(files):
    """The whole cycle on a dyno laid out otherwise (vendor B: CDAB, scaled integers, separate
    tables, its own codes): the simulator serves the map and ``run --register-map`` drives it.
    With ``--read-back off`` and ``--lead-in off`` (a line's takt settings): both blocks are
    flashed and confirmed without a read-back, every capture starts at speed, and the record
    says so."""
    from eol_cal.dyno.mapfile import load_register_map

    db = files["dir"] / "vendor-b.sqlite"
    regmap = load_register_map("vendor-b")
    with loopback_station("VB-0001", SEED, files["dir"] / "sim-b", spec_for=lambda req: paper("VB-0001"),
                          register_map=regmap) as st:
        res = CliRunner().invoke(cli, run_args(files, st, "VB-0001", db, files["dir"] / "reports-b",
                                               "--register-map", "vendor-b", "--read-back", "off",
                                               "--lead-in", "off"))
        wait_stopped(st.dyno.sim)
        assert (st.dyno.sim.enabled, st.dyno.sim.setpoint, st.dyno.sim.speed) == (False, 0.0, 0.0)
        assert st.dyno.sim.captures_started == 3 + 2 and st.dyno.sim.window_reads > 0  # 3 segments, 2 verifications
    rec = json.loads(res.stdout)["record"]
    assert res.exit_code == 0, (rec["verdict"], rec["reasons"], rec.get("error"))
    assert rec["verdict"] == "pass" and rec["station"]["dyno_register_map"] == regmap.name
    assert [(b["role"], b["verified"], b["confirmed"]) for b in rec["blocks"]] == [
        ("prepare", False, True), ("calibrated", False, True)]
    assert [c["lead_in_s"] for c in rec["captures"].values()] == [0.0, 0.0]
    assert abs(rec["fit"]["k6"]["value"] - MOTOR.k6) < 0.05 * MOTOR.k6
    assert rec["metrics"]["pp_after_pct"] < 0.5 * rec["metrics"]["pp_before_pct"]


@pytest.mark.slow  # a station run up to the fit
def test_a_bench_file_that_is_not_the_dyno_s_fails_at_the_fit_with_what_to_do(files, tmp_path):
    """Issue 34 (b): the full run passes on the paper bench file because the simulated dyno says its
    plant ran that bench (``sim_bench``); a bench file that is only an assumption about the dyno
    (here ``resonant-250`` on the paper plant; on a real dyno the built-in ``paper``), which one
    speed band cannot verify, fails the default limit ``max_bench_assumed`` at the fit: no
    calibrated block, the reason says to identify the bench."""
    db = tmp_path / "results.sqlite"
    with loopback_station("BA-0001", SEED, tmp_path / "sim", spec_for=lambda req: paper("BA-0001")) as st:
        res = CliRunner().invoke(cli, run_args(files, st, "BA-0001", db, tmp_path / "reports",
                                               "--bench", "resonant-250"))
        wait_stopped(st.dyno.sim)
    rec = json.loads(res.stdout)["record"]
    assert res.exit_code == 1, (rec["verdict"], rec["reasons"], rec.get("error"))
    assert rec["verdict"] == "fail" and [s["step"] for s in rec["steps"]][-1] in ("fit", "report")
    assert rec["fit"]["model_check"]["bench"] == "assumed"
    (reason,) = rec["reasons"]
    assert "max_bench_assumed" in reason and "eol-cal bench identify" in reason and "resonant-250" in reason
    assert [b["role"] for b in rec["blocks"]] == ["prepare"]
    check = next(c for c in rec["checks"] if c["key"] == "max_bench_assumed")
    assert check["pass"] is False and check["stage"] == "fit"


@pytest.mark.slow  # a whole station run; the operator loop test keeps the cycle in the fast loop
def test_same_run_passes_one_variant_and_fails_another(full_run, files):
    rec = full_run["rec"]
    f = rec["fit"]
    m = Measured(k6=f["k6"]["value"], ci_k6=f["k6"]["ci95"], ci_phase_k6_deg=math.degrees(f["phase_k6"]["ci95"]),
                 ci_c6_nm=max(f["c6"]["ci95"], f["c6"]["value"] * f["phase_c6"]["ci95"]), fit_r2=f["fit"]["r2"],
                 fit_rms_nm=f["fit"]["rms"], pp_before_pct=rec["metrics"]["pp_before_pct"],
                 pp_after_pct=rec["metrics"]["pp_after_pct"],
                 hall_deviation_deg=max(abs(d) for d in f["hall_angle"]["deviation_deg"]), hall_source="measured")
    assert f["hall_angle"]["source"] == "measured"
    assert verdict(m, load_limits(files["limits"], "TEST")) == ("pass", [])
    v, reasons = verdict(m, load_limits(files["limits"], "TIGHT"))
    assert v == "fail"
    assert any("max_pp_after_pct" in r for r in reasons) and any("min_improvement_pct" in r for r in reasons)


@pytest.mark.slow
@pytest.mark.parametrize(("fault", "at_capture", "failed_step"), [
    (SimFault.OVER_SPEED, 2, "acquire"),
    (SimFault.TORQUE_SENSOR, 5, "acquire compensated"),  # 3 segments before, the 2nd of the compensated run
])
def test_dyno_fault_ends_in_safe_state_with_an_error_record_while_the_db_is_locked(files, tmp_path, fault, at_capture,
                                                                                    failed_step):
    db = tmp_path / "results.sqlite"
    spool = files["dir"] / "spool"
    serial = f"F-{int(fault)}"
    with loopback_station(serial, 7, tmp_path / "sim", source=synthetic_source,
                          faults=(FaultPlan(fault, "capture", at_capture),)) as st:
        CliRunner().invoke(cli, ["records", "--db", str(db)])  # nothing yet
        sqlite3.connect(db).execute("PRAGMA journal_mode=WAL").connection.close()
        holder = sqlite3.connect(db, isolation_level=None)
        holder.execute("BEGIN EXCLUSIVE")  # another process holds the database for the whole run
        try:
            # the analytic source's torque path is rigid: fitted with its own bench file (``none``)
            res = CliRunner().invoke(cli, run_args(files, st, serial, db, tmp_path / "reports", "--db-timeout", "0.2",
                                                   "--bench", "none"))
        finally:
            holder.execute("ROLLBACK")
            holder.close()
        wait_stopped(st.dyno.sim)
        sim = st.dyno.sim
        assert not sim.enabled and sim.setpoint == 0.0 and sim.speed == 0.0
        flash = st.flash_file
    assert res.exit_code == 2, res.output
    doc = json.loads(res.stdout)
    rec = doc["record"]
    assert rec["verdict"] == "error" and rec["error"]["step"] == failed_step
    # what the ECU boots now, as recorded and as in its flash: the prepared (uncompensated) block
    # when the cycle ended before the calibrated one was written, else the calibrated one
    active = B.unpack(active_block_from_file(flash), "active")
    if failed_step == "acquire":
        assert rec["ecu_active"] == {"block": "uncompensated", "sequence": 1, "bank": rec["blocks"][0]["bank"]}
        assert active.flags == B.FLAG_INTERP_ENABLE | B.FLAGS_ESTIMATOR and active.sequence == 1
    else:
        assert rec["ecu_active"]["block"] == "calibrated" and rec["ecu_active"]["sequence"] == 2
        assert active.flags & B.FLAG_COMP_ENABLE and active.sequence == 2
    assert "fault" in rec["error"]["message"] and "speed set to 0 and drive disabled" in rec["error"]["message"]
    assert rec["safe_state"].startswith("speed 0, drive disabled")
    assert rec["steps"][-2]["step"] == failed_step and not rec["steps"][-2]["ok"]
    # no capture of the failed acquisition was saved as good
    which = "before" if failed_step == "acquire" else "after"
    assert which not in rec["captures"]
    assert not (Path(rec["report_dir"]) / f"{which}.mf4").exists()
    assert rec["kind"] == "production"  # something was written to the ECU: a measured attempt, not a refusal
    if failed_step == "acquire compensated":
        assert rec["blocks"][-1]["role"] == "calibrated"  # it had been flashed; the ECU keeps it
    # the locked database: the record waited in the spool; the next command writes it in
    assert doc["saved"]["where"] == "spool"
    assert Path(doc["saved"]["path"]).exists()
    res = CliRunner().invoke(cli, ["records", "--db", str(db), "--flush", "--spool-dir", str(spool), "--json"])
    assert res.exit_code == 0, res.output
    (stored,) = json.loads(res.stdout)["records"]
    assert stored == rec
    assert not Path(doc["saved"]["path"]).exists()


@pytest.mark.slow
def test_a_motor_of_another_type_on_the_dyno_is_refused_before_the_fit(files, tmp_path):
    # the station is set up for an 8-pole motor type; the dyno turns the paper's 6-pole motor
    motor = tmp_path / "eps8.toml"
    motor.write_text('name = "eps8"\npoles = 8\n')
    db = tmp_path / "results.sqlite"
    with loopback_station("W-1", 7, tmp_path / "sim", source=synthetic_source) as st:
        res = CliRunner().invoke(cli, run_args(files, st, "W-1", db, tmp_path / "reports", "--motor", str(motor)))
        wait_stopped(st.dyno.sim)
        flash = st.flash_file
    assert res.exit_code == 2, res.output
    rec = json.loads(res.stdout)["record"]
    assert rec["verdict"] == "error" and rec["error"]["step"] == "fit"
    assert "poles" in rec["error"]["message"] and "eps8" in rec["error"]["message"]
    assert rec["fit"] is None and [b["role"] for b in rec["blocks"]] == ["prepare"]
    # the block it prepared the ECU with is for the motor type it was given
    assert B.unpack(active_block_from_file(flash), "active").poles == 8
    assert rec["ecu_active"]["block"] == "uncompensated"


def test_bad_inputs_refused_before_the_dyno_moves(files, tmp_path):
    runner = CliRunner()
    base = ["run", "--dyno", "127.0.0.1:1", "--interface", "virtual", "--channel", "x", "--db", str(tmp_path / "r.sqlite"),
            "--serial", "S-1", "--key-file", str(files["key"]), "--report-dir", str(tmp_path / "rep")]
    bad = tmp_path / "bad.toml"
    bad.write_text(LIMITS.replace("max_k6 = 0.0025\nmax_pp_before_pct = 25.0\nmax_pp_after_pct = 2.0",
                                  "max_pp_after_pct = 2.0", 1))
    res = runner.invoke(cli, base + ["--limits", str(bad)])
    assert res.exit_code == 2 and "variant.TEST.max_k6" in res.output and str(bad) in res.output
    res = runner.invoke(cli, base + ["--limits", str(files["limits"]), "--variant", "NOPE"])
    assert res.exit_code == 2 and "'NOPE' not in the file" in res.output
    res = runner.invoke(cli, [a for a in base if a not in ("--key-file", str(files["key"]))] + ["--limits", str(files["limits"])],
                        env={"EOL_CAL_KEY_FILE": ""})
    assert res.exit_code == 2 and "key-file" in res.output
    res = runner.invoke(cli, base + ["--limits", str(files["limits"]), "--serial", "S" * 17])
    assert res.exit_code == 2 and "16 ASCII" in res.output
    res = runner.invoke(cli, base[:2] + ["nohost:50x"] + base[3:] + ["--limits", str(files["limits"])])
    assert res.exit_code == 2 and "'50x' is not a number" in res.output  # a bare HOST is port 502
    res = runner.invoke(cli, base + ["--limits", str(files["limits"]), "--register-map", "vendor-z"])
    assert res.exit_code == 2 and "vendor-z" in res.output
    res = runner.invoke(cli, base + ["--limits", str(files["limits"]), "--bench", "nope"])
    assert res.exit_code == 2 and "nope" in res.output
    bad_motor = tmp_path / "motor.toml"
    bad_motor.write_text("poles = -2\n")
    res = runner.invoke(cli, base + ["--limits", str(files["limits"]), "--motor", str(bad_motor)])
    assert res.exit_code == 2 and str(bad_motor) in res.output and "poles" in res.output
    assert not (tmp_path / "r.sqlite").exists() and not (tmp_path / "rep").exists()


def test_verification_segments_are_the_operating_point_in_both_directions():
    from eol_cal.dyno.setpoints import setpoints_from_profile
    from eol_cal.plant.profile import load_profile
    from eol_cal.analysis.point_metrics import verify_segments

    segs = setpoints_from_profile(load_profile("eol-default"))
    chosen = verify_segments(segs, 60.0, 65.0)
    assert [(s.speed_rpm, s.iq) for s in chosen] == [(60.0, 65.0), (-60.0, -65.0)]
    assert verify_segments(segs, -60.0, -65.0) == chosen
    assert verify_segments(segs, 90.0, 65.0) == segs  # no such point: the whole profile


def test_a_wrong_key_is_an_error_before_the_dyno_turns_and_the_ecu_keeps_no_block(files, tmp_path):
    db = tmp_path / "results.sqlite"
    wrong = tmp_path / "wrong.hex"
    wrong.write_text("00" * 16)
    with loopback_station("K-1", 3, tmp_path / "sim", source=synthetic_source) as st:
        args = run_args(files, st, "K-1", db, tmp_path / "reports")
        args[args.index("--key-file") + 1] = str(wrong)
        res = CliRunner().invoke(cli, args)
        wait_stopped(st.dyno.sim)
        assert not st.dyno.sim.enabled and st.dyno.sim.speed == 0.0
        flash = st.flash_file
    assert res.exit_code == 2, res.output
    rec = json.loads(res.stdout)["record"]
    # the pre-flight's seed/key is refused: nothing was flashed, captured or written: a refusal
    assert rec["verdict"] == "error" and rec["error"]["step"] == "pre-flight"
    assert rec["kind"] == "refusal" and rec["refusal_codes"] == ["key_refused"]
    assert rec["captures"] == {} and [s["step"] for s in rec["steps"]] == ["pre-flight", "report"]
    assert "security" in rec["error"]["message"].lower() or "35" in rec["error"]["message"]
    assert active_block_from_file(flash) is None  # nothing was written into a bank
    assert [(r.kind, r.verdict) for r in query_records(db)] == [("refusal", "error")]


@pytest.mark.slow
def test_demo_one_motor_from_the_command_line(tmp_path):
    res = CliRunner().invoke(cli, ["demo", "--motors", "1", "--out", str(tmp_path / "demo")])
    assert res.exit_code == 0, res.output
    assert "DEMO-0001" in res.output and "pass" in res.output
    (rec,) = query_records(tmp_path / "demo" / "results.sqlite")
    assert rec.verdict == "pass" and rec.station.extra["demo"] is True
    assert Path(rec.report_dir, "report.html").exists()
    assert (tmp_path / "demo" / "limits.toml").exists()
    # it ends pointing at both pages; the lot page links the motor's report relative to itself
    lot = (tmp_path / "demo" / "lot.html").read_text()
    rel = Path(rec.report_dir).relative_to(tmp_path / "demo").as_posix()
    assert f'href="{rel}/report.html"' in lot
    assert "lot page:" in res.output and "report.html" in res.output


def test_windows_split_where_the_rounded_segment_starts_say():
    import numpy as np

    from eol_cal.capture.data import Capture
    from eol_cal.capture.windows import split_windows as split_segments

    # the dyno writes segment_starts to the microsecond: 3.7975246 s is written 3.797525
    t = np.concatenate([np.arange(100) / 1e4, 3.7975246 + np.arange(120) / 1e4, 5.2000004 + np.arange(80) / 1e4])
    cap = Capture(t, {"torque": np.arange(300.0)}, {"serial": "S", "segment_starts": "0.000000,3.797525,5.200000",
                                                      "segments": 3}, source="dyno")
    pieces = split_segments(cap)
    assert [len(p.t) for p in pieces] == [100, 120, 80]
    assert [p["torque"][0] for p in pieces] == [0.0, 100.0, 220.0]
    assert all(np.ptp(np.diff(p.t)) < 1e-9 for p in pieces)
    assert "segment_starts" not in pieces[1].metadata and pieces[1].source == "dyno#2"


@pytest.mark.slow
def test_report_page_opens_offline_in_chromium(full_run, tmp_path):
    """The run's report.html in headless Chromium from file://, network off: nothing fetched
    but the file itself (and its inline data: images), no console error, every plot drawn,
    the verdict and every limit row there, at most two A4 pages printed."""
    from _chromium import Chromium, element_sizes, not_blank, pdf_pages
    from playwright.sync_api import expect

    rec = full_run["rec"]
    page = Path(rec["report_dir"]) / "report.html"
    with Chromium() as b:
        log = b.open(page.as_uri())
        p = b.page
        expect(p.locator("#verdict")).to_have_text(rec["verdict"].upper())
        sizes = element_sizes(p, "svg.plot")
        rows = p.locator("tr.limit-row").evaluate_all("rs => rs.map(r => [r.dataset.key, r.lastElementChild.textContent])")
        b_ecu = p.locator("#ecu").text_content()
        residual_panels = p.locator("#fig-residual g[id^=residual-segment-]").count()
        shot = b.screenshot(tmp_path / "report.png")
        pages = pdf_pages(b.pdf())
    assert b.left_behind == []
    assert log.console_errors == []
    assert [u for u in log.requests if not u.startswith("data:")] == [page.as_uri()]
    assert len(sizes) == 3 and all(s["w"] > 100 and s["h"] > 100 for s in sizes), sizes
    assert [k for k, _ in rows] == [c["key"] for c in rec["checks"]]  # the record's checks; an optional limit left off is none
    assert all(status in ("PASS", "FAIL") for _, status in rows)
    # the ECU's state in the record is on the page: CRCs and flags of both blocks
    ecu = b_ecu
    for text in (*(b["crc32"] for b in rec["blocks"]), "COMP_ENABLE|INTERP_ENABLE"):
        assert text in ecu
    # every fitted segment has its residual panel (the record lists them)
    assert residual_panels == len(rec["fit"]["segments"])
    colours, spread = not_blank(shot)
    assert colours > 50 and spread > 10
    assert 1 <= pages <= 2


@pytest.mark.slow
def test_one_record_shape_whether_the_cycle_passed_failed_or_erred(full_run, files, tmp_path):
    """eol_cal.station.outcome.to_record: the same keys and the run-record schema on pass, fail (at the fit) and refusal."""
    from eol_cal.schemas import validator

    check = validator("run-record")
    low = tmp_path / "low.toml"  # a k6 limit no motor meets: the cycle stops after the fit, nothing flashed
    low.write_text(LIMITS.split("[variant.TIGHT]")[0].replace("max_k6 = 0.0025", "max_k6 = 0.00001"))
    wrong = tmp_path / "wrong.hex"
    wrong.write_text("00" * 16)
    records = {"pass": full_run["rec"]}
    with loopback_station("R-1", 5, tmp_path / "sim", spec_for=lambda req: MOTOR) as st:
        args = run_args(files, st, "R-1", tmp_path / "r.sqlite", tmp_path / "reports")
        args[args.index("--limits") + 1] = str(low)
        res = CliRunner().invoke(cli, args)
        assert res.exit_code == 1, res.output
        records["fail"] = json.loads(res.stdout)["record"]
        args[args.index("--key-file") + 1] = str(wrong)
        res = CliRunner().invoke(cli, args)
        assert res.exit_code == 2, res.output
        records["error"] = json.loads(res.stdout)["record"]
    for verdict_, rec in records.items():
        assert rec["verdict"] == verdict_
        check.validate(rec)
        assert RunRecord.from_json(rec).to_json() == rec
    assert {frozenset(r) for r in records.values()} == {frozenset(records["pass"])}
    fail = records["fail"]
    assert [s["step"] for s in fail["steps"]] == ["pre-flight", "prepare ECU", "acquire", "fit", "report"]
    assert any("max_k6" in r for r in fail["reasons"]) and fail["error"] is None
    assert [b["role"] for b in fail["blocks"]] == ["prepare"]
    assert fail["ecu_active"]["block"] == "uncompensated" and fail["fit"]["status"] == "ok"
    # judged once: the fit's limits at the fit (max_k6 failed), the ripple's not judged (never reached)
    status = {c["key"]: c["pass"] for c in fail["checks"]}
    assert status["max_k6"] is False and status["min_r2"] is True and status["max_pp_after_pct"] is None
    err = records["error"]
    assert err["error"]["step"] == "pre-flight" and err["fit"] is None and err["safe_state"] is not None
    assert err["kind"] == "refusal" and err["refusal_codes"] == ["key_refused"]


@pytest.mark.slow  # a whole station run
def test_records_json_matches_its_schema(full_run):
    from eol_cal.schemas import validator

    res = CliRunner().invoke(cli, ["records", "--db", str(full_run["db"]), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert [r["serial"] for r in doc["records"]] == [SERIAL] and doc["schema"] == "eol-cal/records/2"
    validator("records").validate(doc)
