"""``eol-cal bench identify``: the bench's torque path from a master motor's sweep (commissioning)."""

from __future__ import annotations

import click

from cli.common import console, err_console, handle_errors
from cli.paths import io_paths


@click.group("bench")
def bench_group() -> None:
    """The test bench: its torque path identified at commissioning (docs/bench-identify.md)."""


@bench_group.command("identify")
@click.argument("captures", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Bench file (TOML) to write: what `eol-cal fit --bench` and the station's `bench` setting read.")
@click.option("--plot", "plot_file", type=click.Path(dir_okay=False),
              help="PNG of the measured gain and phase against the model.")
@click.option("--map", "map_file", type=click.Path(dir_okay=False), help="Channel map (TOML) for foreign files.")
@click.option("--motor", "motor_file", type=click.Path(dir_okay=False),
              help="Motor TOML overriding the paper preset: the master motor's rotor inertia J and friction B.")
@click.option("--base", "base_bench", default="paper", show_default=True, metavar="NAME|FILE.toml",
              help="Bench the values the sweep cannot resolve are held at (the dyno's speed loop; J_dyno unless "
                   "resolved).")
@click.option("--name", default=None, help="The identified bench's name [default: the output file's stem].")
@click.option("--settle", "settle_s", type=float, default=0.2, show_default=True,
              help="Settling time dropped after each speed step (s).")
@handle_errors
@io_paths(inputs=("captures", "map_file", "motor_file", "base_bench"), outputs=("output", "plot_file"))
def identify_cmd(captures, output, plot_file, map_file, motor_file, base_bench, name, settle_s):
    """Identify the bench's torque path from the master motor's sweep captures (profile bench-sweep).

    The 6th, 12th and 18th harmonics of the motor's ripple move through frequency with the speed:
    their phasors at the transducer, against the air-gap torque (the motor's own ripple plus kt
    times the measured q current's), give the shaft's torsion mode (K_shaft, shaft_zeta, J_dyno
    where resolved) and the transducer's bandwidth and delay, each with a 95 % interval. Exit 0
    with the bench file written, 2 when the sweep cannot identify the path (the reason names the
    file and the field).
    """
    from pathlib import Path

    from eol_cal.analysis.bench_id.identify import identify_bench
    from eol_cal.analysis.bench_id.output import plot_bench, write_bench
    from eol_cal.analysis.bench_id.sweep import sweep_points
    from eol_cal.capture.io import read_capture
    from eol_cal.domain.bench_mechanics import load_mechanics
    from eol_cal.domain.motor_params import load_motor

    params = load_motor("paper", motor_file)
    base = load_mechanics(base_bench)
    caps = [read_capture(p, map_file) for p in captures]
    points = sweep_points(caps, params, settle_s=settle_s)
    res = identify_bench(points, params, base, name=name or Path(output).stem)
    write_bench(res, output)
    if plot_file:
        plot_bench(res, plot_file)
    console.print(f"bench identified from master motor {points.serial}: {len(points.M)} points at "
                  f"{len(set(abs(round(s)) for s in points.speed_rpm))} speeds, "
                  f"{points.freq_hz.min():.0f} .. {points.freq_hz.max():.0f} Hz, Birge ratio {res.birge:.2f}")
    for key, e in res.estimates.items():
        ci = "" if e.ci95 is None else f" ± {e.ci95:.3g}"
        note = f"  ({e.status}{': ' + e.note if e.note else ''})" if e.status != "identified" else ""
        console.print(f"  {key:<20} {e.value:.6g}{ci} {e.unit}{note}")
    for line in res.dropped:
        console.print(f"  dropped: {line}")
    left_out = {f"left out: {line}" for line in points.skipped}
    for line in res.notes:
        if line not in left_out:
            console.print(f"  note: {line}")
    for line in points.skipped:
        err_console.print(f"warning: left out {line}")
    console.print(f"written: {output}" + (f", {plot_file}" if plot_file else ""))


COMMANDS = [bench_group]
