"""A synthetic lot of realistic run records: the real record of an `eol-cal demo` motor
(``fixtures/run_record_demo.json``, through :func:`eol_cal.sim.run_records.make_record`) with its values,
verdict, station, serial and time varied per run. Deterministic (run ``i`` is always the same
record but for its ``run_id``). Used by tests/test_lot_columns.py and bench/bench_records.py.
"""

from __future__ import annotations

import datetime as dt

from eol_cal.records.limits import LIMITS
from eol_cal.records.record import RunRecord
from eol_cal.sim.run_records import make_record

#: the key of k6's upper limit (spelled once, in the limits table)
MAX_K6 = next(lim.key for lim in LIMITS if lim.quantity == "k6" and lim.sense == "max")
T0 = dt.datetime(2026, 11, 2, 6, 0, tzinfo=dt.UTC)
#: what makes a failed run fail (values past the demo variant's limits), by ``i % 4``
_FAILS = ({"pp_after": 2.5}, {"k6": 1.25e-3}, {"r2": 0.25}, {"pp_after": 2.2, "r2": 0.2})
_STEPS = ("acquire", "flash", "fit")
_REFUSALS = ("wrong_serial", "dyno_unreachable", "key_refused")


def _u(i: int, k: int) -> float:
    """A pseudo-random number in [0, 1) of run ``i``, stream ``k`` (Knuth's multiplicative hash)."""
    return ((i * 2654435761 + k * 40503 * 2246822519) % 2**32) / 2**32


def lot_record(i: int, motors: int, stations: int = 6, hi_every: int = 0, refusals: bool = False) -> RunRecord:
    """Run ``i`` of a lot of ``motors`` serials (run i tests motor ``i % motors``: more runs than
    motors are re-tests). Every tenth run starts at the same millisecond as the one before (a
    tie); every 13th has no station id; with ``hi_every`` every such run is variant EPS-HI (its
    own k6 limit). 6 % of the runs fail, 2 % end in an error (no metrics); with ``refusals`` another
    3 % are refusals (wrong serial, dead dyno, wrong key)."""
    seconds = 37 * i - (37 if i % 10 == 9 else 0)
    started = (T0 + dt.timedelta(seconds=seconds)).isoformat(timespec="milliseconds")
    u = _u(i, 0)
    kw: dict = dict(started=started, station=f"EOL-{i % stations}" if i % 13 else None)
    if hi_every and i % hi_every == hi_every - 1:
        kw.update(variant="EPS-HI", limits={MAX_K6: 0.0015})
    serial = f"M{i % motors:06d}"
    if refusals and 0.08 <= u < 0.11:
        return make_record(serial, refused=(_REFUSALS[i % 3],), **kw)
    before, after = 2.8 + 0.5 * _u(i, 7), 0.5 + 0.8 * _u(i, 8)
    kw.update(k6=6.4e-4 + 1.2e-4 * (_u(i, 1) - 0.5), phase_k6=0.2 + 0.1 * _u(i, 2), c6=3.8e-3 + 4e-4 * _u(i, 3),
              phase_c6=-0.3 + 0.05 * _u(i, 4), r2=0.9 + 0.09 * _u(i, 5), rms=3.0e-3 + 1.0e-3 * _u(i, 6),
              pp_before=before, pp_after=after)
    if u < 0.02:
        return make_record(serial, error_step=_STEPS[i % len(_STEPS)], **kw)
    if u < 0.08:
        kw.update(_FAILS[i % 4])
    return make_record(serial, **kw)
