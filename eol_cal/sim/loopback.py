"""A station on loopback: ECU simulator + dyno simulator per motor, for ``eol-cal demo`` and tests.

Per motor: an ECU simulator on its own flash file (python-can-remote server on 127.0.0.1 in a child
process, :func:`eol_cal.sim.remote_ecu.spawn_remote`, so the tester reaches it exactly as
``eol-cal run --interface remote --channel ws://...`` would, from a process of its own), and a
dyno simulator (pymodbus on 127.0.0.1) whose motor is the built-in plant and whose compensation
comes from that same flash file (the rig's capture source, :mod:`eol_cal.sim.rig`). Both bind
free ports and are shut down when the motor is done.

:func:`loopback_line` keeps one dyno simulator and one ECU server at fixed addresses for many
motors, as a line's station does (the benchmark drives ``eol-cal station`` against it): each
:meth:`LoopbackLine.load` puts the next motor on the dyno and a fresh ECU behind the same URL.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from eol_cal.dyno import sim_dyno as ds
from eol_cal.dyno.client import parse_address
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.dyno.transfer import DynoConfig
from eol_cal.ecu.session import ClientTiming
from eol_cal.ecu.sim_ecu import SimConfig
from eol_cal.ecu.transport import IsoTpTiming, open_bus
from eol_cal.infra.exchange_log import quiet
from eol_cal.domain.motor_params import load_motor
from eol_cal.plant.variation import draw_spec
from eol_cal.sim.remote_ecu import spawn_remote
from eol_cal.sim.rig import plant_source, prepare_plant

if TYPE_CHECKING:
    import can

    from eol_cal.dyno.regmap import RegisterMap
    from eol_cal.dyno.sim_dyno import DynoSimThread, FaultPlan
    from eol_cal.dyno.sim_capture import CaptureRequest, CaptureSource
    from eol_cal.plant.params import PlantSpec
    from eol_cal.sim.remote_ecu import RemoteEcuProcess


#: the tester's timing towards these simulators. The dyno answers from the tester's own process, where
#: the plant computes too, the ECU from a child beside it on the same cores: a loaded machine holds an
#: answer up for as long as it does not schedule that process, not the real ECU's P2 of 50 ms the
#: tester's 0.5 s allows for. Beside a CPU hog at load 19 on 2 cores 7 of 15 state reads (one try
#: each) missed a 0.5 s P2, silent up to 1.4 s: four misses in a row failed a demo motor's
#: acquisition. 5 s (and 5 s between an answer's frames, N_Bs and N_Cr) still bounds a dead simulator.
SIM_ECU_TIMING = ClientTiming(p2_s=5.0, isotp=IsoTpTiming(n_bs_ms=5000, n_cr_ms=5000))
#: ... the tester's Modbus request time-out towards the dyno simulator (s), for the same reason (a real
#: dyno's: ``dyno.timeout_s``, 1 s); four tries (``DynoConfig.retries``) still bound a dead simulator
SIM_DYNO_TIMEOUT_S = 5.0
#: ... and the dyno watchdog the tester sets on them (ms), for the same reason (a real dyno's: 2 s)
SIM_WATCHDOG_MS = 30_000


def demo_motor_spec(seed: int, serial: str) -> PlantSpec:
    """The demo's motor number ``seed``: the plant's production draw around the paper's bench
    (:func:`eol_cal.plant.variation.draw_spec`)."""

    return draw_spec(seed, serial=serial)


@dataclass
class LoopbackStation:
    """The simulators of one motor and how to reach them (``ecu_timing``, ``dyno_timeout_s``,
    ``watchdog_ms``: the tester's settings for simulators in its own process, :data:`SIM_ECU_TIMING`)."""

    serial: str
    dyno_address: str
    can_channel: str
    flash_file: Path
    dyno: DynoSimThread
    ecu: RemoteEcuProcess
    ecu_timing: ClientTiming = SIM_ECU_TIMING
    dyno_timeout_s: float = SIM_DYNO_TIMEOUT_S
    watchdog_ms: int = SIM_WATCHDOG_MS

    def open_bus(self) -> can.BusABC:
        """The tester's bus: python-can ``remote`` to the ECU simulator."""

        return open_bus("remote", self.can_channel)

    def dyno_config(self, register_map: RegisterMap | None = None) -> DynoConfig:
        """The tester's dyno configuration towards this simulator (``register_map``: the one it serves)."""

        host, port = parse_address(self.dyno_address)
        return DynoConfig(host=host, port=port, timeout=self.dyno_timeout_s, watchdog_ms=self.watchdog_ms,
                          register_map=register_map)


@contextlib.contextmanager
def loopback_station(serial: str, seed: int, work_dir: str | Path, *,
                     spec_for: Callable[[CaptureRequest], PlantSpec] | None = None,
                     source: CaptureSource | None = None,
                     faults: tuple[FaultPlan, ...] = (),
                     register_map: RegisterMap | None = None,
                     realtime: bool = False, bitrate: int | None = None,
                     prepare: int | None = None) -> Iterator[LoopbackStation]:
    """Start the ECU and dyno simulators of one motor on 127.0.0.1; stop them on exit.

    Parameters
    ----------
    serial : str
        Motor serial (the ECU's F18C and the dyno's DUT serial).
    seed : int
        Motor draw and noise seed.
    work_dir : path
        Where the ECU's flash file lives.
    spec_for : callable, optional
        ``CaptureRequest -> PlantSpec`` for the rig's plant source (default :func:`demo_motor_spec`).
    source : callable, optional
        A capture source instead of the rig's plant (e.g. ``eol_cal.dyno.sim_capture.synthetic_source``,
        which does not see the ECU).
    faults : tuple of FaultPlan
        Dyno faults that fire by themselves.
    register_map : RegisterMap, optional
        The register layout the dyno simulator serves (default: the reference map).
    realtime : bool
        The dyno simulator in real time: a capture takes its physical time (:class:`~eol_cal.dyno.sim_dyno.DynoSim`).
    bitrate : int or None
        Pace the ECU simulator's bus to this CAN bit rate (bit/s); None: unpaced.
    prepare : int or None
        The estimator options (contract flags bits 2-5) of the blocks the cycle will flash: the rig's
        plant compiles its programs for them before the dyno simulator serves
        (:func:`~eol_cal.sim.rig.prepare_plant`), not inside a capture the tester times. None:
        at the first capture that runs them. Without the rig's plant (``source`` given): ignored.
    """

    quiet(("pymodbus", "isotp", "UdsClient", "Connection", "can", "can_remote"))  # unless an exchange log is on
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    flash_file = work_dir / f"{serial}.flash"
    motor = load_motor("paper")
    ecu = spawn_remote(flash_file, host="127.0.0.1", port=0, config=SimConfig(serial=serial, bitrate=bitrate))
    try:
        if source is None:
            spec = demo_motor_spec(seed, serial)
            spec_of = spec_for or (lambda req: spec)
            source = plant_source(flash_file, spec_of)
            if prepare is not None:
                prepare_plant(spec_of, prepare, serial, seed)
        sim = ds.DynoSim(source, serial=serial, motor=motor, seed=seed, faults=list(faults), register_map=register_map,
                         realtime=realtime)
        with ds.DynoSimThread(sim, "127.0.0.1", 0) as dyno:
            yield LoopbackStation(serial, f"127.0.0.1:{dyno.port}", ecu.url, flash_file, dyno, ecu)
    finally:
        ecu.close()


@dataclass
class LoopbackLine:
    """One station's simulators at fixed addresses for many motors (:func:`loopback_line`)."""

    dyno_address: str
    can_channel: str
    dyno: DynoSimThread
    ecu: RemoteEcuProcess
    work_dir: Path
    bitrate: int | None = None
    serial: str | None = None

    def load(self, serial: str, seed: int) -> Path:
        """The next motor: drawn with ``seed`` on the dyno, a fresh (erased) ECU with ``serial``
        behind the same URL. Returns the ECU's flash file. Call between motors only."""

        flash_file = self.work_dir / f"{serial}.flash"
        flash_file.unlink(missing_ok=True)
        self.ecu.replace(flash_file, SimConfig(serial=serial, bitrate=self.bitrate))
        spec = demo_motor_spec(seed, serial)
        sim = self.dyno.sim
        sim.serial, sim.seed = serial, seed
        sim.source = plant_source(flash_file, lambda req: spec)
        sim.captures.clear()
        self.serial = serial
        return flash_file


@contextlib.contextmanager
def loopback_line(work_dir: str | Path, *, register_map: RegisterMap | None = None, realtime: bool = False,
                  bitrate: int | None = None, prepare: int | None = None) -> Iterator[LoopbackLine]:
    """A dyno simulator and an ECU server on 127.0.0.1 (free ports) that stay for many motors;
    load each motor with :meth:`LoopbackLine.load` before its cycle. Arguments as
    :func:`loopback_station`; ``prepare``: the plant's programs for blocks of these estimator options
    compiled (or loaded from JAX's cache) before the dyno simulator serves, not inside the first
    motor's capture, which its tester times as a real dyno's (they depend on no motor's values)."""

    quiet(("pymodbus", "isotp", "UdsClient", "Connection", "can", "can_remote"))
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    if prepare is not None:
        spec = demo_motor_spec(1, "PREPARE")
        prepare_plant(lambda req: spec, prepare, spec.serial, 1)
    ecu = spawn_remote(work_dir / "idle.flash", host="127.0.0.1", port=0, config=SimConfig(bitrate=bitrate))
    try:
        sim = ds.DynoSim(synthetic_source, serial="IDLE", motor=load_motor("paper"), register_map=register_map,
                         realtime=realtime)
        with ds.DynoSimThread(sim, "127.0.0.1", 0) as dyno:
            yield LoopbackLine(f"127.0.0.1:{dyno.port}", ecu.url, dyno, ecu, work_dir, bitrate)
    finally:
        ecu.close()
