"""A what-if lot: motors drawn from a production spread, each run through the station's cycle on
the simulated plant, recorded as runs of kind ``simulated`` (``eol-cal lot simulate``).

Each motor runs the production steps (:func:`eol_cal.station.cycle.run_motor`: pre-flight,
prepare, acquire, fit, table, flash, acquire compensated, metrics, verdict, report, record)
through the one executor, against simulators reached through the instrument interfaces a line's
station uses (a Modbus dyno, an ECU on a python-can bus): the caller hands in :data:`Simulators`,
``eol-cal lot simulate`` those ``eol-cal run`` meets on loopback
(:func:`eol_cal.sim.loopback.loopback_station`: the dyno simulator whose motor is the drawn one,
the ECU simulator over python-can-remote, both on 127.0.0.1; the library does not import its
simulators). The same steps, the same judging, the same record builder as a motor on a line. The run's files
(captures, blocks, fit, report) and the cycle's own database go to a directory of the batch that
is removed when the batch is done; the records go back to the lot.

Motors run in batches, a batch per task on a Dask cluster (:func:`simulate_lot`). A lot is
named; its motors' serials and run ids follow from the name and the motor's number, so a killed
run continues where it stopped: the batches whose records are all in the database are skipped,
and a record written twice is kept once. Motor ``i`` is drawn from the spread with seed
``seed + i`` and the dyno simulator's noise seeded with it too: the same lot (name, spread,
limits, seed) gives the same records but for their times.
"""

from __future__ import annotations

import tempfile
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol
from collections.abc import Callable, Sequence

from eol_cal.errors import InputError
from eol_cal.station.whatif_plan import LotPlan
from eol_cal.infra.inputs import loads_json

if TYPE_CHECKING:
    from eol_cal.ecu.session import ClientTiming

#: the largest seed a plant motor can be drawn with (``eol-cal simulate``'s): numpy's and JAX's int64, one spare
SEED_MAX = 2**63 - 2
#: the largest seed of a lot's motor: the dyno simulator seeds its captures' noise with
#: ``seed * 1000 + capture`` (:func:`eol_cal.sim.rig.plant_capture`), an int64 too
LOT_SEED_MAX = (2**63 - 1) // 1000 - 1


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
    if not 0 <= plan.seed <= LOT_SEED_MAX - plan.motors:
        raise InputError(None, "--seed", f"{plan.seed}: 0 .. {LOT_SEED_MAX - plan.motors} (motor i is drawn with seed "
                                         "SEED + i, its captures' noise with (SEED + i) * 1000 + capture, and "
                                         "numpy's and JAX's seeds are 0 .. 2**63 - 1)")
    load_spread(plan.spread)
    load_limits(plan.limits_file, plan.variant)
    load_profile(plan.profile)


# ------------------------------------------------------------------------------------------
# one batch: what a task runs


class PlantStation(Protocol):
    """One motor's simulated instruments as the cycle reaches them
    (:class:`eol_cal.sim.loopback.LoopbackStation`): the dyno's Modbus address, the ECU's bus, and
    the tester's settings for simulators in its own process."""

    dyno_address: str
    ecu_timing: ClientTiming
    watchdog_ms: int

    def open_bus(self) -> Any: ...


#: ``(serial, seed, work_dir, spec_for=request -> PlantSpec)``: one motor's simulators, started
#: for the block and stopped after it (:func:`eol_cal.sim.loopback.loopback_station`); sent to the
#: workers by reference, so a module's function
Simulators = Callable[..., AbstractContextManager[PlantStation]]


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


def simulate_motor(plan: LotPlan, i: int, work_dir: Path, simulators: Simulators,
                   cache_dir: Path | None = None) -> Any:
    """Motor ``i`` through the station's cycle (:func:`eol_cal.station.cycle.run_motor`) on its
    ``simulators``, its files under ``work_dir``; its :class:`~eol_cal.records.record.RunRecord`
    (kind ``simulated``, run id :meth:`LotPlan.run_id`). A motor whose cycle erred is recorded so,
    the step named, as on a line."""
    from eol_cal.dyno.client import parse_address
    from eol_cal.dyno.transfer import DynoConfig
    from eol_cal.ecu import protocol as P
    from eol_cal.ecu.client import hmac_seed_to_key
    from eol_cal.domain.bench_mechanics import mechanics_or_rigid
    from eol_cal.plant.presets import preset_spec
    from eol_cal.records.limits import load_limits
    from eol_cal.station.cycle import run_motor
    from eol_cal.station.run import StationConfig

    spec = lot_motor(plan, i)
    with simulators(plan.serial(i), plan.seed + i, work_dir / "sim", spec_for=lambda req: spec) as st:
        host, port = parse_address(st.dyno_address)
        cfg = StationConfig(
            serial=plan.serial(i), dyno=DynoConfig(host=host, port=port, watchdog_ms=st.watchdog_ms),
            open_bus=st.open_bus, ecu_timing=st.ecu_timing, seed_to_key=hmac_seed_to_key(P.DEV_SECRET),
            limits=load_limits(plan.limits_file, plan.variant), db=work_dir / "runs.sqlite",
            report_dir=work_dir / "reports", profile=plan.profile, spool_dir=work_dir / "spool", cache_dir=cache_dir,
            motor=preset_spec(plan.preset).motor, mechanics=mechanics_or_rigid(plan.bench), kind="simulated",
            station=lot_station(plan, i, spec))
        return run_motor(cfg, run_id=plan.run_id(i)).record


def simulate_batch(plan: LotPlan, indices: Sequence[int], simulators: Simulators,
                   cache_dir: str | None = None) -> list[dict[str, Any]]:
    """The run records (JSON) of motors ``indices`` of the lot, one batch, each motor through the
    station's cycle on its ``simulators`` (:func:`simulate_motor`); the runs' files are removed
    afterwards."""
    with tempfile.TemporaryDirectory(prefix=f"lot-{plan.name}-") as d:
        return [simulate_motor(plan, i, Path(d), simulators, None if cache_dir is None else Path(cache_dir)).to_json()
                for i in indices]


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


def simulate_lot(plan: LotPlan, db: str | Path, client: Any, simulators: Simulators,
                 on_done: Callable[[int], None] | None = None, cache_dir: str | Path | None = None,
                 retries: int = 2) -> LotOutcome:
    """Simulate the lot's motors not yet recorded on ``client`` (a ``distributed.Client``), a batch
    per task, each motor through the station's cycle on its ``simulators``, and insert each
    batch's records into ``db`` as it comes back (``on_done(n)``: n more motors recorded). A task
    whose worker died is run again (``retries``); a batch that failed on every try is reported,
    not recorded (a rerun simulates it)."""
    from distributed import as_completed

    from eol_cal.records.record import RunRecord
    from eol_cal.records.write import insert_records

    check_plan(plan)
    done = recorded_runs(db, plan)
    todo = [b for b in plan.batches() if any(plan.run_id(i) not in done for i in b)]
    before = sum(1 for b in plan.batches() for i in b if plan.run_id(i) in done)
    keys = [f"lot-simulate-{plan.name}-{b[0]}" for b in todo]
    mapped = client.map(simulate_batch, [plan] * len(todo), todo, [simulators] * len(todo), key=keys,
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
