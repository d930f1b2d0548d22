"""A synthetic lot of realistic run records: the real record of an `eol-cal demo` motor
(``fixtures/run_record_demo.json``, 9 kB as stored) with its values, verdict, station, serial
and time varied per run. Deterministic (run ``i`` is always the same record but for its
``run_id``). Used by tests/test_lot_columns.py and bench/bench_records.py.
"""

from __future__ import annotations

import datetime as dt
import json
import uuid
from pathlib import Path
from typing import Any

TEMPLATE: dict[str, Any] = json.loads(
    (Path(__file__).resolve().parent.parent / "fixtures" / "run_record_demo.json").read_text())
T0 = dt.datetime(2026, 11, 2, 6, 0, tzinfo=dt.timezone.utc)
_FAIL_REASONS = ("p-p after = 2.5 % exceeds max_pp_after_pct = 2",
                 "k6 = 0.00125 N*m/A exceeds max_k6 = 0.0012",
                 "fit R^2 = 0.25 below min_r2 = 0.3",
                 "hall table not measured: too few transitions")
_STEPS = ("acquire", "flash", "fit")


def _u(i: int, k: int) -> float:
    """A pseudo-random number in [0, 1) of run ``i``, stream ``k`` (Knuth's multiplicative hash)."""
    return ((i * 2654435761 + k * 40503 * 2246822519) % 2**32) / 2**32


def lot_record(i: int, motors: int, stations: int = 6, hi_every: int = 0) -> dict[str, Any]:
    """Run ``i`` of a lot of ``motors`` serials (run i tests motor ``i % motors``: more runs than
    motors are re-tests). Every tenth run starts at the same millisecond as the one before (a
    tie); every 13th has no station id; with ``hi_every`` every such run is variant EPS-HI (its
    own max_k6). 6 % of the runs fail, 2 % end in an error (no fit, no metrics)."""
    seconds = 37 * i - (37 if i % 10 == 9 else 0)
    started = (T0 + dt.timedelta(seconds=seconds)).isoformat(timespec="milliseconds")
    r = dict(TEMPLATE)
    r.update(run_id=uuid.uuid4().hex, serial=f"M{i % motors:06d}", started_at=started, ended_at=started,
             verdict="pass", reasons=[], error=None)
    u = _u(i, 0)
    station = {k: v for k, v in TEMPLATE["station"].items()}
    if i % 13:
        station["id"] = f"EOL-{i % stations}"
    r["station"] = station
    if hi_every and i % hi_every == hi_every - 1:
        r["limits"] = {**TEMPLATE["limits"], "variant": "EPS-HI", "max_k6": 0.0015}
    if u < 0.02:
        step = _STEPS[i % len(_STEPS)]
        r.update(verdict="error", reasons=[f"{step}: simulated fault"], fit=None, metrics={},
                 error={"step": step, "type": "DynoError", "message": "simulated fault", "traceback": None})
        return r
    if u < 0.08:
        r.update(verdict="fail", reasons=list(_FAIL_REASONS[i % 4: i % 4 + 1 + i % 2]))
    fit = TEMPLATE["fit"]
    r["fit"] = {**fit, "k6": {**fit["k6"], "value": 6.4e-4 + 1.2e-4 * (_u(i, 1) - 0.5)},
                "phase_k6": {**fit["phase_k6"], "value": 0.2 + 0.1 * _u(i, 2)},
                "c6": {**fit["c6"], "value": 3.8e-2 + 4e-3 * _u(i, 3)},
                "phase_c6": {**fit["phase_c6"], "value": -0.3 + 0.05 * _u(i, 4)},
                "fit": {**fit["fit"], "r2": 0.9 + 0.09 * _u(i, 5), "rms": 3.0e-3 + 1.0e-3 * _u(i, 6)}}
    before, after = 2.8 + 0.5 * _u(i, 7), 0.5 + 0.8 * _u(i, 8)
    r["metrics"] = {**TEMPLATE["metrics"], "pp_before_pct": before, "pp_after_pct": after,
                    "improvement_pct": 100.0 * (before - after) / before}
    return r
