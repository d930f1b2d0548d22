"""A what-if lot: motors drawn from a production spread, each run through the station's cycle on the
plant, recorded as runs of kind ``simulated`` (``eol-cal lot simulate``).

Each motor runs the production steps (:func:`eol_cal.station.cycle.run_motor`: every step module of
:mod:`eol_cal.station.steps` through the one executor, the one record builder) on instruments
handed in (:data:`InstrumentsFor`; the command and the benchmark hand in the plant in-process,
:func:`eol_cal.sim.plant_instruments.plant_instruments`: the ECU simulator on a virtual CAN channel,
the dyno's captures through its register map, no sockets): what ``eol-cal run`` records on the
loopback simulators, but for its kind, run id, station and times (tests/test_whatif_same_record.py).

Motors run in batches, a batch per task on a Dask cluster (:func:`simulate_lot`), a task's motors
in threads, :data:`MOTOR_THREADS` at a time (:func:`simulate_batch`). A lot is named; its motors'
serials and run ids follow from the name and the motor's number, so a killed run continues where
it stopped: the batches whose records are all in the database are skipped, and a record written
twice is kept once. Motor ``i`` is drawn from the spread with seed ``seed + i``, and the dyno's
noise seeded with it: the same lot (name, spread, limits, seed) gives the same records, whatever
the batch size.
"""

from __future__ import annotations

import sys
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager


from eol_cal.errors import InputError
from eol_cal.station.whatif_plan import LotPlan
from eol_cal.infra.inputs import loads_json

if TYPE_CHECKING:
    from eol_cal.records.record import RunRecord
    from eol_cal.station.executor import Observer
    from eol_cal.station.instruments import Instruments

#: the largest seed a motor can be drawn with: its dyno's captures are seeded ``seed * 1000 +
#: capture`` (:func:`eol_cal.sim.rig.plant_capture`), within numpy's and JAX's int64
SEED_MAX = (2**63 - 1) // 1000 - 1


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
        motor=motor, mechanics=mechanics_or_rigid(plan.bench), kind="simulated", station=lot_station(plan, i, spec),
        report_plots=False)  # the batch removes its runs' directories: plots nobody sees were half a motor's CPU
    with instruments(plan.serial(i), plan.seed + i, work_dir / "sim", lambda req: spec, seed_to_key=key,
                     timing=timing, motor=motor) as inst:
        return run_motor(cfg, observers=observers, instruments=inst, run_id=plan.run_id(i)).record


def _no_bus() -> Any:
    raise RuntimeError("a what-if motor reaches its ECU through its instruments only")


# ------------------------------------------------------------------------------------------
# one batch: what a task runs


#: motors of a batch whose cycles run at once, each in a thread. 32 motors
#: (bench/bench_lot_simulate.py, 2 workers, load 22): 1 thread 62 s wall / 44.3 CPU s, 2: 53.5 /
#: 47.2, 3: 56.4 / 50.9, the whole batch of 8 (load 16-21): 80 / 95 (the cycles' Python contends for
#: the interpreter's lock, switched every 0.5 ms by the executor); 2 with the process's first motor
#: alone (load 17-20): 66 / 48.0. A warm motor (load 21): 0.85 CPU s alone, 0.91 two at a time, its
#: wall 2.20 -> 1.44 s. A batched plant call for the motors' captures is not made: XLA's float32
#: results depend on the call's width and a motor's place in it (1 ulp, grown to 0.1 % in some
#: motors' currents), so a motor's record would depend on its batch. One: a lot's workers already
#: take the cores (a Dask worker per core), and one at a time costs the least CPU (no worse than the
#: batched steps it replaced: 44.3 against 42.9 CPU s for the 32 motors); raise it for a lot on a
#: machine with idle cores and few workers
MOTOR_THREADS = 1
#: set once this process's first what-if motor ended: that motor runs alone, as it traces and
#: compiles the JAX programs every motor calls (two threads at it would each trace them)
_TRACED = threading.Event()


def simulate_batch(plan: LotPlan, indices: Sequence[int], instruments: InstrumentsFor,
                   cache_dir: str | None = None) -> list[dict[str, Any]]:
    """The run records (JSON) of motors ``indices`` of the lot, one batch, each motor through the
    station's cycle on its ``instruments`` (:func:`simulate_motor`), :data:`MOTOR_THREADS` motors
    at a time (the process's first alone, :data:`_TRACED`); the runs' files (captures, blocks,
    reports) are removed afterwards.

    The threads overlap one motor's waits (its ECU's answers, the flash) and its work outside
    the interpreter's lock (the plant's and the fit's XLA programs) with another's Python; each
    motor's plant runs alone, so its record is the one it gets in any batch
    (tests/test_whatif_batch.py). A motor's exception fails the batch once every motor has ended
    (as :func:`simulate_lot` reports it)."""
    cache = None if cache_dir is None else Path(cache_dir)
    switch = sys.getswitchinterval()  # each cycle's executor sets and restores it: concurrently, out of order
    try:
        with (tempfile.TemporaryDirectory(prefix=f"lot-{plan.name}-") as d,
              ThreadPoolExecutor(max_workers=MOTOR_THREADS, thread_name_prefix="lot-motor") as pool):
            def run(i: int) -> RunRecord:
                return simulate_motor(plan, i, Path(d) / str(i), instruments, cache)

            jobs = [pool.submit(run, i) for i in indices[:1]]
            if jobs and not _TRACED.is_set():
                wait(jobs)
                _TRACED.set()
            jobs += [pool.submit(run, i) for i in indices[1:]]
            return [job.result().to_json() for job in jobs]
    finally:
        sys.setswitchinterval(switch)


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


def simulate_lot(plan: LotPlan, db: str | Path, client: Any, instruments: InstrumentsFor,
                 on_done: Callable[[int], None] | None = None, cache_dir: str | Path | None = None,
                 retries: int = 2) -> LotOutcome:
    """Simulate the lot's motors not yet recorded on ``client`` (a ``distributed.Client``), a batch
    per task, each motor through the station's cycle on its ``instruments`` (a module's function:
    sent to the workers by reference), and insert each batch's records into ``db`` as it comes back (``on_done(n)``: n more
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
    mapped = client.map(simulate_batch, [plan] * len(todo), todo, [instruments] * len(todo), key=keys,
                        retries=retries, pure=False, cache_dir=None if cache_dir is None else str(cache_dir))
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
