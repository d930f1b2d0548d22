"""``eol-cal fit``: per-motor ripple fit from captures, JSON result, optional plots."""

from __future__ import annotations

import contextlib
import gc
import math
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import click

from cli.common import (CommandExit, console, err_console, estimator_bits, estimator_option, loop_kernels,
                        handle_errors, styled)
from cli.paths import io_paths
from eol_cal.analysis.intervals import CiLimits

#: the fit's own interval limits, the options' defaults
_CI = CiLimits()

if TYPE_CHECKING:
    from eol_cal.analysis.motor_result import ValueCi


def enable_jax_cache() -> Path | None:
    """JAX's persistent compilation cache, so a second ``eol-cal fit`` skips compiling.

    Directory: :func:`eol_cal.analysis.fit.cache.default_cache_dir` (``$EOL_CAL_JAX_CACHE`` or
    ``~/.cache/eol-cal/jax``; ``off``: no cache). Returns it (``None``: no cache) for the fit's
    serialized solvers, which live there too.
    """
    from eol_cal.analysis.fit.cache import default_cache_dir, enable_compile_cache

    return enable_compile_cache(default_cache_dir())


@contextlib.contextmanager
def loading_uncollected() -> Iterator[None]:
    """Python's cyclic garbage collector off while the fit's libraries load, then what they made
    frozen out of its later passes (``gc.freeze``).

    JAX, the fit's modules and their imports make ~200 000 objects, none of them garbage; the
    collections their allocation triggers cost ~0.15 CPU s of a one-capture ``eol-cal fit``
    (0.85 -> 0.70 s for the imports, measured at load ~20)."""
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if collecting:
            gc.enable()


def _harmonics(text: str) -> tuple[int, ...]:
    try:
        orders = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise click.BadParameter(f"{text!r}: comma-separated orders, e.g. 6,12,18") from None
    return orders


def frame_estimator(choice: str | None, paths: list[str], traces: list) -> tuple[int, list[str]]:
    """The estimator options the fit measures the firmware frame with, and warnings.

    The options the captures' ECU ran (:func:`eol_cal.capture.ecu_state.common_options`) unless
    ``choice`` (``--estimator``) says otherwise, which is then warned about per capture that
    recorded others; ``best`` when no capture recorded a block.
    """
    from eol_cal.capture.ecu_state import common_options, recorded_options
    from eol_cal.errors import InputError
    from eol_cal.firmware.options import options_label

    recorded = recorded_options(paths, traces)
    if choice is not None:
        bits = estimator_bits(choice)
        return bits, [f"{path}: the ECU ran estimator {options_label(r)}, the frame is measured with "
                      f"{options_label(bits)} (--estimator)" for path, r in recorded.items() if r != bits]
    try:
        ran = common_options(recorded)
    except InputError as exc:
        raise InputError(exc.file, exc.field, f"{exc.reason}; fit them apart or choose one with --estimator") from None
    return (estimator_bits("best") if ran is None else ran), []


@click.command("fit")
@click.argument("captures", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="Result JSON to write.")
@click.option("--map", "map_file", type=click.Path(dir_okay=False), help="Channel map (TOML) for foreign files.")
@click.option("--plot", "plot_dir", type=click.Path(file_okay=False), help="Write per-motor PNGs here.")
@click.option("--harmonics", default="6,12,18", show_default=True, help="Orders to fit: 6, optionally 12 and 18.")
@click.option("--no-c6", is_flag=True, help="Do not fit the load-independent (cogging) part.")
@click.option("--no-k6", is_flag=True, help="Do not fit the load-proportional part.")
@click.option("--delay", "delay_s", type=float, help="Known transducer delay / time constant (s) instead of fitting it.")
@click.option("--transducer", type=click.Choice(["delay", "lowpass"]), default="lowpass", show_default=True,
              help="Torque transducer model: pure delay, or first-order low-pass (gain and phase).")
@click.option("--bench", "bench_name", default="paper", show_default=True, metavar="NAME|FILE.toml",
              help="Dyno bench of the captures (eol_cal/benches/NAME.toml or a TOML file): its shaft and "
                   "current-loop response is divided out of the measured ripple; 'none': rigid coupling.")
@click.option("--frame", type=click.Choice(["firmware", "offline"]), default="firmware", show_default=True,
              help="Angle frame of the phases: the firmware estimator's (run over the capture), or the offline hall frame.")
@click.option("--hall-angle", "hall_angle", type=click.Choice(["measured", "nominal"]), default="measured", show_default=True,
              help="Hall table for the block (and the frame of the phases): measured from the motor's own hall "
                   "transitions, or the contract's nominal one.")
@click.option("--drift-degree", default=2, show_default=True, type=click.IntRange(0, 5),
              help="Per-segment drift polynomial degree.")
@click.option("--settle", "settle_s", default=0.1, show_default=True, type=click.FloatRange(0.0),
              help="Settling time dropped after each step (s).")
@click.option("--max-ci-k6", default=_CI.k6_rel, show_default=True, type=click.FloatRange(0.0),
              help="Widest 95 % interval of k6, fraction of k6.")
@click.option("--max-ci-phase", default=_CI.phase_k6_deg, show_default=True, type=click.FloatRange(0.0),
              help="Widest 95 % interval of phase_k6 (deg).")
@click.option("--max-ci-c6", default=_CI.c6_nm, show_default=True, type=click.FloatRange(0.0),
              help="Widest 95 % cogging phasor error (N*m).")
@click.option("--min-model-p", default=_CI.model_p, show_default=True, type=click.FloatRange(0.0, 1.0),
              help="Least p-value of the model check (k6 and c6 per speed band agree); below: status model_mismatch.")
@click.option("--max-steps", default=64, show_default=True, type=click.IntRange(1), help="Solver step limit.")
@click.option("--solver", type=click.Choice(["gn", "lm"]), default="gn", show_default=True,
              help="Gauss-Newton or Levenberg-Marquardt.")
@click.option("--batch", type=click.Choice(["auto", "loop", "vmap", "map"]), default="auto", show_default=True,
              help="How many motors are solved in JAX (auto: vmap from 16 motors on, else loop).")
@click.option("--allow-untraced", is_flag=True,
              help="Fit captures with no record of the ECU state (a foreign DAQ's): a warning instead of a refusal.")
@click.option("--allow-compensated", is_flag=True,
              help="Fit captures taken under compensation (COMP_ENABLE): a warning instead of a refusal.")
@estimator_option("those the ECU ran during the captures: the firmware frame is measured with that estimator "
                  "[default: the options the captures' ECU state records; best for captures without one].", default=None)
@click.option("--json", "as_json", is_flag=True, help="Also print the result JSON on stdout.")
@handle_errors
@io_paths(inputs=("captures", "map_file", "bench_name"), outputs=("output",), output_dirs=("plot_dir",))
def fit_cmd(captures, output, map_file, plot_dir, harmonics, no_c6, no_k6, delay_s, transducer, bench_name, frame,
            hall_angle, drift_degree, settle_s, max_ci_k6, max_ci_phase, max_ci_c6, min_model_p, max_steps, solver, batch,
            allow_untraced, allow_compensated, estimator, as_json):
    """Fit each motor's 6th-harmonic ripple (k6, c6, phases, delay) from its captures.

    Captures are grouped by their ``serial``; all captures of one motor fit jointly. Exit 0 when
    every fit is usable, 1 when a fit did not converge or its interval is too wide, 2 on bad input.

    A capture must say what the ECU ran (metadata ecu_before/ecu_after, docs/capture-format.md):
    refused when the ECU's block changed during it; refused unless allowed when it has no such
    record (--allow-untraced) or was taken under compensation (--allow-compensated).
    """

    loop_kernels()  # before the process's first JAX computation
    with loading_uncollected():
        from rich.progress import Progress
        from rich.table import Table

        from eol_cal.analysis.fit import FitSpec
        from eol_cal.analysis.fit.motors import FitOptions, fit_motors
        from eol_cal.analysis.result import STATUS_OK, write_result
        from eol_cal.domain.bench_mechanics import mechanics_or_rigid
        from eol_cal.capture.ecu_state import check_trace, trace_of
        from eol_cal.capture.io import read_capture
        from eol_cal.records.limits import Measured, bench_assumed, check, limit_on

        cache_dir = enable_jax_cache()
    spec = FitSpec(
        harmonics=_harmonics(harmonics),
        fit_c=not no_c6,
        fit_k=not no_k6,
        drift_degree=drift_degree,
        delay_s=delay_s,
        transducer=transducer,
        max_steps=max_steps,
        solver=solver,
    )
    limits = CiLimits(k6_rel=max_ci_k6, phase_k6_deg=max_ci_phase, c6_nm=max_ci_c6, model_p=min_model_p)
    mechanics = mechanics_or_rigid(bench_name)
    caps = [read_capture(p, map_file) for p in captures]
    traces = [trace_of(cap.metadata, path) for path, cap in zip(captures, caps, strict=True)]
    for path, trace, cap in zip(captures, traces, caps, strict=True):  # every refusal before any fit starts
        for warning in check_trace(trace, path, allow_untraced=allow_untraced, allow_compensated=allow_compensated,
                                   serial=cap.metadata.get("serial")):
            click.echo(f"warning: {warning}", err=True)
    bits, warnings = frame_estimator(estimator, captures, traces)
    for warning in warnings:
        click.echo(f"warning: {warning}", err=True)
    options = FitOptions(spec=spec, limits=limits, settle_s=settle_s, frame=frame, batch=batch, mechanics=mechanics,
                         hall_angle=hall_angle, cache_dir=cache_dir, estimator_options=bits)
    serials = {c.serial for c in caps if "serial" in c.metadata}
    with Progress(console=err_console, transient=True, disable=len(serials) < 2) as progress:
        task = progress.add_task("fitting", total=len(serials))
        res = fit_motors(caps, options, progress=lambda n: progress.update(task, completed=n))
    results = res.results
    if plot_dir:
        from eol_cal.analysis.fit.plot import plot_fit, plot_residual_spectrum

        Path(plot_dir).mkdir(parents=True, exist_ok=True)
        for mi, f in zip(res.inputs, res.fits, strict=True):
            safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in mi.serial)
            plot_fit(Path(plot_dir) / f"{safe}_fit.png", mi, f, spec)
            plot_residual_spectrum(Path(plot_dir) / f"{safe}_residual.png", mi, f, spec)
    doc = res.to_json()
    write_result(doc, output)

    table = Table(title=f"ripple fit, values ± 95 % ({len(results)} motor{'s' if len(results) != 1 else ''})")
    for col in ("serial", "status", "k6 mN*m/A", "φk6 deg", "c6 mN*m", "φc6 deg", "τ µs", "rms mN*m", "R²", "steps"):
        table.add_column(col, justify="right" if col not in ("serial", "status") else "left", no_wrap=col == "serial")
    for r in results:
        e = r.estimates
        table.add_row(
            r.serial, r.status if r.status == STATUS_OK else styled((r.status, "red")),
            *(_pm(None if e is None else getattr(e, key), scale, deg) for key, scale, deg in _ESTIMATE_COLUMNS),
            f"{r.fit['rms'] * 1e3:.3g}", f"{r.fit['r2']:.3f}", str(r.fit["steps"]),
        )
    (err_console if as_json else console).print(table)
    for r in results:
        for source, why in r.left_out or ():
            err_console.print(f"{r.serial}: capture {source} left out of the fit: {why}")
        for reason in r.reasons:
            err_console.print(f"{r.serial}: {reason}")
        if r.solver_result not in (None, "successful"):  # optimistix's name for how it ended
            err_console.print(f"{r.serial}: the solver ended with {r.solver_result}")
        if r.status == STATUS_OK and bench_assumed(r.model_check):
            # what the station's default limits fail the motor with, in the same words
            row = limit_on("bench_assumed")
            assert row is not None and isinstance(row.default, float)
            err_console.print(f"{r.serial}: warning: {check(row, row.default, Measured.of_fit(r)).reason}")
        if "unchecked" in r.model:
            err_console.print(f"{r.serial}: {r.model['unchecked']}")
    if as_json:
        import json

        click.echo(json.dumps(doc, indent=2, allow_nan=False))
    if any(r.status != STATUS_OK for r in results):
        raise CommandExit(1)


#: the table's estimate columns: the estimate, the factor to the unit shown, a phase shown in deg
_ESTIMATE_COLUMNS = (("k6", 1e3, False), ("phase_k6", 1.0, True), ("c6", 1e3, False), ("phase_c6", 1.0, True),
                     ("delay_s", 1e6, False))


def _pm(e: ValueCi | None, scale: float, deg: bool = False) -> str:
    """An estimate and its 95 % interval as the table shows them (``-``: none)."""
    if e is None or e.value is None:
        return "-"

    def f(v: float) -> float:
        return math.degrees(v) if deg else v * scale

    if e.ci95 is None:
        return f"{f(e.value):.4g}"
    ci = float(f"{f(e.ci95):.2g}")  # two significant digits, written out ("100", not "1e+02")
    return f"{f(e.value):.4g}±{ci:g}"


COMMANDS = [fit_cmd]
