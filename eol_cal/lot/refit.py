"""Refit a lot's captures on a Dask ``distributed`` cluster: one task per motor run (a station
run's directory, or a directory of one motor's captures), results keyed by serial and
comparable with the run records.

Each task reads the run's captures and fits them as the station does (the options of
:func:`eol_cal.station.run.fit_motor`, so the same k6 as the record of that run), and, with limits, judges the fit's
part of them (:func:`eol_cal.station.limits.judge` of the fit stage: k6, the intervals, R^2, RMS, the
hall table; the ripple limits need the compensated capture, which a refit does not make). A capture
that cannot be read or fitted gives a row with ``error`` and no numbers; the lot goes on. So does
a capture that ``eol-cal fit`` would refuse by its recorded ECU state (the block changed during
it, another motor's ECU, taken under compensation); untraced captures (older runs) are refitted,
and the firmware frame is measured under the estimator options the captures' ECU ran (else the
variant's).
Tasks are pure (a file in, a row out), so ``distributed`` may rerun one whose worker died.
"""

from __future__ import annotations

import glob
import math
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from eol_cal.errors import InputError

CAPTURE_SUFFIXES = (".mf4", ".csv")
#: the file a station run writes before compensation (eol_cal.station.cycle); a directory of runs
#: is refitted from these
STATION_CAPTURE = "before.mf4"
ROW_KEYS = ("serial", "capture", "k6", "phase_k6", "c6", "r2", "rms", "status", "verdict", "reasons", "failed_checks",
            "error")


def find_captures(patterns: Sequence[str], kind: str | Sequence[str] | None = "production") -> list[list[Path]]:
    """The capture files of directories (their station ``before.mf4`` files, recursively, else
    every capture in them), files and globs, grouped by directory: one group per motor run
    (a station run directory, or a directory holding one motor's captures); sorted, each once.

    A station run directory whose record (``report.json``) is of another kind than ``kind``
    (default ``production``; ``all`` or None: every kind) is left out: a master motor's or a
    simulated run is not a motor of the lot unless asked for."""
    from eol_cal.station.records_query import kinds_of

    kinds = kinds_of(kind)
    out: set[Path] = set()
    for pat in patterns:
        p = Path(pat)
        if p.is_dir():
            found = [q for q in p.rglob(STATION_CAPTURE) if kinds is None or _run_kind(q.parent) in (*kinds, None)]
            found = found or [q for q in p.rglob("*") if q.suffix.lower() in CAPTURE_SUFFIXES
                              and q.name != STATION_CAPTURE]
        elif p.is_file():
            found = [p]
        else:
            found = [Path(q) for q in glob.glob(pat, recursive=True) if Path(q).suffix.lower() in CAPTURE_SUFFIXES]
        if not found:
            raise InputError(pat, None, "no capture files (.mf4, .csv) found")
        out.update(q.resolve() for q in found)
    groups: dict[Path, list[Path]] = {}
    for q in sorted(out):
        groups.setdefault(q.parent, []).append(q)
    return [groups[k] for k in sorted(groups)]


def _run_kind(run_dir: Path) -> str | None:
    """The kind of a station run directory's record (None: no readable record there)."""
    import json

    from eol_cal.station.record import record_kind

    try:
        return record_kind(json.loads((run_dir / "report.json").read_text(encoding="utf-8")))
    except (OSError, ValueError):
        return None


def refit_capture(paths: Sequence[str | Path], limits_file: str | None = None, variant: str | None = None,
                  bench: str = "paper", motor: str = "paper", cache_dir: str | Path | None = None) -> dict[str, Any]:
    """One motor's row (:data:`ROW_KEYS`) from its captures; never raises for a bad capture
    (``error`` says why).

    The fit is the station's (:func:`eol_cal.station.run.fit_motor`'s options: joint windows,
    firmware frame), with the dyno ``bench`` (a name or TOML file; ``"none"``: rigid coupling)
    and ``motor`` preset the runs were made with (the record's ``station.bench``, ``station.motor``). ``k6``, ``c6`` in N*m/A and N*m, ``phase_k6`` in rad,
    ``rms`` in N*m, as in the records; ``capture`` names the first file. ``cache_dir``: the fit's
    serialized solvers (:mod:`eol_cal.analysis.fit.cache`; ``None``: none).
    """
    from eol_cal import __version__
    from eol_cal.analysis.fit.motors import FitOptions, fit_motors
    from eol_cal.capture.ecu_state import check_trace, common_options, recorded_options, trace_of
    from eol_cal.capture.io import read_capture
    from eol_cal.errors import EolCalError
    from eol_cal.station.limits import Measured, failed, judge, load_limits

    row: dict[str, Any] = dict.fromkeys(ROW_KEYS)
    row.update(capture=str(paths[0]), reasons=[], failed_checks=[])
    try:
        lim = load_limits(limits_file, variant) if limits_file else None
        caps = [read_capture(p) for p in paths]
        row["serial"] = caps[0].serial
        # what fit refuses, a refit refuses (per serial): a block changed during the capture, another
        # motor's ECU, a capture under compensation; untraced captures (older runs) are refitted
        traces = [trace_of(c.metadata, str(p)) for p, c in zip(paths, caps)]
        for p, c, t in zip(paths, caps, traces):
            check_trace(t, str(p), allow_untraced=True, serial=c.metadata.get("serial"))
        ran = common_options(recorded_options([str(p) for p in paths], traces))
        from eol_cal.mechanics import mechanics_or_rigid
        from eol_cal.motor import load_motor

        common = dict(batch="loop", mechanics=mechanics_or_rigid(bench), motor=load_motor(motor),
                      cache_dir=None if cache_dir is None else Path(cache_dir))
        # the estimator the runs measured under: the one their ECU state records, else the variant's
        # (default best, as the station's)
        if ran is not None:
            common["estimator_options"] = ran
        elif lim is not None:
            common["estimator_options"] = lim.estimator_options
        opts = FitOptions(**common) if lim is None else FitOptions(limits=lim.ci_limits(), **common)
        res = fit_motors(caps, opts, __version__)
        if len(res.records) != 1:
            raise InputError(str(paths[0]), "serial", f"the directory holds {len(res.records)} motors, expected one")
        (rec,) = res.records
        from eol_cal.analysis.motor_result import MotorResult

        result = MotorResult.from_json(rec, str(paths[0]), "motors[0].")
    except (EolCalError, OSError, ValueError) as exc:
        row["error"] = f"{type(exc).__name__}: {exc}"
        row["verdict"] = "error"
        return row
    row["status"] = result.status
    for key in ("k6", "phase_k6", "c6"):
        row[key] = None if result.estimates is None else getattr(result.estimates, key).value
    row["r2"], row["rms"] = result.fit.get("r2"), result.fit.get("rms")
    if not result.usable:
        row["verdict"], row["reasons"] = "fail", list(result.reasons)
        row["failed_checks"] = [f"fit {result.status}"]
    elif lim is not None:
        checks = judge(Measured.of_fit(result), lim, "fit")
        reasons = failed(checks)
        row["verdict"], row["reasons"] = ("fail", reasons) if reasons else ("pass", [])
        row["failed_checks"] = [c.key for c in checks if c.passed is False]
    return row


def refit_lot(paths: Sequence[Sequence[Path]], client: Any, limits_file: str | None = None, variant: str | None = None,
              on_done: Callable[[dict[str, Any]], None] | None = None, retries: int = 2,
              bench: str = "paper", motor: str = "paper", cache_dir: str | Path | None = None) -> list[dict[str, Any]]:
    """Refit every group of captures (one motor run, :func:`find_captures`) as one task on
    ``client`` (a ``distributed.Client``); rows in the order of ``paths``. ``retries``: how often a task whose worker died is run again.
    ``cache_dir``: the fit's serialized solvers, a directory on the workers' machines (``None``: none)."""
    from distributed import as_completed

    # one graph update for the whole lot (a submit per task is a scheduler round trip each); the
    # arguments are file names and a few strings: nothing of size goes over the wire either way
    keys = [f"refit-{i}-{group[0].parent.name}" for i, group in enumerate(paths)]
    mapped = client.map(refit_capture, [[str(q) for q in group] for group in paths], key=keys, retries=retries,
                        pure=False, limits_file=limits_file, variant=variant, bench=bench, motor=motor,
                        cache_dir=None if cache_dir is None else str(cache_dir))
    futures = {fut: i for i, fut in enumerate(mapped)}
    rows: list[dict[str, Any] | None] = [None] * len(paths)
    for fut in as_completed(futures):
        i = futures[fut]
        try:
            rows[i] = fut.result()
        except Exception as exc:  # noqa: BLE001 - a task that failed on every retry: reported per capture
            row = dict.fromkeys(ROW_KEYS)
            row.update(capture=str(paths[i][0]), reasons=[], failed_checks=[], verdict="error",
                       error=f"{type(exc).__name__}: {exc}")
            rows[i] = row
        if on_done is not None:
            on_done(rows[i])
    return [r for r in rows if r is not None]


def write_rows(path: str | Path, rows: Iterable[dict[str, Any]]) -> Path:
    """Write rows as JSON Lines (``.jsonl``) or Parquet (``.parquet``), atomically."""
    import json

    from eol_cal.atomic import atomic_write

    path = Path(path)
    rows = list(rows)
    if path.suffix == ".jsonl":
        atomic_write(path, "".join(json.dumps(_json_safe(r), allow_nan=False) + "\n" for r in rows))
    elif path.suffix == ".parquet":
        import io

        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pylist([{**r, "reasons": list(r["reasons"] or []),
                                        "failed_checks": list(r.get("failed_checks") or [])} for r in rows])
        buf = io.BytesIO()
        pq.write_table(table, buf)
        atomic_write(path, buf.getvalue())
    else:
        raise InputError(str(path), None, "results file must end in .jsonl or .parquet")
    return path


def read_rows(path: str | Path) -> list[dict[str, Any]]:
    """Rows written by :func:`write_rows`."""
    import json

    path = Path(path)
    try:
        if path.suffix == ".parquet":
            import pyarrow.parquet as pq

            return pq.read_table(path).to_pylist()
        return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]
    except (OSError, ValueError) as exc:
        raise InputError(str(path), None, f"cannot read the refit results: {exc}") from None


def _json_safe(r: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()}
