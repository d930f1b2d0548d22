"""The simulated rig: the built-in plant behind the dyno simulator, running what the ECU
simulator's flash holds.

The dyno simulator (:mod:`eol_cal.dyno.sim_dyno`) knows no ECU: at every capture it asks a capture
source for the recording. The rig's source reads the ECU simulator's flash file at that moment
(:func:`active_calibration`: the active bank's parameter block and the mode its flags select)
and runs the plant with it, so a flash changes what the next capture shows, as on a real line
where the motor's ECU runs the block the tester wrote. :func:`eol_cal.sim.loopback.loopback_station` puts
the two simulators together with this source.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from eol_cal.analysis.fit.table import uncompensated_block
from eol_cal.capture.data import Capture
from eol_cal.dyno.registers import DutCmdKind
from eol_cal.dyno.sim_capture import CaptureRequest, CaptureSource, i_qo_of
from eol_cal.ecu.flash import active_block_from_file
from eol_cal.firmware.block import FLAG_COMP_ENABLE, FLAG_MECH_COMP_ENABLE, ParamBlock, pack, unpack
from eol_cal.firmware.contract import FLAGS_MECH_NEEDS
from eol_cal.firmware.settling import FIRST_EDGES_S
from eol_cal.plant import variation
from eol_cal.plant.ecu_model import mode_of_block, true_block
from eol_cal.plant.params import PlantSpec
from eol_cal.plant.presets import preset_spec
from eol_cal.plant.profile import Profile, ProfileSegment
from eol_cal.plant.simulate import PlantCarry, simulate

#: firmware mode without a valid parameter bank: the raw encoder angle, no compensation
NO_BLOCK_MODE = "raw"


@dataclass(frozen=True)
class ActiveCalibration:
    """What the motor's ECU runs at a capture: the calibration in its active bank.

    Attributes
    ----------
    mode : str
        ``raw``, ``estimated`` or ``compensated``: the angle source and compensation the block's
        flags select (:data:`NO_BLOCK_MODE` without a valid bank).
    block : ParamBlock or None
        The active parameter block, or None without a valid bank.
    """

    mode: str = NO_BLOCK_MODE
    block: ParamBlock | None = None


def active_calibration(flash_file: str | Path | None) -> ActiveCalibration:
    """The ECU's active calibration from its simulator's flash file: the block and its mode.

    No file (not given, or before the ECU simulator created it) or no valid bank: the raw mode
    without a block.
    """
    if flash_file is None or not Path(flash_file).exists():
        return ActiveCalibration()

    data = active_block_from_file(flash_file)
    if data is None:
        return ActiveCalibration()
    block = unpack(data, f"{flash_file} (active bank)")
    return ActiveCalibration(mode_of_block(block), block)


#: ``(request, active calibration) -> capture``: a recording that depends on what the ECU runs
CalibratedCapture = Callable[[CaptureRequest, ActiveCalibration], Capture]


def with_ecu(flash_file: str | Path | None, capture: CalibratedCapture) -> CaptureSource:
    """A dyno capture source that reads the ECU's active calibration at each capture and hands it on."""

    def source(req: CaptureRequest) -> Capture:
        return capture(req, active_calibration(flash_file))

    return source


def default_plant_spec(req: CaptureRequest, preset: str = "paper") -> PlantSpec:
    """The motor on the dyno: the plant preset, or with a seed a motor drawn from production
    tolerances around it (:mod:`eol_cal.plant.variation`)."""
    spec = preset_spec(preset, serial=req.serial)
    if req.seed is None:
        return spec

    return variation.vary(spec, req.seed)


#: longest gap (s) between two captures the rig's plant goes on over (the shaft turning between
#: them); a longer one starts afresh, with the pre-roll
MAX_RESUME_GAP_S = 2.0


@dataclass(frozen=True)
class _Ended:
    """Where the plant's previous capture ended: for whom, at which point, and its scan state."""

    key: tuple
    speed_rpm: float
    i_qo: float
    carry: PlantCarry


def plant_capture(spec_for: Callable[[CaptureRequest], PlantSpec] | None = None) -> CalibratedCapture:
    """The built-in plant (:func:`eol_cal.plant.simulate.simulate`) recording one capture.

    Each capture is simulated from power-up with the ECU's pre-roll
    (:func:`eol_cal.firmware.settling.settle_s`: what a real line's lead-in turns), except in real
    time when the shaft turned on since the previous capture (:attr:`CaptureRequest.gap_s`, at
    most :data:`MAX_RESUME_GAP_S`) for the same motor and the ECU runs the same block (not reset):
    then the plant goes on from where that capture ended, ramping to the new point over the gap
    and settling for :data:`~eol_cal.firmware.settling.FIRST_EDGES_S`, as a real ECU keeps what it
    learned and identified (MECH.md: reversals do not withdraw). So the simulator computes a
    verification's second direction in a fraction of its time, not an identification again.

    Parameters
    ----------
    spec_for : callable, optional
        ``request -> PlantSpec``: the motor on the dyno (default :func:`default_plant_spec`).
    """
    ended: list[_Ended] = []  # the dyno asks for one capture at a time

    def capture(req: CaptureRequest, cal: ActiveCalibration) -> Capture:
        spec = (spec_for or default_plant_spec)(req)
        f_tick = spec.motor.f_pwm
        step = f_tick / req.rate_hz
        if abs(step - round(step)) > 1e-9:
            raise ValueError(f"capture rate {req.rate_hz} Hz does not divide the plant's {f_tick} Hz")
        step = int(round(step))
        iq = i_qo_of(req, spec.motor.kt)
        seconds = req.n_samples * step / f_tick
        seed = (req.seed or 0) * 1000 + req.capture_index
        key = (req.serial, req.seed, cal.mode, None if cal.block is None else pack(cal.block))
        prev = ended.pop() if ended else None
        resume = (prev if prev is not None and prev.key == key and req.gap_s is not None
                  and req.gap_s <= MAX_RESUME_GAP_S else None)
        skip = 0  # ticks simulated before the recording (a resumed run's ramp and settling)
        if resume is None:
            profile = Profile("dyno", (ProfileSegment(speed_rpm=req.speed_rpm, seconds=seconds, iq=iq),))
        else:
            assert req.gap_s is not None  # resume requires it
            lead = int(round((req.gap_s + FIRST_EDGES_S) * f_tick / step)) * step  # on the DAQ's grid
            skip = 1 + lead
            profile = Profile("dyno", (
                ProfileSegment(speed_rpm=resume.speed_rpm, seconds=1.0 / f_tick, iq=resume.i_qo),
                ProfileSegment(speed_rpm=req.speed_rpm, seconds=(lead + req.n_samples * step) / f_tick, iq=iq,
                               ramp_s=max(req.gap_s, 1.0 / f_tick))))

        def daq(cap: Capture) -> Capture:
            # the plant runs at the PWM tick; the dyno's DAQ keeps every step-th sample
            channels = {k: v[skip::step][: req.n_samples] for k, v in cap.channels.items()}
            return Capture(cap.t[skip::step][: req.n_samples] - cap.t[skip] if len(cap.t) > skip else cap.t[:0],
                           channels, dict(cap.metadata), dict(cap.truth), source="<plant>")

        recorded = None
        if (partial := req.partial) is not None:
            def recorded(so_far: list) -> None:  # each piece as it is computed: the dyno's buffer fills with it
                if len(so_far[0].capture.t) > skip:
                    partial(daq(so_far[0].capture))

        out: list[PlantCarry] = []
        result = simulate(spec, profile, mode=cal.mode, blocks=cal.block, seed=seed, recorded=recorded,
                          resume=None if resume is None else resume.carry, carry_out=out)[0]
        ended.append(_Ended(key, req.speed_rpm, iq, out[0]))
        return daq(result.capture)

    return capture


def plant_source(flash_file: str | Path | None,
                 spec_for: Callable[[CaptureRequest], PlantSpec] | None = None) -> CaptureSource:
    """The rig's capture source: the plant running the ECU simulator's active bank.

    Parameters
    ----------
    flash_file : path or None
        The ECU simulator's flash file, read at every capture (None: no ECU, raw mode).
    spec_for : callable, optional
        ``request -> PlantSpec`` (default :func:`default_plant_spec`).
    """
    return with_ecu(flash_file, plant_capture(spec_for))


#: samples of each capture :func:`prepare_plant` records (the plant's programs do not depend on the length)
PREPARE_SAMPLES = 100


def prepare_plant(spec_for: Callable[[CaptureRequest], PlantSpec], options: int, serial: str, seed: int | None = None,
                  rate_hz: float = 10_000.0) -> None:
    """Compile (or load from JAX's cache) the plant's programs for the blocks an end-of-line cycle
    flashes into the ECU of motor ``spec_for(request)`` (a capture of motor ``serial``, draw ``seed``, at
    ``rate_hz`` Hz): the uncompensated block of estimator ``options``, then the
    calibrated layout-2 block (``MECH_COMP_ENABLE`` where the options allow it), as
    :func:`eol_cal.analysis.fit.table.uncompensated_block` and ``block_from_result`` make them.

    A dyno simulator calls it before it serves, so its captures do not compile inside its
    client's capture time-out, which is a real dyno's: the compensated program alone takes 12 CPU s
    cold, more than that time-out of 60 s at load 16 on 2 cores. A calibration the cycle did not
    foresee (a fit that leaves the mechanical part off) still compiles at its first capture.
    """
    request = CaptureRequest(60.0, DutCmdKind.IQ, 0.0, PREPARE_SAMPLES, rate_hz, serial, seed, 0)
    spec = spec_for(request)
    measured = uncompensated_block(spec.serial[:16], spec.motor, calibrated_at=0, options=options)
    flags = measured.flags | FLAG_COMP_ENABLE
    if flags & FLAGS_MECH_NEEDS == FLAGS_MECH_NEEDS:
        flags |= FLAG_MECH_COMP_ENABLE
    calibrated = true_block(spec, flags=flags, mech=True)  # block_from_result's table length: compiled into the scan
    capture = plant_capture(spec_for)
    for block in (measured, calibrated):
        capture(request, ActiveCalibration(mode_of_block(block), block))
