"""``eol-cal index``: the ripple index eta of encoder quantisation over a PPR range (seed eq. 12)."""

from __future__ import annotations

import click

from cli.common import console, handle_errors, print_json
from cli.paths import io_paths
from eol_cal.errors import InputError

#: round PPR values the seed's Fig. 4 discussion reads off (200, 500), besides powers of two
_ROUND_PPR = (100, 200, 500, 1000)


def index_rows(poles: int, ppr: int, ppr_min: int, ppr_max: int) -> list[dict]:
    """Rows of the eta table: powers of two and round values in [ppr_min, ppr_max], plus ``ppr``.

    Parameters
    ----------
    poles : int
        Number of poles P.
    ppr, ppr_min, ppr_max : int
        Highlighted PPR and the range.

    Returns
    -------
    rows : list of dict
        ``ppr``, ``deg_per_count`` (electrical deg per A pulse, P*180/N_enc), ``eta_pct`` (%),
        ``selected`` (bool), sorted by PPR.
    """
    import numpy as np

    from eol_cal.analysis.metrics import eta_percent

    values = {2**k for k in range(31) if ppr_min <= 2**k <= ppr_max}
    values |= {v for v in _ROUND_PPR if ppr_min <= v <= ppr_max}
    values.add(ppr)
    n = np.array(sorted(values))
    eta = eta_percent(n, poles)
    return [
        {"ppr": int(v), "deg_per_count": poles * 180.0 / int(v), "eta_pct": float(e), "selected": int(v) == ppr}
        for v, e in zip(n, eta, strict=True)
    ]


@click.command("index")
@click.option("--poles", type=click.IntRange(min=2), default=6, show_default=True, help="Number of poles P.")
@click.option("--ppr", type=click.IntRange(min=1), default=64, show_default=True,
              help="Encoder pulses per mechanical revolution (channel A) to highlight.")
@click.option("--min", "ppr_min", type=click.IntRange(min=1), default=16, show_default=True, help="Smallest PPR.")
@click.option("--max", "ppr_max", type=click.IntRange(min=1), default=2048, show_default=True, help="Largest PPR.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON (keys in docs/json.md).")
@click.option("--plot", "plot_file", type=click.Path(dir_okay=False, writable=True),
              help="Write the eta-against-PPR figure (seed Fig. 4 analogue) to this PNG.")
@handle_errors
@io_paths(outputs=("plot_file",))
def index_cmd(poles: int, ppr: int, ppr_min: int, ppr_max: int, as_json: bool, plot_file: str | None) -> None:
    """Torque ripple index eta = 100*(1 - cos(P*pi/N_enc)) % of encoder quantisation over a PPR range."""
    if poles % 2:
        raise InputError(None, "--poles", f"must be even, got {poles}")
    if ppr_min >= ppr_max:
        raise InputError(None, "--min/--max", f"--min ({ppr_min}) must be below --max ({ppr_max})")
    rows = index_rows(poles, ppr, ppr_min, ppr_max)
    selected = next(r for r in rows if r["selected"])
    if plot_file:
        import numpy as np

        from eol_cal.analysis.plots import plot_eta

        plot_eta(plot_file, poles, ppr, min(ppr_min, ppr), max(ppr_max, ppr), np.array([r["ppr"] for r in rows]))
    if as_json:
        print_json({
            "schema": "eol-cal/index/1",
            "poles": poles,
            "ppr": ppr,
            "eta_pct": selected["eta_pct"],
            "deg_per_count": selected["deg_per_count"],
            "rows": rows,
            "plot": plot_file,
        })
        return
    from rich.table import Table

    table = Table(title=f"Ripple index eta, P = {poles} (seed eq. 12)")
    table.add_column("PPR", justify="right")
    table.add_column("el. deg/count", justify="right")
    table.add_column("eta %", justify="right")
    for r in rows:
        style = "bold red" if r["selected"] else None
        mark = " <" if r["selected"] else ""
        table.add_row(f"{r['ppr']}{mark}", f"{r['deg_per_count']:.3f}", f"{r['eta_pct']:.3g}", style=style)
    console.print(table)
    if plot_file:
        console.print(f"plot written: {plot_file}")


COMMANDS = [index_cmd]
