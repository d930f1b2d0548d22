"""A what-if lot: motors drawn from a production spread, each run through the station's calibration
in simulation, recorded as runs of kind ``simulated`` (``eol-cal lot simulate``).

Per motor, as the station cycle (:mod:`eol_cal.station.cycle`) does it on a line: the uncompensated
block with the variant's estimator options (prepare), the calibration capture over the test
profile, the fit (:func:`eol_cal.station.run.fit_motor`) judged by the fit stage's limits, the
calibrated block (:func:`eol_cal.analysis.fit.table.block_from_result`), the capture with the
compensation at the fit's operating point, the ripple before and after
(:func:`eol_cal.analysis.point_metrics.point_ripple`) judged by the ripple's limits, and the run
record (:class:`~eol_cal.records.record.RunRecord`). The plant replaces the dyno and the ECU (the
ECU's estimator and compensator are the firmware reference's, run by the plant); no capture or
block file is written.

Motors run in batches (one batched plant call per capture, :func:`simulate_batch`), a batch per
task on a Dask cluster (:func:`simulate_lot`). A lot is named; its motors' serials and run ids
follow from the name and the motor's number, so a killed run continues where it stopped: the
batches whose records are all in the database are skipped, and a record written twice is kept
once. Motor ``i`` is drawn from the spread with seed ``seed + i`` and its noise seeded by its
batch: the same lot (name, spread, limits, seed, batch size) gives the same records.
"""

from __future__ import annotations

import functools
import hashlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager


from eol_cal.errors import InputError
from eol_cal.station.whatif_plan import LotPlan, SimMotor
from eol_cal.infra.inputs import loads_json

if TYPE_CHECKING:
    from eol_cal.capture.data import Capture
    from eol_cal.records.record import RunRecord
    from eol_cal.station.executor import Observer
    from eol_cal.station.instruments import Instruments

#: the largest seed a motor (and its batch's noise, seed + 1) can be drawn with: numpy's and JAX's int64
SEED_MAX = 2**63 - 2


def check_plan(plan: LotPlan) -> None:
    """Refuse a plan that cannot run, before anything is simulated (names the option)."""
    from eol_cal.plant.profile import load_profile
    from eol_cal.plant.spread import load_spread
    from eol_cal.records.limits import load_limits

    if not plan.name or any(c in plan.name for c in "/\\\x00") or len(plan.name) > 10:
        raise InputError(None, "--lot", f"{plan.name!r}: 1 to 10 characters, no slashes (the serials are NAME-000001 "
                                        "and a block holds 16)")
    if plan.motors < 1 or plan.motors > 999_999:
        raise InputError(None, "--motors", f"{plan.motors}: 1 .. 999999")
    if plan.batch < 1:
        raise InputError(None, "--batch", f"{plan.batch}: at least 1")
    if not 0 <= plan.seed <= SEED_MAX - plan.motors:
        raise InputError(None, "--seed", f"{plan.seed}: 0 .. {SEED_MAX - plan.motors} (motor i is drawn with seed "
                                         f"SEED + i, and numpy's and JAX's seeds are 0 .. 2**63 - 1)")
    load_spread(plan.spread)
    load_limits(plan.limits_file, plan.variant)
    load_profile(plan.profile)


# ------------------------------------------------------------------------------------------
# one motor through the production cycle, on instruments handed in


#: ``(serial, seed, work_dir, spec_for, *, seed_to_key, timing, motor)`` -> a context manager of
#: one motor's :class:`~eol_cal.station.instruments.Instruments` (the plant in-process:
#: :func:`eol_cal.sim.plant_instruments.plant_instruments`); handed in, so the library below the
#: simulators does not import them
InstrumentsFor = Callable[..., AbstractContextManager["Instruments"]]


def lot_motor(plan: LotPlan, i: int) -> Any:
    """Motor ``i`` of the lot: the spread's draw with seed ``plan.seed + i`` around the preset
    (a :class:`~eol_cal.plant.params.PlantSpec`; its serial the lot's)."""
    from eol_cal.plant.presets import preset_spec
    from eol_cal.plant.spread import load_spread

    return load_spread(plan.spread).draw(plan.seed + i, preset_spec(plan.preset), serial=plan.serial(i))


def lot_station(plan: LotPlan, i: int, spec: Any) -> dict[str, Any]:
    """The record's station of motor ``i``: the lot's (``sim:NAME``), what makes the lot (a rerun
    must match, :func:`recorded_runs`) and the drawn motor's truth."""
    truth = {k: float(getattr(spec, k)) for k in ("k6", "phase_k6", "c6", "phase_c6", "unb1")}
    return {"id": plan.station, "simulated": {**plan.fingerprint(), "motor": i, "spread_seed": plan.seed + i},
            "truth": truth}


def simulate_motor(plan: LotPlan, i: int, work_dir: Path, instruments: InstrumentsFor,
                   cache_dir: Path | None = None, observers: Sequence[Observer] = ()) -> RunRecord:
    """Motor ``i`` through the station's cycle (:func:`eol_cal.station.cycle.run_motor`, every
    production step through the one executor) on its ``instruments``, its files under
    ``work_dir``: its record (kind ``simulated``, run id :meth:`LotPlan.run_id`). A motor whose
    cycle erred is recorded so, the step named, as on a line. ``observers`` get each step's
    start and end (:class:`~eol_cal.station.executor.StepEvent`)."""
    from eol_cal.domain.bench_mechanics import mechanics_or_rigid
    from eol_cal.dyno.transfer import DynoConfig
    from eol_cal.ecu import protocol as P
    from eol_cal.ecu.client import ClientTiming, hmac_seed_to_key
    from eol_cal.plant.presets import preset_spec
    from eol_cal.records.limits import load_limits
    from eol_cal.station.cycle import run_motor
    from eol_cal.station.run import StationConfig

    spec = lot_motor(plan, i)
    motor, key, timing = preset_spec(plan.preset).motor, hmac_seed_to_key(P.DEV_SECRET), ClientTiming()
    cfg = StationConfig(
        serial=plan.serial(i), dyno=DynoConfig(), open_bus=_no_bus, seed_to_key=key, ecu_timing=timing,
        limits=load_limits(plan.limits_file, plan.variant), db=work_dir / "runs.sqlite",
        report_dir=work_dir / "reports", profile=plan.profile, spool_dir=work_dir / "spool", cache_dir=cache_dir,
        motor=motor, mechanics=mechanics_or_rigid(plan.bench), kind="simulated", station=lot_station(plan, i, spec))
    with instruments(plan.serial(i), plan.seed + i, work_dir / "sim", lambda req: spec, seed_to_key=key,
                     timing=timing, motor=motor) as inst:
        return run_motor(cfg, observers=observers, instruments=inst, run_id=plan.run_id(i)).record


def _no_bus() -> Any:
    raise RuntimeError("a what-if motor reaches its ECU through its instruments only")


# ------------------------------------------------------------------------------------------
# one batch: what a task runs


def _windows(capture: Capture, profile: Any, f_tick: float) -> list[Capture]:
    """The steady part of each profile segment (after its ramp) as a capture of its own: what the
    station's dyno delivers (one window per segment)."""
    from eol_cal.capture.data import Capture as Cap

    out = []
    for k, ((a, b), seg) in enumerate(zip(profile.segment_bounds(f_tick), profile.segments, strict=True), start=1):
        a = min(b - 1, a + int(round(seg.ramp_s * f_tick)))
        out.append(Cap(capture.t[a:b], {n: v[a:b] for n, v in capture.channels.items()}, dict(capture.metadata),
                       dict(capture.truth), {}, source=f"{capture.source}#{k}"))
    return out


def _flashed(blk: Any, role: str) -> Any:
    """The record of a block the simulated ECU ran (nothing archived: no file)."""
    from eol_cal.firmware import block as B
    from eol_cal.station.archive import block_fields
    from eol_cal.records.record import FlashedBlock

    image = B.pack(blk)
    return FlashedBlock(role=role, path=None, sha256=hashlib.sha256(image).hexdigest(), bytes=len(image), bank=None,
                        sequence=blk.sequence, crc32=f"{B.check(image).crc_stored or 0:08x}", verified=True,
                        confirmed=True, **block_fields(image))


def simulate_batch(plan: LotPlan, indices: Sequence[int], cache_dir: str | None = None) -> list[dict[str, Any]]:
    """The run records (JSON) of motors ``indices`` of the lot, one batch; never raises for a motor
    (a motor whose step fails is recorded with verdict ``error``, the step named)."""
    from eol_cal import __version__
    from eol_cal.analysis.fit.table import block_from_result, uncompensated_block
    from eol_cal.domain.bench_mechanics import mechanics_or_rigid
    from eol_cal.plant.presets import preset_spec
    from eol_cal.plant.profile import constant, load_profile
    from eol_cal.plant.simulate import simulate
    from eol_cal.plant.spread import load_spread
    from eol_cal.station.context import now_iso
    from eol_cal.records.limits import Measured, failed, judge, load_limits
    from eol_cal.station.outcome import simulated_record
    from eol_cal.station.run import fit_motor

    spread, lim = load_spread(plan.spread), load_limits(plan.limits_file, plan.variant)
    profile, base = load_profile(plan.profile), preset_spec(plan.preset)
    motor, mechanics = base.motor, mechanics_or_rigid(plan.bench)
    options = lim.estimator_options
    motors = [SimMotor(i, spread.draw(plan.seed + i, base, serial=plan.serial(i)), now_iso()) for i in indices]
    noise_seed = plan.seed + indices[0]
    cache = None if cache_dir is None else Path(cache_dir)

    def step(m: SimMotor, name: str, fn: Callable[[], Any]) -> Any:
        from eol_cal.records.record import Step

        t0 = time.perf_counter()
        try:
            out = fn()
        except (InputError, ValueError, FloatingPointError) as exc:
            m.steps.append(Step(name, round(time.perf_counter() - t0, 4), False, f"{type(exc).__name__}: {exc}"))
            m.failed_step, m.error = name, exc
            return None
        m.steps.append(Step(name, round(time.perf_counter() - t0, 4), True))
        return out

    # prepare ECU + acquire: the calibration capture of the whole batch under the uncompensated blocks
    prepared = [uncompensated_block(m.spec.serial, motor, calibrated_at=0, options=options) for m in motors]
    for m, b in zip(motors, prepared, strict=True):
        m.blocks.append(_flashed(b, "prepare"))
    t0 = time.perf_counter()
    runs = simulate([m.spec for m in motors], profile, mode="estimated", blocks=prepared, seed=noise_seed)
    share = round((time.perf_counter() - t0) / len(motors), 4)
    from eol_cal.records.record import Step

    for m, run in zip(motors, runs, strict=True):
        m.steps += [Step("prepare ECU", 0.0, True), Step("acquire", share, True)]
        m.before = _windows(run.capture, profile, motor.f_pwm)
        # fit (its limits), table
        fitted = step(m, "fit", functools.partial(fit_motor, m.before, lim, __version__, motor, mechanics, cache, options))
        if fitted is None:
            continue
        _fitted, m.result, extra = fitted
        if not m.result.usable:
            m.verdict, m.reasons = "fail", [f"fit {m.result.status}: {r}" for r in m.result.reasons] or [
                f"fit {m.result.status}"]
            continue
        m.measured = Measured.of_fit(m.result)
        m.judged["fit"] = judge(m.measured, lim, "fit")
        if failed(m.judged["fit"]):
            m.verdict, m.reasons = "fail", failed(m.judged["fit"])
            continue
        m.before = extra[0]  # the fit's windows and angles, for the ripple before
        m.calibrated = step(m, "table", functools.partial(block_from_result, m.result, motor, calibrated_at=0,
                                                                  source=f"<{m.spec.serial}>", options=options))
        if m.calibrated is not None:
            m.blocks.append(_flashed(m.calibrated, "calibrated"))
            m.steps.append(Step("flash", 0.0, True))

    # acquire compensated: each operating point's motors in one batch
    todo = [m for m in motors if m.calibrated is not None]
    by_point: dict[tuple[float, float], list[SimMotor]] = {}
    for m in todo:
        op = m.result.operating_point
        by_point.setdefault((round(float(op.speed_rpm), 6), round(float(op.i_qo_a), 6)), []).append(m)
    for (rpm, iq), group in by_point.items():
        seconds = _point_seconds(profile, rpm, iq)
        t0 = time.perf_counter()
        after = simulate([m.spec for m in group], constant(rpm, seconds, iq=iq), mode="compensated",
                         blocks=[m.calibrated for m in group], seed=noise_seed + 1)
        share = round((time.perf_counter() - t0) / len(group), 4)
        for m, run in zip(group, after, strict=True):
            m.steps.append(Step("acquire compensated", share, True))
            step(m, "metrics", functools.partial(_judge_ripple, m, run.capture, lim))
    return [simulated_record(plan, m, lim).to_json() for m in motors]


def _point_seconds(profile: Any, rpm: float, iq: float) -> float:
    """How long the station's compensated capture at the operating point lasts: its segment's
    steady part (the profile's longest otherwise)."""
    # as verify_segments matches them (by magnitude, within 2 %); a segment given as torque by speed only
    steady = [s.seconds - s.ramp_s for s in profile.segments
              if abs(abs(s.speed_rpm) - abs(rpm)) <= 0.02 * max(abs(rpm), 1e-9)
              and (s.iq is None or abs(abs(s.iq) - abs(iq)) <= 0.02 * max(abs(iq), 1e-9))]
    return max(steady) if steady else max(s.seconds - s.ramp_s for s in profile.segments)


def _judge_ripple(m: SimMotor, after: Capture, lim: Any) -> None:
    from eol_cal.analysis.angle import capture_angle
    from eol_cal.analysis.point_metrics import nearest_segment, point_ripple
    from eol_cal.records.limits import failed
    from eol_cal.station.steps.measure_ripple import judge_ripple

    op = m.result.operating_point
    k = nearest_segment(m.before.captures, op.speed_rpm, op.i_qo_a)
    before = point_ripple(m.before.captures[k], m.before.angles[k])
    after_pr = point_ripple(after, capture_angle(after))
    m.metrics, m.measured, m.judged["ripple"] = judge_ripple(m.result, before, after_pr, m.measured, lim)
    reasons = failed(m.judged["ripple"])
    m.verdict, m.reasons = ("fail", reasons) if reasons else ("pass", [])


# ------------------------------------------------------------------------------------------
# the lot: batches on a cluster, records into the database


@dataclass
class LotOutcome:
    """What :func:`simulate_lot` did: motors recorded before and now, batches that failed."""

    motors: int
    recorded_before: int
    recorded_now: int
    failed_batches: list[tuple[list[int], str]]


def recorded_runs(db: str | Path, plan: LotPlan) -> set[str]:
    """The run ids of the lot's motors the database holds already; refuses a lot of the same name
    made otherwise (another spread, limits, seed, profile or batch size)."""
    from eol_cal.records.connect import is_url
    from eol_cal.records.tables import runs
    from eol_cal.records.query import read_rows, select_runs

    if not is_url(db) and not Path(db).exists():
        return set()
    q = select_runs(station=plan.station, kind="simulated").with_only_columns(runs.c.run_id, runs.c.record_json)
    rows = read_rows(db, q)
    want = plan.fingerprint()
    for row in rows[:1]:
        # a record's station keeps what the station recorded beside its own keys (StationInfo.extra)
        doc = loads_json(str(row["record_json"]), str(db), f"run {row.get('run_id')} record_json")
        got = ((doc.get("station") if isinstance(doc, dict) else None) or {}).get("simulated") or {}
        made = {k: got.get(k) for k in want}
        if made != want:
            diff = ", ".join(f"{k} {made[k]!r} (now {want[k]!r})" for k in want if made[k] != want[k])
            raise InputError(str(db), "--lot", f"lot {plan.name!r} in the database was made with {diff}: give another "
                                               "--lot name, or the same settings to continue it")
    return {row["run_id"] for row in rows}


def simulate_lot(plan: LotPlan, db: str | Path, client: Any, on_done: Callable[[int], None] | None = None,
                 cache_dir: str | Path | None = None, retries: int = 2) -> LotOutcome:
    """Simulate the lot's motors not yet recorded on ``client`` (a ``distributed.Client``), a batch
    per task, and insert each batch's records into ``db`` as it comes back (``on_done(n)``: n more
    motors recorded). A task whose worker died is run again (``retries``); a batch that failed on
    every try is reported, not recorded (a rerun simulates it)."""
    from distributed import as_completed

    from eol_cal.records.record import RunRecord
    from eol_cal.records.write import insert_records

    check_plan(plan)
    done = recorded_runs(db, plan)
    todo = [b for b in plan.batches() if any(plan.run_id(i) not in done for i in b)]
    before = sum(1 for b in plan.batches() for i in b if plan.run_id(i) in done)
    keys = [f"lot-simulate-{plan.name}-{b[0]}" for b in todo]
    mapped = client.map(simulate_batch, [plan] * len(todo), todo, key=keys, retries=retries, pure=False,
                        cache_dir=None if cache_dir is None else str(cache_dir))
    futures = dict(zip(mapped, todo, strict=True))
    now, failed_batches = 0, []
    for fut in as_completed(futures):
        batch = futures[fut]
        try:
            docs = fut.result()
        except Exception as exc:  # noqa: BLE001 - a batch that failed on every retry: reported, not recorded
            failed_batches.append((batch, f"{type(exc).__name__}: {exc}"))
            continue
        records = [RunRecord.from_json(d, f"lot {plan.name}") for d in docs]
        added = insert_records(db, [r for r in records if r.run_id not in done])
        done.update(r.run_id for r in records)
        now += added
        if on_done is not None:
            on_done(added)
    return LotOutcome(plan.motors, before, now, failed_batches)
