"""The station's instruments (:class:`eol_cal.station.instruments.Instruments`) on the plant, in-process:
what a what-if motor's cycle runs on instead of the loopback simulators' sockets.

The ECU is the ECU simulator (:class:`eol_cal.ecu.sim_ecu.EcuSimulator`) on a python-can ``virtual``
channel of this process: the tester's UDS/ISO-TP client flashes, reads back and reads the state
exactly as on ``eol-cal run``'s bus. The dyno is the rig's capture source
(:func:`eol_cal.sim.rig.plant_source`: the plant running what the ECU's flash file holds) asked for
each capture as the dyno simulator asks it (:class:`~eol_cal.dyno.sim_capture.CaptureRequest`: the
set point as its registers hold it, the capture's number for its noise seed, the lead-in captured
and not read), then put through the register map's encoding and the client's decoding
(:func:`~eol_cal.dyno.sim_capture.capture_to_buffer`, the map's ``words_to_analog`` and
``unpack_digital``) and joined as :func:`eol_cal.dyno.profile_run.assemble` joins the windows: the
capture the production path decodes, without Modbus. Only its time axis differs: a window starts
at its physical time (the ramps and captures before it), not at the wall-clock time a dyno took.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import can
import numpy as np

from eol_cal.capture import validate
from eol_cal.capture.ecu_state import Trace, with_ecu_state
from eol_cal.dyno.mapfile import default_register_map
from eol_cal.dyno.profile_run import DynoWindow, assemble, window_times
from eol_cal.dyno.registers import DriveState, Interlock
from eol_cal.dyno.setpoints import lead_in_samples, lead_point_samples
from eol_cal.dyno.sim_capture import CaptureRequest, CaptureSource, capture_to_buffer
from eol_cal.ecu.flash import NorFlash
from eol_cal.ecu.sim_ecu import EcuSimulator, SimConfig
from eol_cal.ecu.transport import open_bus, private_channel_name
from eol_cal.domain.motor_params import load_motor
from eol_cal.domain.bench_mechanics import SIMULATED_BENCH_KEY
from eol_cal.records.record import DynoStatus, PreflightResult
from eol_cal.sim.rig import plant_source
from eol_cal.station.acquisition import ReadAfter, read_ecu_with
from eol_cal.station.archive import flash_archived
from eol_cal.station.flash_ahead import FlashAhead
from eol_cal.station.instruments import Flashed, OpenFlash
from eol_cal.station.preflight import check_ecu, serial_problems

if TYPE_CHECKING:
    from eol_cal.capture.data import Capture
    from eol_cal.domain.motor_params import MotorParams
    from eol_cal.dyno.profile_run import WindowHook
    from eol_cal.dyno.regmap import RegisterMap
    from eol_cal.dyno.setpoints import DynoSetpoint
    from eol_cal.ecu.session import ClientTiming
    from eol_cal.plant.params import PlantSpec


def _f32(x: float) -> float:
    """A value as the dyno's float32 register holds it."""
    return float(np.float32(x))


class PlantInstruments:
    """The plant and the ECU simulator of one motor, in-process (module doc).

    Parameters
    ----------
    serial : str
        The motor's serial (the ECU's F18C and the dyno's DUT serial).
    seed : int
        The dyno's noise seed (its captures' seeds, as the dyno simulator's).
    source : CaptureSource
        The recording of each capture (:func:`eol_cal.sim.rig.plant_source`).
    open_bus : callable
        Opens a tester bus to the ECU simulator.
    seed_to_key, timing, motor
        The ECU's security algorithm, the tester's timing, the station's motor.
    register_map : RegisterMap, optional
        The dyno's register layout (default: the reference map).
    """

    def __init__(self, serial: str, seed: int, source: CaptureSource, open_bus: Callable[[], object], *,
                 seed_to_key: Callable[[bytes], bytes], timing: ClientTiming, motor: MotorParams,
                 register_map: RegisterMap | None = None) -> None:
        self.serial, self.seed, self.source = serial, seed, source
        self.open_bus, self.seed_to_key, self.timing, self.motor = open_bus, seed_to_key, timing, motor
        self.regmap = default_register_map() if register_map is None else register_map
        self.dyno_motor = load_motor("paper")  # the dyno simulator's identification (loopback_station's)
        self.captures = 0  # captures started, as the dyno counts them (each capture's noise seed)
        self.sim_bench = ""  # the last capture's claim of the torque path its plant ran (the simulator's register)

    @property
    def channels(self) -> frozenset[str]:
        return frozenset(self.regmap.channels)

    def _ident(self) -> dict:
        """The identification registers as the client decodes them."""
        m = self.regmap
        values: dict[str, float | int | str] = {
            "map_version": m.map_version or 0, "dut_serial": self.serial, "dut_poles": self.dyno_motor.poles,
            "dut_encoder_ppr": self.dyno_motor.N_enc, "dut_kt": self.dyno_motor.kt, "sim_bench": self.sim_bench}
        return {k: m.decode(k, m.encode(k, v)) for k, v in values.items() if k in m}

    def preflight(self, serial: str) -> PreflightResult:
        ident = self._ident()
        dyno = DynoStatus(map_version=int(ident["map_version"]), dut_serial=str(ident.get("dut_serial") or ""),
                          faults=0, interlocks=int(Interlock.ALL), drive_state=int(DriveState.DISABLED))
        ecu, problems = check_ecu(self.open_bus, self.seed_to_key, self.timing)
        return PreflightResult(dyno, ecu, tuple(problems + serial_problems(serial, ecu.state, dyno.dut_serial)))

    def _record(self, seg: DynoSetpoint, n_samples: int, rate_hz: int, names: Sequence[str], skip: int
                ) -> dict[str, np.ndarray]:
        """One capture as the dyno records it and the client reads it (samples ``skip`` on)."""
        kind, value = seg.command()
        self.captures += 1
        req = CaptureRequest(speed_rpm=_f32(abs(seg.speed_rpm)) * (-1.0 if seg.speed_rpm < 0 else 1.0),
                             dut_cmd_kind=kind, dut_cmd=_f32(value), n_samples=n_samples, rate_hz=float(rate_hz),
                             serial=self.serial, seed=self.seed, capture_index=self.captures)
        recorded = self.source(req)
        self.sim_bench = str(recorded.metadata.get(SIMULATED_BENCH_KEY, ""))
        buffer = capture_to_buffer(recorded, n_samples, self.regmap)
        m = self.regmap
        out: dict[str, np.ndarray] = {}
        for name in names:
            cid = m.channels[name]
            if cid in buffer:
                per = m.regs_per_sample(cid)
                out[name] = m.words_to_analog(buffer[cid][skip * per:])
        digital = buffer[m.window.digital_id]
        per = m.regs_per_sample(m.window.digital_id)
        out["enc_a"], out["enc_b"], out["hall"] = m.unpack_digital(digital[skip * per:])
        return out

    def acquire(self, segments: Sequence[DynoSetpoint], *, serial: str, rate_hz: int, channels: Sequence[str],
                comment: str, on_window: WindowHook | None = None, lead_in_s: float = 0.0,
                lead_in_point: DynoSetpoint | None = None, read_after: ReadAfter | None = None
                ) -> tuple[Capture, Trace]:
        read_ecu = read_ecu_with(self.open_bus, self.timing)
        before = read_ecu()
        data: list[DynoWindow] = []
        t, speed = 0.0, 0.0  # the physical time (s) and the shaft's speed (rpm)
        if lead_in_point is not None:
            # The lead-in point's capture is never read, and each capture's plant starts from
            # power-up (the rig goes on from a capture only in real time): it is counted (its
            # number seeds the next captures' noise), not simulated.
            n_point = lead_point_samples(lead_in_point, rate_hz)
            self.captures += 1
            t += abs(lead_in_point.speed_rpm) / lead_in_point.ramp_rpm_s + n_point / rate_hz
            speed = lead_in_point.speed_rpm
        for i, seg in enumerate(segments):
            n = int(round(seg.seconds * rate_hz))
            lead = lead_in_samples(lead_in_s, rate_hz) if i == 0 else 0
            t += abs(seg.speed_rpm - speed) / seg.ramp_rpm_s + lead / rate_hz
            chans = self._record(seg, n + lead, rate_hz, channels, lead)
            data.append(DynoWindow(t, float(rate_hz), chans))
            t, speed = t + n / rate_hz, seg.speed_rpm
            if on_window is not None:
                on_window(i, data[-1], window_times(data)[-1])
        after = read_ecu() if read_after is None else read_after().result()
        lead_s = lead_in_samples(lead_in_s, rate_hz) / rate_hz
        meta: dict = {"comment": comment, **({"lead_in_s": lead_s} if lead_s or lead_in_point else {})}
        if lead_in_point is not None:
            meta |= {"lead_in_point_rpm": float(lead_in_point.speed_rpm),
                     "lead_in_point_s": lead_point_samples(lead_in_point, rate_hz) / rate_hz}
        capture = validate(assemble(data, self._ident(), serial, meta))
        capture = dataclasses.replace(capture, metadata=with_ecu_state(capture.metadata, before, after))
        return capture, Trace(before, after)

    def flash(self, data: bytes, *, role: str, path: Path, source: str,
              before_commit: Callable[[], None] | None = None, read_back: bool = True) -> Flashed:
        return flash_archived(self.open_bus, data, role=role, path=path, seed_to_key=self.seed_to_key,
                              timing=self.timing, motor=self.motor, source=source, before_commit=before_commit,
                              read_back=read_back)

    def flash_ahead(self, traced: bool = False) -> OpenFlash:
        return FlashAhead(self.open_bus, seed_to_key=self.seed_to_key, timing=self.timing, motor=self.motor,
                          traced=traced)

    def safe_state(self) -> str:
        # the in-process dyno turns only inside a capture's request: it stands between two
        return "speed 0, drive disabled (confirmed)"


@contextlib.contextmanager
def plant_instruments(serial: str, seed: int, work_dir: str | Path, spec_for: Callable[[CaptureRequest], PlantSpec],
                      *, seed_to_key: Callable[[bytes], bytes], timing: ClientTiming, motor: MotorParams
                      ) -> Iterator[PlantInstruments]:
    """One motor's :class:`PlantInstruments`: the ECU simulator on a private virtual channel with its
    flash file in ``work_dir``, the rig's plant (``spec_for``) behind the dyno; stopped on exit."""
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    flash_file = work_dir / f"{serial}.flash"
    channel = private_channel_name()
    ecu = EcuSimulator(can.Bus(interface="virtual", channel=channel), NorFlash(flash_file),
                       SimConfig(serial=serial)).start()
    try:
        yield PlantInstruments(serial, seed, plant_source(flash_file, spec_for),
                               lambda: open_bus("virtual", channel), seed_to_key=seed_to_key,
                               timing=timing, motor=motor)
    finally:
        ecu.stop()
        ecu.bus.shutdown()


__all__ = ["PlantInstruments", "plant_instruments"]
