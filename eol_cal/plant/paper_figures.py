"""Analogues of the seed paper's Figs. 9-12 for a simulated run: angle, currents, torque."""

from __future__ import annotations

from pathlib import Path
from collections.abc import Sequence

import numpy as np

from eol_cal.infra.atomic import atomic_path
from eol_cal.rendering.renderer import literal_texts, plain, pyplot


def plot_runs(results: Sequence, path: str | Path, seconds: float = 0.5) -> None:
    """One column per run (e.g. raw, estimated, compensated): angle, currents, torque.

    Parameters
    ----------
    results : sequence of SimResult
        Runs to draw; the last ``seconds`` (s) of each are shown, like the paper's
        100 ms/div scope views.
    path : path
        PNG file, written atomically.
    """
    plt = pyplot()

    n = len(results)
    fig, axes = plt.subplots(4, n, figsize=(5.5 * n, 10), sharex="col", squeeze=False)
    for j, r in enumerate(results):
        c = r.capture
        t = c.t
        sel = t >= t[-1] - seconds
        ts = t[sel] - t[sel][0]
        ax = axes[:, j]
        ax[0].plot(ts, r.theta_r[sel], label=r"$\theta_r$ true", lw=1.0)
        ax[0].plot(ts, r.theta_enc[sel], label=r"$\theta_{enc}$ (edges)", lw=0.8)
        ax[0].plot(ts, r.theta_hat[sel], label=r"$\hat\theta_r$ estimated", lw=0.8, ls="--")
        ax[0].set_ylabel("electrical angle (rad)")
        ax[0].legend(loc="upper right", fontsize=7)
        ax[1].plot(ts, c["iq"][sel], label="$i_q$", lw=0.8)
        ax[1].plot(ts, c["id"][sel], label="$i_d$", lw=0.8)
        ax[1].plot(ts, c["ia"][sel], label="$i_a$", lw=0.8)
        ax[1].set_ylabel("current (A)")
        ax[1].legend(loc="upper right", fontsize=7)
        ax[2].plot(ts, c["iqc"][sel], lw=0.8, color="tab:red")
        ax[2].set_ylabel("$i_{qc}$ (A)")
        ax[3].plot(ts, c["torque"][sel], lw=0.8, color="k")
        ax[3].set_ylabel("torque (N*m)")
        ax[3].set_xlabel("time (s)")
        mode = c.truth.get("mode", "")
        ax[0].set_title(f"{plain(c.metadata.get('serial', ''))}  mode {plain(mode)}  "
                        f"{np.mean(c['speed']):.0f} rpm, i_qo {np.mean(c['iq_ref']):.0f} A", fontsize=9)
    fig.tight_layout()
    literal_texts(fig)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
