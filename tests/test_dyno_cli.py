"""``eol-cal acquire`` and ``eol-cal dyno-sim`` through click and as real processes on 127.0.0.1."""

from __future__ import annotations

import logging
import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.capture import read_capture
from eol_cal.dyno.registers import SimFault
from eol_cal.dyno.sim_dyno import DynoSim, DynoSimThread, FaultPlan
from eol_cal.dyno.sim_capture import synthetic_source

pytestmark = pytest.mark.slow  # process-level or multi-second: not in the fast loop

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

PROFILE = """
name = "short"
[[segment]]
speed_rpm = 60.0
iq = 30.0
seconds = 0.4

[[segment]]
speed_rpm = -90.0
torque_nm = -1.5
seconds = 0.4
ramp_s = 0.1
"""


@pytest.fixture
def profile(tmp_path: Path) -> Path:
    p = tmp_path / "short.toml"
    p.write_text(PROFILE)
    return p


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_acquire_writes_a_capture(tmp_path: Path, profile: Path):
    out = tmp_path / "cap.csv"
    with DynoSimThread(DynoSim(synthetic_source, serial="M-CLI")) as th:
        r = CliRunner().invoke(cli, ["acquire", "--dyno", f"127.0.0.1:{th.port}", "--profile", str(profile), "-o", str(out),
                                     "--json", "--split-windows"])
    assert r.exit_code == 0, r.output
    cap = read_capture(out)
    assert cap.metadata["serial"] == "M-CLI" and cap.metadata["segments"] == 2
    assert len(cap.t) == 4000 + 3000  # 0.4 s and 0.4 - 0.1 s at 10 kHz
    assert '"samples": 7000' in r.output
    w1, w2 = read_capture(tmp_path / "cap.w1.csv"), read_capture(tmp_path / "cap.w2.csv")
    assert (len(w1.t), len(w2.t)) == (4000, 3000) and w1.metadata["segments"] == 1
    assert w1["speed"][0] == 60.0 and w2["speed"][0] == -90.0


def test_acquire_refuses_bad_output_and_address(tmp_path: Path, profile: Path):
    r = CliRunner().invoke(cli, ["acquire", "--dyno", "127.0.0.1:5020", "--profile", str(profile), "-o", str(tmp_path / "x.txt")])
    assert r.exit_code == 2 and "x.txt" in r.output and ".csv or .mf4" in r.output
    r = CliRunner().invoke(cli, ["acquire", "--dyno", "localhost:50x", "-o", str(tmp_path / "x.csv")])
    assert r.exit_code == 2 and "'50x' is not a number" in r.output
    r = CliRunner().invoke(cli, ["acquire", "--dyno", ":5020", "-o", str(tmp_path / "x.csv")])
    assert r.exit_code == 2 and "HOST:PORT" in r.output


def test_acquire_dyno_without_port_uses_modbus_502(tmp_path: Path, profile: Path):
    # nothing listens on 127.0.0.1:502 here (a privileged port): the refusal names the port tried
    r = CliRunner().invoke(cli, ["acquire", "--dyno", "127.0.0.1", "--profile", str(profile), "-o", str(tmp_path / "x.csv"),
                                 "--retries", "0", "--timeout", "0.2"])
    assert r.exit_code == 2 and "dyno 127.0.0.1:502" in r.output, r.output


def test_acquire_unreachable_dyno_exit_2_no_file(tmp_path: Path, profile: Path):
    out = tmp_path / "cap.mf4"
    port = _free_port()  # nothing listens there
    r = CliRunner().invoke(cli, ["acquire", "--dyno", f"127.0.0.1:{port}", "--profile", str(profile), "-o", str(out),
                                 "--retries", "1", "--timeout", "0.2"])
    assert r.exit_code == 2
    assert "failed after 2 attempts" in r.output and "safe state NOT confirmed" in r.output
    assert not list(tmp_path.glob("cap*")) and not list(tmp_path.glob(".cap*"))


def test_acquire_fault_exit_2_no_file(tmp_path: Path, profile: Path):
    out = tmp_path / "cap.mf4"
    sim = DynoSim(synthetic_source, faults=[FaultPlan(SimFault.OVER_SPEED, "capture", 2)])
    with DynoSimThread(sim) as th:
        r = CliRunner().invoke(cli, ["acquire", "--dyno", f"127.0.0.1:{th.port}", "--profile", str(profile), "-o", str(out)])
    assert r.exit_code == 2 and "OVER_SPEED" in r.output and "drive disabled" in r.output
    assert not sim.enabled and sim.setpoint == 0.0
    assert not list(tmp_path.glob("cap*")) and not list(tmp_path.glob(".cap*"))


@pytest.mark.parametrize("register_map", ["default", "vendor-b"])
def test_dyno_sim_and_acquire_as_processes(tmp_path: Path, profile: Path, register_map: str):
    exe = [sys.executable, "-m", "cli.main"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    port = _free_port()
    server = subprocess.Popen(exe + ["dyno-sim", "--listen", f"127.0.0.1:{port}", "--source", "synthetic", "--serial", "M-PROC",
                                     "--register-map", register_map],
                              stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = server.stderr.readline()
        assert re.search(rf"on 127\.0\.0\.1:{port}\b", line), line
        out = tmp_path / "cap.mf4"
        r = subprocess.run(exe + ["acquire", "--dyno", f"127.0.0.1:{port}", "--profile", str(profile), "-o", str(out),
                                  "--register-map", register_map],
                           capture_output=True, text=True, timeout=60, env=env)
        assert r.returncode == 0, r.stderr
        assert read_capture(out).metadata["serial"] == "M-PROC"
        if register_map == "vendor-b":  # the client on the other map is stopped at once, in one line
            other = subprocess.run(exe + ["acquire", "--dyno", f"127.0.0.1:{port}", "--profile", str(profile),
                                          "-o", str(tmp_path / "x.mf4"), "--retries", "0"],
                                   capture_output=True, text=True, timeout=60, env=env)
            lines = [ln for ln in other.stderr.splitlines() if ln.strip()]
            assert other.returncode == 2 and len(lines) == 1 and not (tmp_path / "x.mf4").exists(), other.stderr
            assert "is " in lines[0] and "default.toml this dyno's register map?" in lines[0]
            assert "write" not in lines[0]  # nothing written on a layout the map does not describe
        # a second simulator on the same port is refused cleanly
        r2 = subprocess.run(exe + ["dyno-sim", "--listen", f"127.0.0.1:{port}", "--source", "synthetic"],
                            capture_output=True, text=True, timeout=30, env=env)
        assert r2.returncode == 2 and "--listen" in r2.stderr
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(10)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


def test_the_plant_backed_simulator_runs_its_tick_loop_as_one_kernel():
    # as `eol-cal simulate` and the station's fit: ~40 % less of the simulator's CPU a capture
    # (docs/benchmarks.md), whatever XLA_FLAGS the caller's environment held (none here)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    server = subprocess.Popen([sys.executable, "-m", "cli.main", "dyno-sim", "--listen", f"127.0.0.1:{_free_port()}",
                               "--source", "plant"], stderr=subprocess.PIPE, text=True,
                              env={**env, "PYTHONUNBUFFERED": "1"})
    try:
        assert "dyno simulator on 127.0.0.1" in server.stderr.readline()
        ready = server.stderr.readline()
        assert ready.startswith("plant ready") and "its tick loop one XLA kernel" in ready, ready
    finally:
        server.send_signal(signal.SIGINT)
        try:
            assert server.wait(30) == 0
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
            raise


def test_bad_register_map_is_one_line_naming_file_and_key(tmp_path: Path, profile: Path):
    bad = tmp_path / "rig.toml"
    bad.write_text("[window]\naddress = 1\n")
    for args in (["acquire", "--dyno", "127.0.0.1:1", "--profile", str(profile), "-o", str(tmp_path / "c.csv")],
                 ["dyno-sim", "--listen", "127.0.0.1:0"]):
        r = CliRunner().invoke(cli, args + ["--register-map", str(bad)])
        assert (r.exit_code == 2 and r.output.count("\n") == 1 and "rig.toml" in r.output
                and "window.registers" in r.output), r.output
        r = CliRunner().invoke(cli, args + ["--register-map", "vendor-z"])
        assert r.exit_code == 2 and "vendor-z" in r.output and "vendor-b" in r.output, r.output


def test_bad_profile_refused_before_the_shaft_turns(tmp_path: Path):
    prof = tmp_path / "bad.toml"
    prof.write_text("[[segment]]\nspeed_rpm = 60.0\niq = 10.0\nseconds = 0.2\nramp_s = 0.2\n")
    sim = DynoSim(synthetic_source)
    with DynoSimThread(sim) as th:
        r = CliRunner().invoke(cli, ["acquire", "--dyno", f"127.0.0.1:{th.port}", "--profile", str(prof),
                                     "-o", str(tmp_path / "c.csv")])
    assert r.exit_code == 2 and "segment 1" in r.output and "fewer than 2 samples" in r.output
    assert "enable" not in [name for _, name, _ in sim.log] and sim.captures_started == 0
