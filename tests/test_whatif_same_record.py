"""Issue 39's done-when: a what-if lot's motor runs the production steps (run_motor through the one
executor) on the plant in-process (eol_cal/sim/plant_instruments.py: the ECU simulator on a virtual
CAN channel, the dyno's captures through its register map, no sockets), so it and `eol-cal run` on
the loopback simulators give the same record for the same motor and seed but for its kind."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.ecu import protocol as P
from eol_cal.plant.presets import preset_spec
from eol_cal.plant.spread import load_spread
from eol_cal.records.record import RunRecord
from eol_cal.sim.loopback import loopback_station
from eol_cal.sim.plant_instruments import plant_instruments
from eol_cal.station.whatif import simulate_motor
from eol_cal.station.whatif_plan import LotPlan
from test_lot_simulate import LIMITS, PROFILE  # the short calibration profile both use


#: what necessarily differs between the two runs of one motor (record paths; ``*``: any index or
#: key), and why
DIFFERS = {
    "kind": "simulated against production: what the test is about",
    "run_id": "the lot's (from its name and the motor's number) against a new one",
    "started_at": "the runs' times", "ended_at": "the runs' times", "steps.*.seconds": "the runs' times",
    "blocks.*.seconds": "the flashes' times",
    "blocks.*.retries": "requests repeated after an answer came late or was lost: how busy the machine was (one "
                        "repeat in a batch of four motors' threads, the suite beside it at load 8)",
    "station": "the lot's station (sim:NAME, what makes the lot, the drawn motor's truth) against the command "
               "line's (the simulators' addresses)",
    "report_dir": "each run's own directory", "captures.*.path": "in the run's directory",
    "blocks.*.path": "in the run's directory",
    "captures.*.sha256": "the capture file holds the run id and the time it was written",
    # a block holds the time it was made: its bytes, CRC and the ECU's CRC read around the captures
    "blocks.*.sha256": "the block's time", "blocks.*.crc32": "the block's time",
    "captures.*.ecu_before.crc32": "the block's time", "captures.*.ecu_after.crc32": "the block's time",
    "metrics.*.span_s": "the window's place in the joined capture: the time between two windows is the "
                        "wall-clock time the dyno took (eol_cal.dyno.profile_run.window_times), the ramps' "
                        "and captures' physical time in-process (eol_cal.sim.plant_instruments)",
    "fit.segments.*.t_start": "the segment's place in the joined capture", "fit.segments.*.t_end": "the same",
}
#: ... and that time axis is why the figures agree to their 10th digit, not to the bit (two `eol-cal
#: run`s of one motor on the plant differ the same way; 572 of 663 compared fields are bit-equal); every
#: other figure, check and word is equal
REL = 1e-8
#: a passing motor's steps on a station without a gate, and their modules (eol_cal/station/steps/)
PRODUCTION = (("pre-flight", "check_ready"), ("prepare ECU", "prepare_ecu"), ("acquire", "acquire_before"),
              ("fit", "fit_capture"), ("table", "make_table"), ("flash", "flash_calibrated"),
              ("acquire compensated", "acquire_after"), ("metrics", "measure_ripple"), ("verdict", "decide_verdict"),
              ("report", "write_report"), ("record", "save_record"))


def _leaves(doc: object, path: tuple[str, ...] = ()) -> dict[tuple[str, ...], object]:
    if isinstance(doc, dict):
        return {k: v for key, val in doc.items() for k, v in _leaves(val, (*path, str(key))).items()}
    if isinstance(doc, list):
        return {k: v for n, val in enumerate(doc) for k, v in _leaves(val, (*path, str(n))).items()}
    return {path: doc}


def _differs(path: tuple[str, ...]) -> bool:
    for pattern in DIFFERS:
        parts = pattern.split(".")
        if len(path) >= len(parts) and all(p in ("*", q) for p, q in zip(parts, path, strict=False)):
            return True
    return False


def _mismatches(a: dict, b: dict) -> list[str]:
    la = {k: v for k, v in _leaves(a).items() if not _differs(k)}
    lb = {k: v for k, v in _leaves(b).items() if not _differs(k)}
    out = [".".join(k) + ": only in one" for k in set(la) ^ set(lb)]
    for k in set(la) & set(lb):
        x, y = la[k], lb[k]
        same = (math.isclose(x, y, rel_tol=REL, abs_tol=1e-15) if isinstance(x, float) and isinstance(y, float)
                else x == y)
        if not same:
            out.append(f"{'.'.join(k)}: {x!r} != {y!r}")
    return sorted(out)


@pytest.mark.slow  # two station cycles on the plant (about 20 s quiet); the batch test keeps lot simulate in the fast loop
def test_lot_simulate_and_run_on_the_plant_give_the_same_record_but_for_its_kind(tmp_path: Path):
    (tmp_path / "short.toml").write_text(PROFILE)
    (tmp_path / "key.hex").write_text(P.DEV_SECRET.hex())
    plan = LotPlan("SAME", "default", str(LIMITS), "EPS-STD", 2, seed=11, profile=str(tmp_path / "short.toml"))
    i = 1
    events: list = []
    lot_doc = simulate_motor(plan, i, tmp_path / "whatif", plant_instruments, observers=[events.append]).to_json()
    # the same motor, drawn as the spread draws it, on the simulators `eol-cal demo` starts, through `eol-cal run`
    spec = load_spread("default").draw(plan.seed + i, preset_spec("paper"), serial=plan.serial(i))
    with loopback_station(plan.serial(i), plan.seed + i, tmp_path / "sim", spec_for=lambda req: spec) as st:
        res = CliRunner().invoke(cli, [
            "run", "--dyno", st.dyno_address, "--interface", "remote", "--channel", st.can_channel,
            "--limits", str(LIMITS), "--variant", "EPS-STD", "--db", str(tmp_path / "runs.sqlite"),
            "--serial", plan.serial(i), "--profile", str(tmp_path / "short.toml"), "--key-file",
            str(tmp_path / "key.hex"), "--report-dir", str(tmp_path / "reports"), "--spool-dir",
            str(tmp_path / "spool"), "--json"])
    assert res.exit_code in (0, 1), res.output
    run_doc = json.loads(res.stdout)["record"]
    lot, run = RunRecord.from_json(lot_doc), RunRecord.from_json(run_doc)
    assert (lot.kind, run.kind) == ("simulated", "production")
    assert lot.run_id == plan.run_id(i) and lot.station.id == "sim:SAME"
    # a motor measured and judged: the fit's figures, every check, the verdict, the blocks
    assert lot.fit is not None and lot.fit.usable and lot.metrics is not None and lot.checks
    assert [s.step for s in lot.steps] == [s.step for s in run.steps]
    assert _mismatches(lot_doc, run_doc) == []
    # one what-if motor from its pre-flight to its record: each production step's module, in order,
    # through the station's executor
    assert [(e.step, e.what, e.module.rsplit(".", 1)[1]) for e in events] == [
        (step, what, module) for step, module in PRODUCTION for what in ("start", "done")]
    assert {(e.run_id, e.serial) for e in events} == {(plan.run_id(i), plan.serial(i))}
