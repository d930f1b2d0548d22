"""A faulted dyno recovered on purpose (issue 36, class 7): ``eol-cal dyno-clear`` clears a
latched fault through the register map once the operator confirms, and a run that a dyno fault
ends after the prepare step records that the motor is left uncalibrated, and why.

Real parts: the dyno simulator over Modbus TCP on 127.0.0.1 (both shipped register maps), the
loopback station (ECU simulator over python-can-remote).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.dyno.mapfile import load_register_map
from eol_cal.dyno.registers import DriveState, Fault, SimFault
from eol_cal.dyno.sim_dyno import DynoSim, DynoSimThread, FaultPlan
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.ecu import protocol as P
from eol_cal.sim.loopback import loopback_station

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def _latched(th: DynoSimThread, fault: Fault) -> None:
    th.call(th.sim._trip, fault)  # what the dyno's own watchdog or sensor does
    assert th.call(th.sim.drive_state) == DriveState.TRIPPED


@pytest.mark.parametrize("regmap", ["default", "vendor-b"])
@pytest.mark.parametrize("fault", [Fault.COMM_WATCHDOG, Fault.OVER_SPEED, Fault.TORQUE_SENSOR,
                                   Fault.COMM_WATCHDOG | Fault.CAPTURE])
def test_a_confirmed_clear_resets_the_latched_fault_and_starts_nothing(regmap, fault):
    with DynoSimThread(DynoSim(synthetic_source, register_map=load_register_map(regmap))) as th:
        _latched(th, fault)
        res = CliRunner().invoke(cli, ["dyno-clear", "--dyno", f"127.0.0.1:{th.port}", "--register-map", regmap],
                                 input="yes\n")
        faults, state, enabled = th.call(lambda: (th.sim.faults, th.sim.drive_state(), th.sim.enabled))
    assert res.exit_code == 0, res.output
    assert "cleared" in res.stdout and fault.name.split("|")[0] in res.stdout
    assert faults == Fault(0) and state == DriveState.DISABLED and not enabled


@pytest.mark.parametrize("answer", ["no\n", "\n", "y\n", ""])
def test_without_the_operators_yes_nothing_is_written(answer):
    with DynoSimThread(DynoSim(synthetic_source)) as th:
        _latched(th, Fault.COMM_WATCHDOG)
        res = CliRunner().invoke(cli, ["dyno-clear", "--dyno", f"127.0.0.1:{th.port}"], input=answer)
        faults = th.call(lambda: th.sim.faults)
    assert res.exit_code == 2, res.output
    assert "nothing was written" in res.stderr.strip().splitlines()[-1]
    assert faults == Fault.COMM_WATCHDOG


def test_a_dyno_without_a_fault_is_left_alone():
    with DynoSimThread(DynoSim(synthetic_source)) as th:
        writes_before = th.call(lambda: len(th.sim.log))
        res = CliRunner().invoke(cli, ["dyno-clear", "--dyno", f"127.0.0.1:{th.port}", "--yes"])
        writes_after = th.call(lambda: len(th.sim.log))
    assert res.exit_code == 0 and "no fault latched" in res.stdout, res.output
    assert writes_after == writes_before


def test_an_unreachable_dyno_is_one_line_and_exit_2():
    res = CliRunner().invoke(cli, ["dyno-clear", "--dyno", "127.0.0.1:1", "--yes", "--timeout", "0.2"])
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert res.stderr.strip().splitlines()[-1].startswith("error:")


@pytest.mark.slow  # two station cycles (10-20 s each)
def test_a_fault_after_prepare_records_the_motor_uncalibrated_and_dyno_clear_lets_the_next_run_in(tmp_path):
    limits = tmp_path / "limits.toml"
    limits.write_bytes((FIXTURES / "limits.toml").read_bytes())
    key = tmp_path / "k.key"
    key.write_text(P.DEV_SECRET.hex())
    with loopback_station("F-9", 7, tmp_path / "sim", source=synthetic_source,
                          faults=(FaultPlan(SimFault.TORQUE_SENSOR, "capture", 2),)) as st:
        args = ["run", "--dyno", st.dyno_address, "--interface", "remote", "--channel", st.can_channel, "--limits",
                str(limits), "--variant", "EPS-STD", "--db", str(tmp_path / "r.sqlite"), "--key-file", str(key),
                "--report-dir", str(tmp_path / "reports"), "--spool-dir", str(tmp_path / "spool"), "--json",
                "--serial", "F-9"]
        first = CliRunner().invoke(cli, args)
        refused = CliRunner().invoke(cli, args)
        cleared = CliRunner().invoke(cli, ["dyno-clear", "--dyno", st.dyno_address, "--yes"])
        faults = st.dyno.call(lambda: st.dyno.sim.faults)
    rec = json.loads(first.stdout)["record"]
    assert first.exit_code == 2 and rec["ecu_active"]["block"] == "uncompensated", first.output
    said = [r for r in rec["reasons"] if r.startswith("motor not calibrated")]
    assert len(said) == 1 and "acquire" in said[0] and "dyno-clear" in said[0] and "ecu restore" in said[0]
    codes = json.loads(refused.stdout)["record"]["refusal_codes"]
    assert "dyno_fault" in codes or "dyno_tripped" in codes, refused.output
    assert cleared.exit_code == 0 and faults == Fault(0), cleared.output


def test_the_watchdog_counts_the_clients_silence_not_a_stall_of_the_simulator():
    """The simulator updates itself every 10 ms while it serves. A step of 3 s is a stall of its own
    (its thread starved on a loaded machine, the client's requests waiting in its socket): no trip,
    where it tripped the watchdog of a client that kept asking (bench_station.py beside a busy
    loop). 0.6 s of its own steps without a request is the client's silence: a trip."""
    sim = DynoSim(synthetic_source)
    sim.watchdog_ms = 500
    sim.enabled = True
    t0 = sim._t_last
    sim.advance(t0 + 3.0)
    assert not sim.faults & Fault.COMM_WATCHDOG and sim.enabled
    for k in range(1, 61):
        sim.advance(t0 + 3.0 + 0.01 * k)
    assert sim.faults & Fault.COMM_WATCHDOG and not sim.enabled
