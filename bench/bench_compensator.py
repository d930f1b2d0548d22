"""Compensator: the firmware's table lookup vs evaluating the ripple model with sinf every tick.

Prints, for table lengths 64/256/1024: the worst-case deviation of the table evaluation from the
analytic i_qc (interpolation + binary32), and the host cost per call of the C reference
(eol_comp_iqc) next to the alternative a firmware engineer would write first (two sinf calls per
tick from c6/k6/phases). Host timings only show the ratio; the C28x figure is not measured here.

    python bench/bench_compensator.py
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from eol_cal.firmware import compensator as comp
from eol_cal.domain.motor_params import load_motor

ROOT = Path(__file__).resolve().parents[1]

RIPPLE = dict(c6=0.012, phase_c6=0.35, k6=0.0015, phase_k6=-0.6)

C_DRIVER = r"""
#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <stdio.h>
#include <time.h>
#include "eol_comp.h"

static float tc[1024], tp[1024];

static float analytic(float th, float om, float iq, float lead, float lim,
                      float c6, float pc, float k6, float pk, float kt)
{
    float a = th + om * lead;
    float s = (c6 * sinf(6.0f * a + pc) + iq * k6 * sinf(6.0f * a + pk)) / kt;
    return s > lim ? lim : (s < -lim ? -lim : s);
}

static double now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

int main(int argc, char **argv)
{
    long i, calls = 20000000L;
    unsigned n = 256;
    volatile float sink = 0.0f;
    float th = 0.0f;
    double t_tab, t_sin;
    (void)argc; (void)argv;
    for (i = 0; i < (long)n; ++i) {
        tc[i] = 0.2f * sinf(6.2831853f * (float)i / (float)n);
        tp[i] = 0.03f * cosf(6.2831853f * (float)i / (float)n);
    }
    {
        double a = now();
        for (i = 0; i < calls; ++i) {
            th += 0.000314f; if (th > 6.2831853f) th -= 6.2831853f;
            sink += eol_comp_iqc(th, 314.0f, 3.0f, tc, tp, (unsigned short)n, 8e-4f, 8.0f);
        }
        t_tab = (now() - a) / (double)calls;
    }
    th = 0.0f;
    {
        double a = now();
        for (i = 0; i < calls; ++i) {
            th += 0.000314f; if (th > 6.2831853f) th -= 6.2831853f;
            sink += analytic(th, 314.0f, 3.0f, 8e-4f, 8.0f, 0.012f, 0.35f, 0.0015f, -0.6f, 0.04905f);
        }
        t_sin = (now() - a) / (double)calls;
    }
    printf("%.3f %.3f\n", t_tab * 1e9, t_sin * 1e9);
    return 0;
}
"""


def table_error(n: int, kt: float) -> float:
    """Largest |table evaluation - analytic| over a dense angle grid and i_qo in [-60, 60] A (A)."""
    tc, tp = comp.make_tables(N=n, kt=kt, **RIPPLE)
    theta = np.linspace(0, 2 * np.pi, 200_001, dtype=np.float32)
    worst = 0.0
    for i_qo in (-60.0, -5.0, 0.0, 5.0, 60.0):
        got = comp.i_qc(theta, np.float32(0), np.float32(i_qo), tc, tp, 0.0, 1e9)
        want = comp.ripple_i_qc(theta.astype(np.float64), i_qo, kt=kt, **RIPPLE)
        worst = max(worst, float(np.max(np.abs(got - want))))
    return worst


def main() -> None:
    kt = load_motor("paper").kt
    peak = (RIPPLE["c6"] + 60 * RIPPLE["k6"]) / kt
    print(f"paper motor kt = {kt:.5f} N*m/A; peak i_qc at i_qo = 60 A: {peak:.3f} A")
    print("table_len  max |table - analytic| (A)  relative to peak")
    for n in (16, 64, 256, 1024):
        e = table_error(n, kt)
        print(f"{n:9d}  {e:27.3e}  {e / peak:16.2e}")
    cc = shutil.which("cc")
    if cc is None:
        print("no cc: C timing skipped")
        return
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "drv.c"
        src.write_text(C_DRIVER)
        exe = Path(tmp) / "drv"
        cdir = ROOT / "firmware_params" / "c"
        subprocess.run([cc, "-std=c99", "-O2", "-ffp-contract=off", f"-I{cdir}", f"-I{cdir.parent}",
                        str(src), str(cdir / "eol_comp.c"), "-o", str(exe), "-lm"], check=True)
        best_tab, best_sin = 1e9, 1e9
        for _ in range(3):
            out = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout.split()
            best_tab, best_sin = min(best_tab, float(out[0])), min(best_sin, float(out[1]))
    print(f"host C, per call (best of 3 x 2e7 calls, N=256): table lookup {best_tab:.1f} ns, "
          f"2 x sinf model {best_sin:.1f} ns, ratio {best_sin / best_tab:.1f}x")

    t = time.perf_counter()
    b_tc, b_tp = comp.make_tables(N=256, kt=kt, **RIPPLE)
    x = np.random.default_rng(0).uniform(0, 6.28, 1_000_000).astype(np.float32)
    comp.i_qc(x, np.float32(314), np.float32(3), b_tc, b_tp, 8e-4, 8.0)
    print(f"numpy reference, 1e6 evaluations: {time.perf_counter() - t:.3f} s")


if __name__ == "__main__":
    main()
