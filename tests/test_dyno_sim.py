"""Dyno simulator and register map: the map is defined once and documented, the server enforces
it, and the ECU's flash file decides what the motor on the dyno runs."""

from __future__ import annotations

import dataclasses

import logging
from pathlib import Path

import numpy as np
import pytest

from eol_cal.dyno import registers as rm
from eol_cal.dyno.client import DynoClient, DynoError
from eol_cal.dyno.setpoints import DynoSetpoint
from eol_cal.dyno.transfer import DynoConfig
from eol_cal.dyno.mapfile import load_register_map
from cli.dyno import parse_fault_plan
from eol_cal.dyno.sim_dyno import DynoSim, DynoSimThread
from eol_cal.dyno.sim_capture import CaptureRequest, synthetic_source
from eol_cal.firmware import block as B

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
DOC = Path(__file__).resolve().parents[1] / "docs" / "dyno.md"
MAPS = ("default", "vendor-b")
#: a hang guard for waits on the simulator (CI at load 16 on 2 cores starves its thread for seconds)
HANG_S = 60.0


@pytest.fixture(params=MAPS)
def regmap(request):
    return load_register_map(request.param)


def test_register_map_doc_lists_every_register():
    text = DOC.read_text()
    # the doc embeds the generated tables verbatim: regenerate with `python -m eol_cal.dyno.mapfile`
    m = load_register_map()
    assert m.markdown_table() in text
    for name in rm.ROLES:
        assert f"`{name}`" in text
    for name in m.channels:
        assert f"`{name}`" in text


def test_register_encoding_round_trips_and_word_order():
    m = load_register_map("default")
    assert m.encode("speed_setpoint", 1.0) == [0x3F80, 0x0000]  # high word first
    assert m.encode("capture_length", 0x12345) == [0x0001, 0x2345]
    assert m.decode("capture_length", [0x0001, 0x2345]) == 0x12345
    assert m.decode("dut_serial", m.encode("dut_serial", "M-0001")) == "M-0001"
    x = np.array([0.0, -1.5, 3.25e-3, 65.0])
    np.testing.assert_array_equal(m.words_to_analog(m.analog_to_words(x)), x.astype(np.float32))
    a, b, h = m.unpack_digital(m.pack_digital([1, 0, 1], [0, 1, 1], [5, 1, 6]))
    assert list(a) == [1, 0, 1] and list(b) == [0, 1, 1] and list(h) == [5, 1, 6]
    assert list(m.pack_digital([1], [1], [5])) == [1 | 2 | 5 << 2]
    with pytest.raises(ValueError):
        m.encode("mode", 70000)


def test_vendor_b_encoding_cdab_scaled_integers_and_codes():
    m = load_register_map("vendor-b")
    assert m.encode("capture_length", 0x12345) == [0x2345, 0x0001]  # low word first ("CDAB")
    assert m.encode("speed_setpoint", 123.4) == [1234, 0]  # 0.1 rpm per count
    assert m.encode("dut_cmd", -1.5) == [(-1500) & 0xFFFF, 0xFFFF]  # mN*m, i32
    assert m.decode("speed", m.encode("speed", -60.0)) == pytest.approx(-60.0)
    assert np.isnan(m.decode("torque", m.encode("torque", float("nan")))) and m.encode("torque", float("nan")) == [0, 0x8000]
    assert m.encode("enable", rm.Switch.ON) == [0x0F] and m.decode("drive_state", [0x13]) == rm.DriveState.AT_SPEED
    assert m.encode("faults", int(rm.Fault.OVER_SPEED | rm.Fault.DRIVE)) == [1 << 3 | 1 << 8]
    assert m.decode("interlocks", [0b1111]) == rm.Interlock.ALL
    with pytest.raises(ValueError, match="code"):
        m.decode("drive_state", [0x12])
    assert list(m.pack_digital([1], [0], [6])) == [1 << 8 | 6 << 4]
    x = np.array([1.0, -2.5])
    assert list(m.analog_to_words(x)) == [0x0000, 0x3F80, 0x0000, 0xC020]
    # the two tables are separate spaces: mode and map_version both at 0
    assert ((m["mode"].table, m["mode"].address) == ("holding", 0)
            and (m["map_version"].table, m["map_version"].address) == ("input", 0))


def _client(port: int, regmap=None) -> DynoClient:
    # the simulator answers from this process: a loaded machine holds an answer up for as long as it
    # does not schedule it (an in-process ECU simulator: 0.5 s missed in 7 of 15 reads beside a CPU
    # hog), and no test here is about a request that goes unanswered
    return DynoClient(DynoConfig(port=port, timeout=5.0, retries=0, register_map=regmap))


def test_server_enforces_the_map(regmap):
    with DynoSimThread(DynoSim(synthetic_source, serial="M-MAP", register_map=regmap)) as dyno:
        c = _client(dyno.port, regmap)
        ident = c.connect()
        assert ident["dut_serial"] == "M-MAP" and ident["map_version"] == regmap.map_version
        with pytest.raises(DynoError, match="refused"):
            c.write(speed=10.0)  # status is read-only
        with pytest.raises(DynoError, match="refused|cannot write"):
            c.write(mode=7)  # refused by the dyno, or (a map with codes) unsayable
        with pytest.raises(DynoError, match="refused"):
            c.write(capture_rate=7000)  # does not divide the 20 kHz tick
        with pytest.raises(DynoError, match="refused"):
            c.write(capture_start=rm.CaptureCommand.ARM)  # drive not enabled
        half = regmap["speed_setpoint"].address + 1
        r = c._client.write_registers(half, [0], device_id=1)  # half of a 32-bit value
        assert r.isError()
        if regmap["drive_state"].table == "holding":  # a status word in the holding table is still read-only
            r = c._client.write_registers(regmap["drive_state"].address, [0], device_id=1)
            assert r.isError()
        dyno.sim.interlocks = rm.Interlock.ALL & ~rm.Interlock.GUARD_CLOSED
        assert c.status()["interlocks"] == rm.Interlock.ALL & ~rm.Interlock.GUARD_CLOSED
        with pytest.raises(DynoError, match="refused"):
            c.write(enable=rm.Switch.ON)
        dyno.sim.interlocks = rm.Interlock.ALL
        c.write(mode=rm.Mode.SPEED, enable=rm.Switch.ON)
        c.write(speed_setpoint=300.0, ramp=3000.0)
        # the ramps take 0.1 s of the simulator's time: the waits are hang guards (the states are checked)
        c.wait(lambda s: s["drive_state"] == rm.DriveState.AT_SPEED, HANG_S, "ramping")
        # AT_SPEED holds within the tolerance, before the ramp's last step: wait for its end
        st = c.wait(lambda s: s["speed"] == pytest.approx(300.0), HANG_S, "ramp end")
        assert st["speed"] == pytest.approx(300.0) and st["drive_state"] == rm.DriveState.AT_SPEED
        assert dyno.sim.setpoint == pytest.approx(300.0) and dyno.sim.ramp == pytest.approx(3000.0)
        with pytest.raises(DynoError, match="refused"):
            c.write(direction=rm.Direction.REVERSE)  # no reversing while spinning
        c.write(stop=rm.Command.EXECUTE)
        st = c.wait(lambda s: s["drive_state"] == rm.DriveState.DISABLED, HANG_S, "stopping")
        assert st["speed"] == 0.0 and c.read(["stop"])["stop"] == rm.Command.IDLE
        c.close()


def test_window_reads_served_from_the_buffer_are_the_datastores_registers(regmap):
    """The simulator answers reads inside its capture window itself (eol_cal.dyno.pdu.server_pdus):
    the registers and the exceptions are those its datastore and request hook give."""
    import asyncio

    from pymodbus.constants import ExcCodes

    sim = DynoSim(synthetic_source, serial="M-WIN", register_map=regmap)
    w = regmap.window
    cid = next(iter(regmap.channels.values()))
    sim.buffer = {cid: (np.arange(3000, dtype=np.uint32) * 7919 % 65536).astype(np.uint16)}
    sim.buf_channel, sim.buf_offset = cid, 100
    fc = 3 if w.table == "holding" or regmap.shared_tables else 4

    def by_hook(address: int, count: int) -> list[int] | ExcCodes:
        registers = [0] * (w.end + 8)
        got = asyncio.run(sim.action(fc, 0, address, count, registers, None))
        return got if got is not None else registers[address:address + count]

    n = regmap.max_read_registers
    reads = [(w.address, n), (w.address + 3, 60), (w.end - n, n), (w.address + 1000, 1)]
    for address, count in reads:
        direct = asyncio.run(sim.direct_read(fc, address, count))
        assert direct == by_hook(address, count) and len(direct) == count
    first = 100 * regmap.regs_per_sample(cid)
    assert asyncio.run(sim.direct_read(fc, w.address, 5)) == sim.buffer[cid][first:first + 5].tolist()
    # what the datastore answers: beyond the window, across its start, the other table
    assert asyncio.run(sim.direct_read(fc, w.address - 1, 2)) is None
    assert asyncio.run(sim.direct_read(fc, w.end - 1, 2)) is None
    assert asyncio.run(sim.direct_read(6, w.address, 1)) is None
    if not regmap.shared_tables:
        assert asyncio.run(sim.direct_read(7 - fc, w.address, 1)) is None
    # a connection being dropped: the same exception either way
    import time
    sim.disconnect_until = time.monotonic() + 60.0
    assert asyncio.run(sim.direct_read(fc, w.address, 2)) == by_hook(w.address, 2) == ExcCodes.DEVICE_BUSY
    sim.disconnect_until = 0.0
    # over TCP
    with DynoSimThread(sim) as dyno:
        c = _client(dyno.port, regmap)
        c.connect()
        read = c._client.read_holding_registers if fc == 3 else c._client.read_input_registers
        assert read(w.address, count=n, device_id=1).registers == sim.buffer[cid][first:first + n].tolist()
        c.close()


def test_fault_register_trips_and_reset_clears(regmap):
    with DynoSimThread(DynoSim(synthetic_source, serial="M-MAP", register_map=regmap)) as dyno:
        c = _client(dyno.port, regmap)
        c.connect()
        c.write(mode=rm.Mode.SPEED, enable=rm.Switch.ON)
        c.write(speed_setpoint=100.0, ramp=5000.0)
        c.write(sim_fault=int(rm.SimFault.TORQUE_SENSOR))
        st = c.status()
        assert st["faults"] & rm.Fault.TORQUE_SENSOR and st["drive_state"] == rm.DriveState.TRIPPED
        assert np.isnan(st["torque"])
        with pytest.raises(DynoError, match="refused"):
            c.write(enable=rm.Switch.ON)  # latched
        c.write(fault_reset=rm.Command.EXECUTE)
        assert c.status()["faults"] == 0
        c.write(enable=rm.Switch.ON)
        c.close()


def test_a_client_on_the_wrong_map_is_stopped_at_connect():
    with DynoSimThread(DynoSim(synthetic_source, register_map=load_register_map("vendor-b"))) as dyno:
        c = _client(dyno.port, load_register_map("default"))
        with pytest.raises(DynoError, match="register map version|refused|raw value"):
            c.connect()
        c.close()


def test_fault_plan_parsing():
    p = parse_fault_plan("disconnect@read:5/300")
    assert (p.kind, p.at, p.index, p.arg_ms) == (rm.SimFault.DISCONNECT, "read", 5, 300)
    assert parse_fault_plan("over-speed").at == "capture"
    for bad in ("melt", "over-speed@capture:0", "disconnect@later:2", "disconnect/0"):
        with pytest.raises(Exception, match="--fault"):
            parse_fault_plan(bad)


def _block(flags: int, sequence: int) -> bytes:
    from eol_cal.domain.motor_params import load_motor

    m = load_motor("paper")
    n = 16
    blk = B.ParamBlock(
        sequence=sequence, flags=flags, serial="M-FLASH", calibrated_at=0, poles=m.poles, encoder_ppr=m.N_enc,
        tick_hz=m.f_pwm, kt=m.kt, hall_angle=(1.0, 3.1, 2.1, 5.2, 0.0, 4.2), c6=0.0, phase_c6=0.0, k6=0.00062,
        phase_k6=0.3, lead_s=1e-3, iqc_limit=6.5, table_const=np.zeros(n, np.float32), table_per_amp=np.zeros(n, np.float32),
    )
    return B.pack(blk)


def test_ecu_flash_decides_the_mode_of_the_next_capture(tmp_path: Path, regmap):
    """The rig reads the ECU simulator's flash at every capture the dyno makes."""
    from eol_cal.ecu.flash import NorFlash
    from eol_cal.sim.rig import ActiveCalibration, with_ecu

    seen: list[tuple[CaptureRequest, ActiveCalibration]] = []

    def recording(req: CaptureRequest, ecu: ActiveCalibration):
        seen.append((req, ecu))
        return synthetic_source(req)

    flash_file = tmp_path / "ecu.flash"
    sim = DynoSim(with_ecu(flash_file, recording), register_map=regmap)
    seg = DynoSetpoint(60.0, 0.2, iq=20.0, ramp_rpm_s=5000.0)

    def capture_once() -> ActiveCalibration:
        c = _client(th.port, regmap)
        c.connect()
        c.set_point(seg)
        c.capture(2000, 10000)
        c.safe_state()
        c.close()
        return seen[-1][1]

    with DynoSimThread(sim) as th:
        assert capture_once().mode == "raw" and seen[-1][1].block is None  # no flash file yet
        flash = NorFlash(flash_file)  # erased: no valid bank
        assert capture_once().mode == "raw"
        flash.program(0, 0, _block(B.FLAG_COMP_ENABLE | B.FLAG_INTERP_ENABLE, 1))
        req = capture_once()
        assert req.mode == "compensated" and req.block.sequence == 1 and req.block.serial == "M-FLASH"
        flash.program(1, 0, _block(B.FLAG_INTERP_ENABLE, 2))  # newer bank, interpolation only
        req = capture_once()
        assert req.mode == "estimated" and req.block.sequence == 2
    assert [r.capture_index for r, _ in seen] == [1, 2, 3, 4]


@pytest.mark.slow
def test_flash_changes_what_the_next_plant_capture_shows(tmp_path: Path):
    """The plant behind the dyno runs the block the ECU's flash holds: raw without a valid bank,
    compensated with the block made from the motor's true ripple once it is programmed."""
    from eol_cal.analysis.angle import capture_angle
    from eol_cal.analysis.spectrum import capture_spectrum
    from eol_cal.ecu.flash import NorFlash
    from eol_cal.sim.rig import plant_source
    from eol_cal.plant.presets import preset_spec
    from eol_cal.plant.ecu_model import true_block

    flash_file = tmp_path / "ecu.flash"
    flash = NorFlash(flash_file)
    spec = preset_spec("paper", serial="M-PLANT")
    sim = DynoSim(plant_source(flash_file, lambda req: spec), serial="M-PLANT")
    seg = DynoSetpoint(60.0, 0.5, iq=65.0, ramp_rpm_s=5000.0)

    def sixth(n: int = 5000) -> float:
        c = DynoClient(DynoConfig(port=th.port, timeout=2.0, retries=1, capture_timeout=120.0))
        c.connect()
        c.set_point(seg)
        c.capture(n, 10000)
        chans = c.read_buffer(["torque", "iq_ref"], n)
        c.safe_state()
        c.close()
        from eol_cal.capture.data import Capture

        cap = Capture(np.arange(n) / 10000.0, chans, {"serial": "M-PLANT", "poles": 6, "encoder_ppr": 64})
        return capture_spectrum(cap, capture_angle(cap)).amplitude(6)

    with DynoSimThread(sim) as th:
        raw = sixth()
        flash.program(0, 0, B.pack(true_block(spec)))
        compensated = sixth()
    assert raw > 0.03  # k6*i_qo = 0.040 N*m plus cogging
    assert compensated < 0.2 * raw


@pytest.mark.slow  # a plant run (seconds on a quiet machine, a minute beside a CPU hog)
def test_the_plant_hands_over_its_capture_in_pieces_that_are_the_capture():
    """The rig's plant gives the dyno each recorded piece as it computes it (a real-time dyno
    answers them while the rest is computed): every piece is the start of the capture it returns."""
    from eol_cal.dyno.registers import DutCmdKind
    from eol_cal.dyno.sim_capture import CaptureRequest
    from eol_cal.sim.rig import ActiveCalibration, plant_capture

    pieces = []
    req = CaptureRequest(speed_rpm=60.0, dut_cmd_kind=DutCmdKind.IQ, dut_cmd=40.0, n_samples=5000, rate_hz=10000.0,
                         serial="M-1", seed=3, capture_index=1, partial=pieces.append)
    whole = plant_capture()(req, ActiveCalibration())
    lengths = [len(p.t) for p in pieces]
    assert len(whole.t) == 5000 and len(pieces) >= 2
    assert lengths == sorted(set(lengths)) and 0 < lengths[0] and lengths[-1] < 5000
    for p in pieces:
        k = len(p.t)
        assert set(p.channels) == set(whole.channels)
        np.testing.assert_array_equal(p.t, whole.t[:k])
        for name, v in p.channels.items():
            np.testing.assert_array_equal(v, whole.channels[name][:k], err_msg=name)
    no_hook = plant_capture()(dataclasses.replace(req, partial=None), ActiveCalibration())
    np.testing.assert_array_equal(no_hook.channels["torque"], whole.channels["torque"])


@pytest.mark.slow  # plant runs (seconds on a quiet machine, a minute or two beside a CPU hog)
def test_the_plant_goes_on_over_a_reversal_while_the_ecu_keeps_its_block(monkeypatch):
    """In real time, a capture after the shaft turned on (a reversal) with the ECU not reset goes
    on from the previous one: the ECU keeps its identification, no pre-roll is computed again, and
    the recording is what a fresh start with the identification already done shows."""
    from eol_cal.dyno.registers import DutCmdKind
    from eol_cal.firmware.contract import FLAG_MECH_COMP_ENABLE, FLAGS_ESTIMATOR
    from eol_cal.plant.ecu_model import true_block
    from eol_cal.plant.presets import preset_spec
    from eol_cal.sim import rig

    spec = preset_spec("paper", serial="M-1")
    flags = B.FLAG_COMP_ENABLE | B.FLAG_INTERP_ENABLE | FLAGS_ESTIMATOR | FLAG_MECH_COMP_ENABLE
    cal = rig.ActiveCalibration("compensated", true_block(spec, flags=flags, mech=True))
    runs = []
    real = rig.simulate

    def simulate(*args, **kw):  # the real plant; what it was asked to run is noted
        runs.append((kw.get("resume") is not None, args[1].seconds))
        return real(*args, **kw)

    monkeypatch.setattr(rig, "simulate", simulate)
    fwd = CaptureRequest(speed_rpm=60.0, dut_cmd_kind=DutCmdKind.IQ, dut_cmd=65.0, n_samples=5000, rate_hz=10000.0,
                         serial="M-1", seed=3, capture_index=1)
    pieces = []
    rev = dataclasses.replace(fwd, speed_rpm=-60.0, dut_cmd=-65.0, capture_index=2, gap_s=0.15, partial=pieces.append)
    source = rig.plant_capture(lambda req: spec)
    source(fwd, cal)
    went_on = source(rev, cal)
    assert runs[1] == (True, pytest.approx(1 / spec.motor.f_pwm + 0.15 + 0.3 + 0.5, abs=2e-4))
    assert len(went_on.t) == 5000 and went_on.t[0] == 0.0 and np.allclose(np.diff(went_on.t), 1e-4)
    for p in pieces:  # the dyno's pieces are the recording's start, never the ramp before it
        np.testing.assert_array_equal(p.channels["torque"], went_on.channels["torque"][:len(p.t)])
    fresh = rig.plant_capture(lambda req: spec)(dataclasses.replace(rev, gap_s=None, partial=None), cal)
    assert runs[2][0] is False  # no gap (the first capture, a drive disabled since): from power-up
    for c in (went_on, fresh):
        assert np.mean(c.channels["speed"]) == pytest.approx(-60.0, rel=0.005)
    assert np.ptp(went_on.channels["torque"]) == pytest.approx(np.ptp(fresh.channels["torque"]), rel=0.25)
    # another block in the ECU (a flash reset it), or too long a gap: from power-up again
    other = rig.ActiveCalibration("compensated", true_block(spec, flags=flags & ~FLAG_MECH_COMP_ENABLE, mech=True))
    source(dataclasses.replace(rev, partial=None), other)
    source(dataclasses.replace(rev, partial=None), other)
    source(dataclasses.replace(rev, partial=None, gap_s=rig.MAX_RESUME_GAP_S + 0.1), other)
    assert [r for r, _s in runs[3:]] == [False, True, False]


def test_the_dyno_package_knows_no_ecu_and_no_block():
    """The rig (eol_cal.sim.rig) wires the ECU in; the dyno package itself imports neither."""
    import subprocess
    import sys

    code = ("import sys, eol_cal.dyno.sim_dyno, eol_cal.dyno.sim_capture, eol_cal.dyno.sim_modbus, eol_cal.dyno.client, "
            "eol_cal.dyno.setpoints, eol_cal.dyno.profile_run, eol_cal.dyno.transfer; "
            "print(sorted(m for m in sys.modules if m.startswith(('eol_cal.ecu', 'eol_cal.firmware', 'eol_cal.station'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
