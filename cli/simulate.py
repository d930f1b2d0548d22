"""``eol-cal simulate``: captures from the built-in plant (the paper's bench in JAX)."""

from __future__ import annotations

from pathlib import Path

import click

from cli.common import console, handle_errors, print_json
from cli.paths import io_paths
from eol_cal.errors import InputError, naming

_SUFFIXES = (".csv", ".mf4")


def _read_block(path: str):
    from eol_cal.firmware import block as B

    data = B.read_block_file(path)
    res = B.check(data)
    if not res.valid:
        raise InputError(path, "block", "invalid parameter block: " + "; ".join(res.reasons))
    return B.unpack(data, path)


def _profile(profile: str | None, speed_rpm: float | None, torque_nm: float | None, iq: float | None,
             seconds: float | None):
    from eol_cal.plant import profile as prof

    if torque_nm is not None and iq is not None:
        raise InputError(None, "--torque-nm/--iq", "give one of them, not both")
    constant = speed_rpm is not None or torque_nm is not None or iq is not None or seconds is not None
    if constant and profile is not None:
        raise InputError(None, "--profile", "give a profile or --speed-rpm/--torque-nm/--iq/--seconds, not both")
    if constant:
        if torque_nm is None and iq is None:
            iq = 65.0
        return prof.constant(60.0 if speed_rpm is None else speed_rpm, 1.5 if seconds is None else seconds,
                             iq=iq, torque_nm=torque_nm)
    return prof.load_profile(profile or "paper")


def _check_target(path: str, flag: str) -> None:
    if Path(path).suffix.lower() not in _SUFFIXES:
        raise InputError(path, flag, f"unknown capture format; use one of {', '.join(_SUFFIXES)}")


def _summary(result, mode: str, path: str | None) -> dict:
    import numpy as np

    c = result.capture
    return {
        "file": path, "serial": c.serial, "mode": mode, "seconds": float(c.t[-1] - c.t[0]),
        "samples": len(c.t), "torque_mean_nm": float(np.mean(c["torque"])),
        "speed_mean_rpm": float(np.mean(c["speed"])),
        "truth": {k: c.truth[k] for k in ("k6", "phase_k6", "c6", "phase_c6", "c12", "unb1", "R_s", "temp_degC")},
    }


@click.command("simulate")
@click.option("-o", "--output", type=click.Path(dir_okay=False), help="Capture file to write (.csv or .mf4).")
@click.option("--preset", default="paper", show_default=True, help="Bench preset (motor, ripple sources, sensors).")
@click.option("--mode", type=click.Choice(["raw", "estimated", "compensated"]),
              help="ECU control angle: raw encoder edges, estimated angle, or estimated + i_qc compensation. "
                   "Default: from --block's flags (as the firmware reads them), else estimated.")
@click.option("--block", "block_file", type=click.Path(dir_okay=False),
              help="Parameter block (binary or Intel HEX) the ECU runs; compensated mode without it "
                   "uses a block made from the plant's true ripple.")
@click.option("--profile", help="Test profile: built-in name (paper, paper-ramp, eol-default) or TOML file.")
@click.option("--speed-rpm", type=float, help="Constant dyno speed (rpm, signed) instead of a profile.")
@click.option("--torque-nm", type=float, help="Constant torque command (N*m).")
@click.option("--iq", type=float, help="Constant nominal q current i_qo (A).")
@click.option("--seconds", type=float, help="Duration of the constant point (s).")
@click.option("--serial", help="Motor serial (with --motors: prefix).")
@click.option("--seed", type=int, help="Draw the motor from production tolerances with this seed "
                                       "(default: the preset motor as it is). Also seeds sensor noise.")
@click.option("--spread", default="default", show_default=True, metavar="NAME|FILE.toml",
              help="Production spread --seed and --motors draw from (eol_cal/spreads/, docs/plant.md).")
@click.option("--motors", type=click.IntRange(min=1), help="Simulate a lot of N motors (seeds seed..seed+N-1), batched.")
@click.option("--out-dir", type=click.Path(file_okay=False), help="Directory for --motors captures.")
@click.option("--format", "fmt", type=click.Choice(["csv", "mf4"]), default="mf4", show_default=True,
              help="File format of --motors captures.")
@click.option("--plot", "plot_file", type=click.Path(dir_okay=False), help="PNG: angle, currents, torque (paper Figs. 9-12).")
@click.option("--json", "as_json", is_flag=True, help="Print a JSON summary.")
@handle_errors
@io_paths(inputs=("block_file", "profile", "spread"), outputs=("output", "plot_file"), output_dirs=("out_dir",))
def simulate_cmd(output, preset, mode, block_file, profile, speed_rpm, torque_nm, iq, seconds, serial, seed,
                 spread, motors, out_dir, fmt, plot_file, as_json) -> None:
    """Simulate a motor on the test bench (or a lot): the plant through a test profile, written as captures.

    Captures carry the plant's truth as truth.* metadata (k6, phases, c6, sensor errors, R_s, ...).
    """
    from eol_cal.numerics.xla import configure_xla

    configure_xla()  # before the first JAX computation of the process
    from cli.fit import enable_jax_cache
    from eol_cal.capture import write_capture
    from eol_cal.plant import presets, variation
    from eol_cal.plant.ecu_model import mode_of_block
    from eol_cal.plant.simulate import simulate
    from eol_cal.station.whatif import SEED_MAX
    from eol_cal.plant.spread import load_spread

    if motors is None and output is None:
        raise InputError(None, "-o", "give -o FILE (or --motors N --out-dir DIR)")
    if motors is not None and (out_dir is None or output is not None):
        raise InputError(None, "--out-dir", "--motors N writes into --out-dir DIR (and takes no -o)")
    if output is not None:
        _check_target(output, "-o")
    if seed is not None and not 0 <= seed <= SEED_MAX - (motors or 1):
        raise InputError(None, "--seed", f"{seed}: 0 .. {SEED_MAX - (motors or 1)} (numpy's and JAX's seeds are 0 .. "
                                         "2**63 - 1; with --motors N the seeds are SEED .. SEED + N - 1)")
    if plot_file is not None and Path(plot_file).suffix.lower() != ".png":
        raise InputError(plot_file, "--plot", "needs a .png file")
    prof = _profile(profile, speed_rpm, torque_nm, iq, seconds)
    block = _read_block(block_file) if block_file else None
    if mode is None:
        mode = mode_of_block(block) if block is not None else "estimated"
    base = presets.preset_spec(preset)
    spread_ = load_spread(spread)

    enable_jax_cache()
    if motors is None:
        spec = base if seed is None else variation.draw_motor(seed, base, spread=spread_)
        if serial:
            spec = spec.replace(serial=serial)
        with naming(block_file):  # "block is for P=8": the block file named
            result = simulate(spec, prof, mode=mode, blocks=block, seed=0 if seed is None else seed)[0]
        write_capture(result.capture, output)
        if plot_file:
            from eol_cal.plant.paper_figures import plot_runs

            plot_runs([result], plot_file)
        doc = _summary(result, mode, output)
        if as_json:
            print_json({"schema": SIMULATE_SCHEMA, **doc})
        else:
            console.print(f"wrote {output}: {doc['serial']}, mode {mode}, profile {prof.name}, "
                          f"{doc['seconds']:.2f} s, mean torque {doc['torque_mean_nm']:.3f} N*m")
        return

    from rich.progress import Progress

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(out_dir, "--out-dir", f"cannot create: {exc.strerror or exc}") from None
    first = 0 if seed is None else seed
    prefix = serial or "SIM"
    specs = [variation.draw_motor(first + i, base, serial=f"{prefix}-{first + i:06d}", spread=spread_)
             for i in range(motors)]
    docs = []
    with Progress(console=console, transient=as_json) as bar:
        task = bar.add_task(f"simulating {motors} motors ({prof.seconds:.1f} s each)", total=1.0)
        with naming(block_file):
            results = simulate(specs, prof, mode=mode, blocks=block, seed=first,
                               progress=lambda f: bar.update(task, completed=f))
        for r in results:
            path = out / f"{r.capture.serial}.{fmt}"
            write_capture(r.capture, path)
            docs.append(_summary(r, mode, str(path)))
    if plot_file:
        from eol_cal.plant.paper_figures import plot_runs

        plot_runs(results[:4], plot_file)
    if as_json:
        print_json({"schema": SIMULATE_SCHEMA, "motors": docs})
    else:
        console.print(f"wrote {len(docs)} captures to {out_dir}")


#: the ``schema`` of ``simulate --json`` (one motor's summary, or ``motors``: one per motor)
SIMULATE_SCHEMA = "eol-cal/simulate/1"

COMMANDS = [simulate_cmd]
