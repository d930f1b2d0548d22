"""Refit a lot's captures on a Dask ``distributed`` cluster: a few motor runs per task (a motor run
is a station run's directory, or a directory of one motor's captures; :data:`REFIT_BATCH`),
results keyed by serial and comparable with the run records.

Each motor's captures are read and fitted as the station does (the options of
:func:`eol_cal.station.run.fit_motor`, so the same k6 as the record of that run), and, with limits, judges the fit's
part of them (:func:`eol_cal.records.limits.judge` of the fit stage: k6, the intervals, R^2, RMS, the
hall table; the ripple limits need the compensated capture, which a refit does not make). A capture
that cannot be read or fitted gives a row with ``error`` and no numbers; the lot goes on. So does
a capture that ``eol-cal fit`` would refuse by its recorded ECU state (the block changed during
it, another motor's ECU, taken under compensation); untraced captures (older runs) are refitted,
and the firmware frame is measured under the estimator options the captures' ECU ran (else the
variant's).
Tasks are pure (files in, rows out), so ``distributed`` may rerun one whose worker died.
"""

from __future__ import annotations

import glob
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple
from collections.abc import Callable, Iterable, Iterator, Sequence

from eol_cal.errors import EolCalError, InputError

if TYPE_CHECKING:
    from eol_cal.analysis.motor_result import MotorResult

CAPTURE_SUFFIXES = (".mf4", ".csv")
#: the file a station run writes before compensation (eol_cal.station.cycle); a directory of runs
#: is refitted from these
STATION_CAPTURE = "before.mf4"
_ERRORS = (EolCalError, OSError, ValueError)
ROW_KEYS = ("serial", "capture", "k6", "phase_k6", "c6", "r2", "rms", "status", "verdict", "reasons", "failed_checks",
            "error")


def find_captures(patterns: Sequence[str], kind: str | Sequence[str] | None = "production") -> list[list[Path]]:
    """The capture files of directories (their station ``before.mf4`` files, recursively, else
    every capture in them), files and globs, grouped by directory: one group per motor run
    (a station run directory, or a directory holding one motor's captures); sorted, each once.

    A station run directory whose record (``report.json``) is of another kind than ``kind``
    (default ``production``; ``all`` or None: every kind) is left out: a master motor's or a
    simulated run is not a motor of the lot unless asked for."""
    from eol_cal.records.query import kinds_of

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
    from eol_cal.infra.inputs import load_json
    from eol_cal.records.record import record_kind

    try:  # the bounded loader: a FIFO or a record nested 100 000 deep is no readable record
        return record_kind(load_json(run_dir / "report.json", max_bytes=64 << 20))
    except (InputError, ValueError):
        return None


#: serials per refit task (:func:`refit_serials`): the firmware estimator runs over all their
#: captures side by side in one batched scan (48 captures cost ~3x what 6 cost, not 8x), and
#: the per-task costs are shared; small enough that two workers finish a lot together
REFIT_BATCH = 8


def refit_capture(paths: Sequence[str | Path], limits_file: str | None = None, variant: str | None = None,
                  bench: str = "paper", motor: str = "paper", cache_dir: str | Path | None = None) -> dict[str, Any]:
    """One motor's row (:data:`ROW_KEYS`) from its captures; never raises for a bad capture
    (``error`` says why). :func:`refit_serials` of one motor."""
    return refit_serials([paths], limits_file, variant, bench, motor, cache_dir)[0]


def refit_serials(groups: Sequence[Sequence[str | Path]], limits_file: str | None = None, variant: str | None = None,
                  bench: str = "paper", motor: str = "paper",
                  cache_dir: str | Path | None = None) -> list[dict[str, Any]]:
    """Rows (:data:`ROW_KEYS`) of many motors, one per group of captures (one motor run each), in
    the order of ``groups``; never raises for a bad capture (that motor's ``error`` says why, the
    others go on).

    The fit is the station's (:func:`eol_cal.station.run.fit_motor`'s options: joint windows,
    firmware frame), with the dyno ``bench`` (a name or TOML file; ``"none"``: rigid coupling)
    and ``motor`` preset the runs were made with (the record's ``station.bench``, ``station.motor``).
    ``k6``, ``c6`` in N*m/A and N*m, ``phase_k6`` in rad,
    ``rms`` in N*m, as in the records; ``capture`` names the first file. ``cache_dir``: the fit's
    serialized solvers (:mod:`eol_cal.analysis.fit.cache`; ``None``: none).

    Each motor is read, segmented and fitted on its own, as ``eol-cal fit`` fits it; only the
    firmware estimator that places the frame runs over every motor's captures at once
    (:func:`eol_cal.analysis.fit.capture.measure_firmware_frames`, the same figures as one motor
    at a time). The windows' p-p figures, which a row does not report, are not computed.
    """
    try:
        setup = _RefitSetup(limits_file, variant, bench, motor, cache_dir)
    except _ERRORS as exc:
        return [_failed(paths, exc) for paths in groups]
    return _finish(setup, _start(setup, groups))


class _Batch(NamedTuple):
    """A batch of motors between its reading and its fits: the rows, the motors ready for their
    fit (row, inputs, options) and their firmware frames' estimator runs, started (None: to be
    measured motor by motor)."""

    rows: list[dict[str, Any]]
    ready: list[tuple[dict[str, Any], Any, Any]]
    frames: Any


def _start(setup: _RefitSetup, groups: Sequence[Sequence[str | Path]]) -> _Batch:
    """Read and segment each motor of a batch, and start the estimator runs of their firmware frames."""
    from eol_cal.analysis.fit.capture import start_firmware_frames

    rows = [_blank(paths) for paths in groups]
    ready = []
    for row, paths in zip(rows, groups, strict=True):
        try:
            ready.append((row, *setup.inputs(paths, row)))
        except _ERRORS as exc:
            _error(row, exc)
    try:
        frames = start_firmware_frames([mi for _, mi, _ in ready], [o.estimator_options for _, _, o in ready])
    except _ERRORS:
        frames = None
    return _Batch(rows, ready, frames)


def _finish(setup: _RefitSetup, batch: _Batch) -> list[dict[str, Any]]:
    """A started batch's frames (its estimator runs' results), fingerprints and fits: its rows."""
    ready = list(batch.ready)
    _frames(ready, batch.frames)
    for row, mi, opts in ready:
        try:
            (result,) = setup.fit(mi, opts)
            setup.judge(row, result)
        except _ERRORS as exc:
            _error(row, exc)
    return batch.rows


def refit_batches(batches: Iterable[Sequence[Sequence[str | Path]]], limits_file: str | None = None,
                  variant: str | None = None, bench: str = "paper", motor: str = "paper",
                  cache_dir: str | Path | None = None) -> Iterator[list[dict[str, Any]]]:
    """:func:`refit_serials` of each batch, in order, one process, one thread: each batch is read,
    segmented and its estimator runs started before the batch ahead of it is fitted, so that JAX
    computes those runs on its own thread meanwhile. The same rows as :func:`refit_serials` of each
    batch (test); a batch that raises gives each of its groups a row with ``error``."""
    try:
        setup = _RefitSetup(limits_file, variant, bench, motor, cache_dir)
    except _ERRORS as exc:
        for groups in batches:
            yield [_failed(paths, exc) for paths in groups]
        return
    ahead: tuple[Sequence[Sequence[str | Path]], _Batch | BaseException] | None = None
    for groups in batches:
        try:
            started: _Batch | BaseException = _start(setup, groups)
        except Exception as exc:  # noqa: BLE001 - a batch that failed: reported per group, the lot goes on
            started = exc
        if ahead is not None:
            yield _finished(setup, *ahead)
        ahead = (groups, started)
    if ahead is not None:
        yield _finished(setup, *ahead)


def _finished(setup: _RefitSetup, groups: Sequence[Sequence[str | Path]], started: _Batch | BaseException
              ) -> list[dict[str, Any]]:
    if isinstance(started, BaseException):
        return [_failed(group, started) for group in groups]
    try:
        return _finish(setup, started)
    except Exception as exc:  # noqa: BLE001 - a batch that failed: reported per group, the lot goes on
        return [_failed(group, exc) for group in groups]


def _blank(group: Sequence[str | Path]) -> dict[str, Any]:
    """A group's row before its refit: every key None, ``capture`` its first file."""
    row: dict[str, Any] = dict.fromkeys(ROW_KEYS)
    row.update(capture=str(group[0]), reasons=[], failed_checks=[])
    return row


def _error(row: dict[str, Any], exc: BaseException) -> dict[str, Any]:
    row["error"] = f"{type(exc).__name__}: {exc}"
    row["verdict"] = "error"
    return row


def _frames(ready: list[tuple[dict[str, Any], Any, Any]], started: Any = None) -> None:
    """The firmware frames of every motor ready for its fit, in one batch (``started``: its
    estimator runs, :func:`~eol_cal.analysis.fit.capture.start_firmware_frames`); a batch that fails
    is measured motor by motor, so only the motor at fault gets the error (and leaves ``ready``)."""
    from eol_cal.analysis.fit.capture import measure_firmware_frames

    try:
        measure_firmware_frames([mi for _, mi, _ in ready], [o.estimator_options for _, _, o in ready], started)
        return
    except _ERRORS:
        pass
    for item in list(ready):
        row, mi, opts = item
        try:
            measure_firmware_frames([mi], [opts.estimator_options])
        except _ERRORS as exc:
            _error(row, exc)
            ready.remove(item)


class _RefitSetup:
    """What every motor of a refit shares: limits, bench, motor preset, the fit's options."""

    def __init__(self, limits_file: str | None, variant: str | None, bench: str, motor: str,
                 cache_dir: str | Path | None) -> None:
        from eol_cal.domain.bench_mechanics import mechanics_or_rigid
        from eol_cal.domain.motor_params import load_motor
        from eol_cal.records.limits import load_limits

        self.lim = load_limits(limits_file, variant) if limits_file else None
        # no mechanical result (fit_mech: the fingerprint's margin and the block's orders, ~40 % of a
        # refit's CPU): a row and its verdict read only the fit stage, and a refit writes no block
        self.common: dict[str, Any] = dict(batch="loop", capture_metrics=False, mech=False,
                                           mechanics=mechanics_or_rigid(bench),
                                           motor=load_motor(motor),
                                           cache_dir=None if cache_dir is None else Path(cache_dir))

    def inputs(self, paths: Sequence[str | Path], row: dict[str, Any]) -> tuple[Any, Any]:
        """One motor's fit inputs (offline frame) and fit options; sets ``row["serial"]``."""
        from eol_cal.analysis.fit.capture import segment_motors
        from eol_cal.analysis.fit.motors import FitOptions
        from eol_cal.capture.ecu_state import check_trace, common_options, recorded_options, trace_of
        from eol_cal.capture.io import read_capture

        caps = [read_capture(p) for p in paths]
        row["serial"] = caps[0].serial
        # what fit refuses, a refit refuses (per serial): a block changed during the capture, another
        # motor's ECU, a capture under compensation; untraced captures (older runs) are refitted
        traces = [trace_of(c.metadata, str(p)) for p, c in zip(paths, caps, strict=True)]
        for p, c, t in zip(paths, caps, traces, strict=True):
            check_trace(t, str(p), allow_untraced=True, serial=c.metadata.get("serial"))
        ran = common_options(recorded_options([str(p) for p in paths], traces))
        common = dict(self.common)
        # the estimator the runs measured under: the one their ECU state records, else the variant's
        # (default best, as the station's)
        if ran is not None:
            common["estimator_options"] = ran
        elif self.lim is not None:
            common["estimator_options"] = self.lim.estimator_options
        opts = FitOptions(**common) if self.lim is None else FitOptions(limits=self.lim.ci_limits(), **common)
        inputs = segment_motors(caps, opts.motor, settle_s=opts.settle_s, min_revs=opts.min_revs,
                                hall_angle=opts.hall_angle, mechanics=opts.mechanics)
        if len(inputs) != 1:
            raise InputError(str(paths[0]), "serial", f"the directory holds {len(inputs)} motors, expected one")
        return inputs[0], opts

    def fit(self, mi: Any, opts: Any) -> list[MotorResult]:
        from eol_cal import __version__
        from eol_cal.analysis.fit.motors import fit_inputs

        return fit_inputs([mi], opts, __version__).results

    def judge(self, row: dict[str, Any], result: MotorResult) -> None:
        """Fill ``row`` from a motor's fit result (judged against the fit stage's limits); raises
        before touching the row when it cannot be judged."""
        from eol_cal.records.limits import Measured, failed, judge

        checks = judge(Measured.of_fit(result), self.lim, "fit") if result.usable and self.lim is not None else None
        row["status"] = str(result.status)
        for key in ("k6", "phase_k6", "c6"):
            row[key] = None if result.estimates is None else getattr(result.estimates, key).value
        row["r2"], row["rms"] = result.fit.get("r2"), result.fit.get("rms")
        if not result.usable:
            row["verdict"], row["reasons"] = "fail", list(result.reasons)
            row["failed_checks"] = [f"fit {result.status}"]
        elif checks is not None:
            reasons = failed(checks)
            row["verdict"], row["reasons"] = ("fail", reasons) if reasons else ("pass", [])
            row["failed_checks"] = [c.key for c in checks if c.passed is False]


#: threads of :func:`refit_in_process`: one. Two threads on two cores were no faster than one
#: (0.91-0.95x its serials a second, quiet; 0.95-0.96x in refit6's runs) for 1.35-1.4x its CPU: the threads overlap
#: only where the GIL is released (numpy's kernels, BLAS, JAX's programs), and each release with the
#: other thread waiting hands the GIL over (6x the voluntary context switches, twice the system
#: time), which costs more than the overlap gains (docs/benchmarks.md, "Lot refit throughput").
#: :func:`refit_lot`'s worker processes share nothing and scale (~1.9x on two cores)
REFIT_THREADS = 1


def refit_in_process(groups: Sequence[Sequence[str | Path]], limits_file: str | None = None,
                     variant: str | None = None, bench: str = "paper", motor: str = "paper",
                     cache_dir: str | Path | None = None, threads: int = REFIT_THREADS, batch: int = REFIT_BATCH,
                     on_done: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """:func:`refit_serials` of every group in this process, ``batch`` groups a task on ``threads``
    threads (no cluster; default :data:`REFIT_THREADS`, one: more are no faster; one thread runs
    the batches through :func:`refit_batches`, each batch's estimator computed by JAX's thread
    while the batch ahead is fitted); rows in the order of ``groups``, the same rows as one batch
    after the other (the arguments as :func:`refit_serials`'; ``on_done`` is called in this thread,
    in order).

    A task is pure (files in, rows out: each thread's batch has its own captures, inputs, fits and
    compression scope, a context variable); what the threads share is the process's caches of
    compiled programs, filled once (two threads that miss one at once each build it, the same
    program). A task that raises gives each of its groups a row with ``error``, as on a cluster
    (:func:`refit_lot`); a bad capture spoils only its own row (:func:`refit_serials`)."""
    from concurrent.futures import ThreadPoolExecutor

    starts = range(0, len(groups), max(1, batch))
    rows: list[dict[str, Any]] = []

    def take(done: list[dict[str, Any]]) -> None:
        for row in done:
            rows.append(row)
            if on_done is not None:
                on_done(row)

    if threads <= 1:
        for done in refit_batches((groups[k:k + batch] for k in starts), limits_file, variant, bench, motor, cache_dir):
            take(done)
        return rows
    with ThreadPoolExecutor(threads, thread_name_prefix="refit") as pool:
        futures = [pool.submit(refit_serials, groups[k:k + batch], limits_file, variant, bench, motor, cache_dir)
                   for k in starts]
        for k, fut in zip(starts, futures, strict=True):
            try:
                done = fut.result()
            except Exception as exc:  # noqa: BLE001 - a task that failed: reported per group, the lot goes on
                done = [_failed(group, exc) for group in groups[k:k + batch]]
            take(done)
    return rows


def _failed(group: Sequence[str | Path], exc: BaseException) -> dict[str, Any]:
    """The row of a group whose task (or whose refit's setup) failed as a whole."""
    return _error(_blank(group), exc)


def refit_lot(paths: Sequence[Sequence[Path]], client: Any, limits_file: str | None = None, variant: str | None = None,
              on_done: Callable[[dict[str, Any]], None] | None = None, retries: int = 2,
              bench: str = "paper", motor: str = "paper", cache_dir: str | Path | None = None,
              batch: int = REFIT_BATCH) -> list[dict[str, Any]]:
    """Refit every group of captures (one motor run, :func:`find_captures`) on ``client`` (a
    ``distributed.Client``), ``batch`` groups per task (:func:`refit_serials`); rows in the order
    of ``paths``. ``retries``: how often a task whose worker died is run again.
    ``cache_dir``: the fit's serialized solvers, a directory on the workers' machines (``None``: none)."""
    from distributed import as_completed

    # one graph update for the whole lot (a submit per task is a scheduler round trip each); the
    # arguments are file names and a few strings: nothing of size goes over the wire either way
    starts = range(0, len(paths), max(1, batch))
    chunks = [[[str(q) for q in group] for group in paths[k:k + batch]] for k in starts]
    keys = [f"refit-{k}-{paths[k][0].parent.name}" for k in starts]
    mapped = client.map(refit_serials, chunks, key=keys, retries=retries, pure=False, limits_file=limits_file,
                        variant=variant, bench=bench, motor=motor, cache_dir=None if cache_dir is None else str(cache_dir))
    futures = {fut: k for fut, k in zip(mapped, starts, strict=True)}
    rows: list[dict[str, Any] | None] = [None] * len(paths)
    for fut in as_completed(futures):
        k = futures[fut]
        try:
            done = fut.result()
        except Exception as exc:  # noqa: BLE001 - a task that failed on every retry: reported per capture
            done = [_failed(group, exc) for group in paths[k:k + batch]]
        for j, row in enumerate(done):
            rows[k + j] = row
            if on_done is not None:
                on_done(row)
    return [r for r in rows if r is not None]


def write_rows(path: str | Path, rows: Iterable[dict[str, Any]]) -> Path:
    """Write rows as JSON Lines (``.jsonl``) or Parquet (``.parquet``), atomically."""
    import json

    from eol_cal.infra.atomic import atomic_write

    path = Path(path)
    rows = list(rows)
    if path.suffix == ".jsonl":
        atomic_write(path, "".join(json.dumps(_json_safe(r), allow_nan=False) + "\n" for r in rows))
    elif path.suffix == ".parquet":
        import io

        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pylist([{**r, "reasons": list(r["reasons"] or [])} for r in rows])
        buf = io.BytesIO()
        pq.write_table(table, buf)
        atomic_write(path, buf.getvalue())
    else:
        raise InputError(str(path), None, "results file must end in .jsonl or .parquet")
    return path


def read_rows(path: str | Path) -> list[dict[str, Any]]:
    """Rows written by :func:`write_rows`."""
    from eol_cal.infra.inputs import check_regular, loads_json, read_text

    path = Path(path)
    file = str(path)
    if path.suffix == ".parquet":
        import pyarrow.parquet as pq

        check_regular(path)
        try:
            rows = pq.read_table(path).to_pylist()
        except (OSError, ValueError) as exc:
            raise InputError(file, None, f"cannot read the refit results: {exc}") from None
    else:
        lines = read_text(path).splitlines()
        rows = [loads_json(line, file, f"line {k}") for k, line in enumerate(lines, start=1) if line.strip()]
    for k, row in enumerate(rows, start=1):
        if not isinstance(row, dict) or not isinstance(row.get("serial"), (str, type(None))):
            raise InputError(file, f"row {k}", "not a refit result row (an object with a serial, null for a "
                                               "capture that could not be read)")
    return rows


def _json_safe(r: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()}
