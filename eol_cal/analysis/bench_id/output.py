"""An identified bench written out: the bench file the fit reads (TOML, atomically) and the plot of
the measured path against the model (PNG).

The file holds the keys of :data:`eol_cal.domain.bench_mechanics.SHAFT_KEYS` (held ones from the base bench,
said so in the table), the transducer's bandwidth (only when resolved) and delay, and an
``[identification]`` table with every estimate's value, 95 % interval, unit and status, the
sweep it came from and the fit's Birge ratio: what :func:`eol_cal.domain.bench_mechanics.load_mechanics` reads
back, plus what a station engineer reads.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from eol_cal.analysis.bench_id.identify import BenchIdentification
from eol_cal.infra.atomic import atomic_write
from eol_cal.rendering.figures import pyplot, save_png
from eol_cal.domain.bench_mechanics import SHAFT_KEYS, torsion_response

#: the 95 % error bars' factor (normal)
_Z95_PLOT = 1.96
_COMMENTS = {
    "J_dyno": "kg*m^2, dyno rotor and coupling hub",
    "K_shaft": "N*m/rad, torsional stiffness of shaft, couplings and transducer",
    "shaft_zeta": "1, damping ratio of the torsion mode",
    "dyno_bw_hz": "Hz, bandwidth of the dyno drive's PI speed loop",
    "dyno_zeta": "1, damping ratio the speed loop is tuned for",
    "transducer_bw_hz": "Hz, the torque transducer's first-order bandwidth",
    "transducer_delay_s": "s, the transducer chain's delay against the capture's sample times",
}


def _value(v: object) -> str:
    """A TOML value: strings as JSON strings (valid TOML basic strings), floats with full precision."""
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    x = float(v)  # type: ignore[arg-type]
    if not math.isfinite(x):
        raise ValueError(f"not a finite number: {x!r}")
    return repr(x)


def bench_toml(res: BenchIdentification, sweep_profile: str | None = None) -> str:
    """The bench file's text (see the module doc)."""
    m = res.mechanics
    lines = [f"# The torque path identified by `eol-cal bench identify` from master motor {res.points.serial}'s sweep",
             "# (docs/bench-identify.md). The fit reads the keys; [identification] is for the reader.",
             f"name = {_value(m.name)}"]
    for key in SHAFT_KEYS:
        e = res.estimates[key]
        held = "" if e.status == "identified" else f" ({e.status})"
        lines.append(f"{key} = {_value(getattr(m, key))}    # {_COMMENTS[key]}{held}")
    if m.transducer_bw_hz is not None:
        lines.append(f"transducer_bw_hz = {_value(m.transducer_bw_hz)}    # {_COMMENTS['transducer_bw_hz']}")
    if m.transducer_delay_s is not None:
        lines.append(f"transducer_delay_s = {_value(m.transducer_delay_s)}    # {_COMMENTS['transducer_delay_s']}")
    lines += ["", "[identification]",
              f"master_serial = {_value(res.points.serial)}",
              f"sources = {_value(list(res.points.sources))}",
              f"base_bench = {_value(res.base.name)}",
              f"points = {len(res.points.M)}",
              f"speeds = {len(np.unique(np.round(np.abs(res.points.speed_rpm))))}",
              f"freq_min_hz = {_value(float(res.points.freq_hz.min()))}",
              f"freq_max_hz = {_value(float(res.points.freq_hz.max()))}",
              f"birge = {_value(res.birge)}",
              f"dof = {res.dof}",
              f"dropped = {_value(res.dropped)}",
              f"notes = {_value(res.notes)}"]
    if sweep_profile:
        lines.append(f"profile = {_value(sweep_profile)}")
    for key, e in res.estimates.items():
        lines += ["", f"[identification.{key}]", f"value = {_value(e.value)}"]
        if e.ci95 is not None:
            lines.append(f"ci95 = {_value(e.ci95)}")
        lines += [f"unit = {_value(e.unit)}", f"status = {_value(e.status)}"]
        if e.note:
            lines.append(f"note = {_value(e.note)}")
    return "\n".join(lines) + "\n"


def write_bench(res: BenchIdentification, path: str | Path, sweep_profile: str | None = None) -> None:
    """Write the bench file at ``path`` atomically (nothing half-written on failure)."""
    atomic_write(path, bench_toml(res, sweep_profile))


def plot_bench(res: BenchIdentification, path: str | Path) -> None:
    """Measured gain and phase of the path at each point against the identified model and the base bench."""
    plt = pyplot()
    pts = res.points
    measured = pts.M / res.inputs()
    sigma = np.sqrt(pts.se_M ** 2 + (np.abs(res.response(pts.omega)) * pts.kt * pts.se_Iq) ** 2) / np.abs(res.inputs())
    f = pts.freq_hz
    grid = np.geomspace(max(f.min() / 1.5, 1.0), f.max() * 1.5, 400)
    w = 2 * np.pi * grid
    model = res.response(w)
    base = torsion_response(w, res.motor.J, res.motor.B, res.base) * (res.response(w) / torsion_response(
        w, res.motor.J, res.motor.B, res.mechanics))
    fig, (ax_g, ax_p) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    # phases drawn continuous: the model's unwrapped, each point within half a turn of it
    model_at = res.response(np.abs(pts.omega))
    for h, marker in zip((6, 12, 18), ("o", "s", "^"), strict=True):
        sel = (pts.harmonic == h) & np.isfinite(measured)
        g = np.where(pts.omega[sel] < 0, np.conj(measured[sel]), measured[sel])
        # points whose 95 % bar spans more than the value carry no phase: drawn faint
        weak = _Z95_PLOT * sigma[sel] > np.abs(g)
        phase_model = np.interp(f[sel], grid, np.degrees(np.unwrap(np.angle(model))))
        phase = phase_model + np.degrees(np.angle(g / model_at[sel]))
        for part, alpha in ((~weak, 1.0), (weak, 0.25)):
            ax_g.errorbar(f[sel][part], np.abs(g[part]), yerr=_Z95_PLOT * sigma[sel][part], fmt=marker, ms=4, lw=0.8,
                          color=f"C{h // 6 - 1}", alpha=alpha, label=f"harmonic {h}" if alpha == 1.0 else None)
            ax_p.errorbar(f[sel][part], phase[part],
                          yerr=np.minimum(np.degrees(_Z95_PLOT * sigma[sel][part] / np.abs(g[part])), 180.0),
                          fmt=marker, ms=4, lw=0.8, color=f"C{h // 6 - 1}", alpha=alpha)
    fn = res.estimates["f_n_hz"]
    ax_g.plot(grid, np.abs(model), "k-", lw=1.2, label=f"identified: {fn.value:.1f} ± {fn.ci95:.1f} Hz, "
                                                       f"zeta {res.mechanics.shaft_zeta:.3f}")
    ax_g.plot(grid, np.abs(base), "k--", lw=0.9, label=f"base bench {res.base.name} (same transducer)")
    ax_p.plot(grid, np.degrees(np.unwrap(np.angle(model))), "k-", lw=1.2)
    ax_p.plot(grid, np.degrees(np.unwrap(np.angle(base))), "k--", lw=0.9)
    ax_g.set_ylim(max(float(np.abs(model).min()) / 3, 1e-4), None)
    ax_g.set_xscale("log")
    ax_g.set_yscale("log")
    ax_g.set_ylabel("gain |T_shaft / T_airgap| (1)")
    ax_p.set_ylabel("phase (deg)")
    ax_p.set_xlabel("frequency (Hz)")
    ax_g.set_title(f"torque path of the bench, master motor {pts.serial}: Birge ratio {res.birge:.2f}, "
                   f"{len(pts.M)} points", fontsize=9)
    ax_g.legend(fontsize=8)
    for ax in (ax_g, ax_p):
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    save_png(fig, path)

