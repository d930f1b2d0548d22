"""Dyno client against the real pymodbus server of the dyno simulator, on 127.0.0.1.

The simulator's capture source here is the analytic model (``synthetic_source``) so these tests
need no JAX; the plant-backed source is exercised in test_dyno_sim.py. Every test runs on both
register maps shipped: the reference layout and vendor B's (other addresses and tables, CDAB
word order, scaled integers, other codes).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from eol_cal.capture import read_capture
from eol_cal.dyno.client import DynoError
from eol_cal.dyno.profile_run import acquire
from eol_cal.dyno.setpoints import DynoSetpoint
from eol_cal.dyno.transfer import DynoConfig
from eol_cal.dyno.mapfile import load_register_map
from eol_cal.dyno.registers import SimFault
from eol_cal.dyno.sim_dyno import DynoSim, DynoSimThread, FaultPlan
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.domain.motor_params import load_motor

MOTOR = load_motor("paper")
POLES, PPR = MOTOR.poles, MOTOR.N_enc


PROFILE = [
    DynoSetpoint(60.0, 0.35, iq=20.0, ramp_rpm_s=3000.0),
    DynoSetpoint(120.0, 0.25, iq=65.0, ramp_rpm_s=3000.0),
    DynoSetpoint(-60.0, 0.35, iq=-40.0, ramp_rpm_s=3000.0),
]


@pytest.fixture(params=["default", "vendor-b"])
def regmap(request):
    return load_register_map(request.param)


def config(port: int, regmap, **kw) -> DynoConfig:
    base = dict(host="127.0.0.1", port=port, timeout=0.5, retries=3, retry_delay=0.05, settle_timeout=60.0, capture_timeout=120.0,
                register_map=regmap)
    base.update(kw)
    return DynoConfig(**base)


@pytest.fixture
def dyno(regmap):
    sim = DynoSim(synthetic_source, serial="M-TEST-1", motor=MOTOR, register_map=regmap)
    with DynoSimThread(sim) as th:
        yield th


def test_profile_end_to_end_into_a_valid_capture_file(dyno, tmp_path: Path, regmap):
    out = tmp_path / "capture.mf4"
    cap = acquire(config(dyno.port, regmap), PROFILE, out, rate_hz=10000)
    assert out.exists()
    back = read_capture(out)
    n = sum(int(round(s.seconds * 10000)) for s in PROFILE)
    assert len(back.t) == n
    assert back.metadata["serial"] == "M-TEST-1"
    assert back.metadata["source"] == "dyno"
    assert int(back.metadata["poles"]) == POLES and int(back.metadata["encoder_ppr"]) == PPR
    assert np.all(np.diff(back.t) > 0)
    # the samples that went through the window are the ones the dyno recorded (f32 on the wire)
    last = dyno.sim.last_capture
    k = int(round(PROFILE[-1].seconds * 10000))
    np.testing.assert_array_equal(back["hall"][-k:], last["hall"])
    np.testing.assert_array_equal(back["enc_b"][-k:], last["enc_b"])
    np.testing.assert_allclose(back["torque"][-k:], last["torque"].astype(np.float32), rtol=0, atol=0)
    np.testing.assert_allclose(back["iq_ref"][-k:], -40.0)
    # segments in order, reverse last, and the drive left stopped and disabled
    assert back["speed"][0] == 60.0 and back["speed"][-1] == -60.0
    assert cap.metadata["segments"] == 3
    _assert_safe(dyno.sim)


def _assert_safe(sim: DynoSim):
    deadline = time.monotonic() + 60.0  # a hang guard: the ramp down takes a fraction of a second
    while time.monotonic() < deadline and sim.speed != 0.0:
        time.sleep(0.02)
    assert not sim.enabled
    assert sim.setpoint == 0.0
    assert sim.speed == 0.0


@pytest.mark.parametrize("kind", [SimFault.OVER_SPEED, SimFault.TORQUE_SENSOR])
def test_fault_during_capture_leaves_safe_state_and_no_file(tmp_path: Path, kind, regmap):
    sim = DynoSim(synthetic_source, serial="M-TEST-2", faults=[FaultPlan(kind, "capture", 2)], register_map=regmap)
    out = tmp_path / "capture.mf4"
    with DynoSimThread(sim) as th:
        with pytest.raises(DynoError) as err:
            acquire(config(th.port, regmap), PROFILE, out)
        _assert_safe(sim)
        # the client itself commanded the safe state (not only the trip)
        names = [name for _, name, _ in sim.log]
        assert "enable" in names[names.index("fault"):]
    assert "speed set to 0 and drive disabled" in str(err.value)
    assert ("OVER_SPEED" if kind == SimFault.OVER_SPEED else "TORQUE_SENSOR") in str(err.value)
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.slow
def test_long_disconnect_fails_safe_and_no_file(tmp_path: Path, regmap):
    # the dyno drops off the network for longer than the client's retries: the client gives up,
    # and the dyno's communication watchdog stops the drive
    sim = DynoSim(synthetic_source, faults=[FaultPlan(SimFault.DISCONNECT, "read", 3, 2500)], register_map=regmap)
    out = tmp_path / "capture.csv"
    with DynoSimThread(sim) as th:
        with pytest.raises(DynoError) as err:
            acquire(config(th.port, regmap, retries=2, watchdog_ms=500), PROFILE, out)
        _assert_safe(sim)
    assert not out.exists() and not list(tmp_path.iterdir())
    assert "failed" in str(err.value)


def test_transient_disconnect_is_retried(tmp_path: Path, regmap):
    sim = DynoSim(synthetic_source, faults=[FaultPlan(SimFault.DISCONNECT, "read", 5, 150)], register_map=regmap)
    out = tmp_path / "capture.csv"
    with DynoSimThread(sim) as th:
        cap = acquire(config(th.port, regmap, retries=4), PROFILE, out)
    assert out.exists()
    assert [n for _, n, _ in sim.log].count("fault") == 1
    back = read_capture(out)
    assert len(back.t) == len(cap.t)
    np.testing.assert_array_equal(back["hall"][-len(sim.last_capture.t):], sim.last_capture["hall"])


def test_split_windows_gives_one_capture_per_segment(dyno, tmp_path: Path, regmap):
    from eol_cal.analysis.angle import capture_angle
    from eol_cal.capture.windows import split_windows

    out = tmp_path / "cap.mf4"
    acquire(config(dyno.port, regmap), PROFILE, out)
    back = read_capture(out)
    windows = split_windows(back)
    assert [len(w.t) for w in windows] == [int(round(s.seconds * 10000)) for s in PROFILE]
    for w, seg in zip(windows, PROFILE, strict=True):
        assert np.all(w["speed"] == seg.speed_rpm)
        ang = capture_angle(w)  # one continuous motion per window: the halls agree with the encoder
        assert np.degrees(ang.hall_residual_rms_rad) < 1.0
        assert ang.speed_rpm == pytest.approx(seg.speed_rpm, rel=1e-3)
    # the same windows come back from the time gaps alone
    no_meta = type(back)(back.t, back.channels, {k: v for k, v in back.metadata.items() if k != "segment_starts"})
    assert [len(w.t) for w in split_windows(no_meta)] == [len(w.t) for w in windows]


@pytest.mark.slow
def test_stuck_heartbeat_stops_the_run(tmp_path: Path, regmap):
    holder: dict = {}

    def hangs_at_second_capture(req):
        if req.capture_index == 2:
            holder["sim"].heartbeat_frozen = 1234  # the dyno's controller hangs; Modbus still answers
            time.sleep(1.5)  # ... and the capture never gets ready in time
        return synthetic_source(req)

    sim = DynoSim(hangs_at_second_capture, register_map=regmap)
    holder["sim"] = sim
    out = tmp_path / "capture.mf4"
    with DynoSimThread(sim) as th:
        with pytest.raises(DynoError, match="heartbeat stuck at 1234"):
            acquire(config(th.port, regmap), PROFILE, out)
        _assert_safe(sim)
    assert not list(tmp_path.iterdir())


def test_the_callers_work_before_the_first_capture_keeps_the_dyno_watchdog_fed(dyno, regmap):
    """The caller's work before the first capture (the station reads the ECU's state there, while the
    shaft ramps) takes three times the dyno's communication watchdog, as an ECU slow to answer would:
    the client reads the dyno's status meanwhile, so the watchdog never stops the drive (it did, and
    the fault it latched refused every later motor at pre-flight); the work's own error still ends the
    run in the safe state."""
    done = []

    def slow() -> None:
        time.sleep(1.5)
        done.append(time.monotonic())

    cap = acquire(config(dyno.port, regmap, watchdog_ms=500), PROFILE, None, rate_hz=10000, before_capture=slow)
    assert done and len(cap.t) == sum(int(round(s.seconds * 10000)) for s in PROFILE)
    assert int(dyno.sim.faults) == 0

    def broken() -> None:
        time.sleep(1.5)
        raise RuntimeError("the ECU did not answer")

    with pytest.raises(RuntimeError, match="the ECU did not answer"):
        acquire(config(dyno.port, regmap, watchdog_ms=500), PROFILE, None, rate_hz=10000, before_capture=broken)
    _assert_safe(dyno.sim)
    assert int(dyno.sim.faults) == 0
