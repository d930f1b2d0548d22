"""The type-1 gauge study against a data set worked by hand, with the formulas written out."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eol_cal.msa.type1 import type1_study

# one reference part, x_ref = 10.000, tolerance T = 0.1 (say 9.95 .. 10.05), 25 measurements:
# 8 x 10.000, 9 x 10.002, 8 x 10.004
X = [10.000] * 8 + [10.002] * 9 + [10.004] * 8
#   mean = 10 + (9 * 0.002 + 8 * 0.004) / 25 = 10.002          -> bias = 0.002
#   s    = sqrt((8 * 0.002^2 + 9 * 0 + 8 * 0.002^2) / 24) = 0.002 sqrt(2/3) = 0.00163299
S = 0.002 * math.sqrt(2.0 / 3.0)
#   Cg   = 0.2 T / (4 s)             = 0.02 / (4 s)           = 2.5 / sqrt(2/3) = 3.0619
#   Cgk  = (0.1 T - |bias|) / (2 s)  = (0.01 - 0.002) / (2 s) = 2 / sqrt(2/3)   = 2.4495
#   t    = bias / (s / sqrt(25))     = 0.002 * 5 / s          = 5 / sqrt(2/3)   = 6.1237
#   %Var(repeatability) = 100 * 4 s / T = 6.532 %


def test_type1_by_hand():
    st = type1_study(X, 10.0, 0.1, quantity="d", unit="mm")
    assert st.n == 25 and st.mean == pytest.approx(10.002, rel=1e-12) and st.bias == pytest.approx(0.002, rel=1e-9)
    assert st.sd == pytest.approx(S, rel=1e-9)
    assert st.cg.value == pytest.approx(2.5 / math.sqrt(2 / 3), rel=1e-9)
    assert st.cg.value == pytest.approx(3.0619, abs=1e-4)
    assert st.cgk.value == pytest.approx(2.0 / math.sqrt(2 / 3), rel=1e-8)
    assert st.cgk.value == pytest.approx(2.4495, abs=1e-4)
    assert st.t == pytest.approx(5.0 / math.sqrt(2 / 3), rel=1e-8)
    assert st.var_repeatability_pct.value == pytest.approx(100 * 4 * S / 0.1, rel=1e-9)
    assert st.capable is True and st.band == pytest.approx((9.99, 10.01))
    # the t-test is scipy's one-sample t-test of H0: mean = x_ref
    import scipy.stats  # ~1 s to import: in the test, not in every worker's collection

    ref = scipy.stats.ttest_1samp(X, 10.0)
    assert st.t == pytest.approx(ref.statistic, rel=1e-9) and st.p_value == pytest.approx(ref.pvalue, rel=1e-6)
    assert st.p_value < 1e-5  # a real bias


def test_type1_six_sigma_convention():
    st = type1_study(X, 10.0, 0.1, l=6.0)  # Minitab's default study variation: +-3 s
    assert st.cg.value == pytest.approx(0.02 / (6 * S), rel=1e-9)  # 2.0412
    assert st.cgk.value == pytest.approx(0.008 / (3 * S), rel=1e-8)  # 1.6330


def test_type1_not_capable_when_the_bias_eats_the_band():
    st = type1_study(np.array(X) + 0.007, 10.0, 0.1)  # bias 0.009: Cgk = (0.01 - 0.009) / (2 s) = 0.306
    assert st.cgk.value == pytest.approx(0.001 / (2 * S), rel=1e-6) and st.capable is False


def test_type1_below_min_n_and_without_tolerance_gives_reasons():
    few = type1_study(X[:7], 10.0, 0.1)
    assert few.cg.value is None and few.cg.reason == "n = 7 < 25" and few.cgk.reason == "n = 7 < 25"
    assert few.capable is None and few.bias == pytest.approx(np.mean(X[:7]) - 10.0)
    no_t = type1_study(X, 10.0, None)
    assert no_t.cg.reason == "no tolerance" and no_t.sd == pytest.approx(S, rel=1e-9)
    flat = type1_study([1.0] * 30, 1.0, 0.5)
    assert flat.cg.reason == "no spread (all measurements equal)" and math.isnan(flat.t)
    no_ref = type1_study(X, None, 0.1)  # repeatability needs no reference; the bias does
    assert no_ref.cg.value == pytest.approx(2.5 / math.sqrt(2 / 3), rel=1e-9) and no_ref.cgk.reason == "no reference"
    assert math.isnan(no_ref.bias) and math.isnan(no_ref.p_value) and no_ref.capable is None
    with pytest.raises(ValueError):
        type1_study(X, 10.0, 0.0)


def test_type1_of_a_phase_across_the_wrap():
    # a master's phase measured 25 times at 179.5 / -179.5 deg against x_ref = 179 deg: the values are
    # 179.5 and 180.5 deg on the circle (not -179.5), mean 180 deg (13 at 179.5, 12 at 180.5: 179.98)
    deg = math.pi / 180
    theta = np.array([179.5 if i % 2 == 0 else -179.5 for i in range(25)]) * deg
    st = type1_study(theta, 179.0 * deg, 20.0 * deg, circular=True)
    mean = (13 * 179.5 + 12 * 180.5) / 25
    assert st.mean / deg == pytest.approx(mean) and st.bias / deg == pytest.approx(mean - 179.0)
    s = np.std([179.5] * 13 + [180.5] * 12, ddof=1)
    assert st.sd / deg == pytest.approx(s)
    assert st.cg.value == pytest.approx(0.2 * 20.0 / (4 * s), rel=1e-9)


class _Runs:
    """What the study's document reads of its runs: how many, and when the first and last began."""

    def __init__(self, n: int) -> None:
        self.started_at = np.array([f"2026-11-01T08:{i:02d}:00" for i in range(n)], dtype=object)

    def __len__(self) -> int:
        return len(self.started_at)


def test_the_study_page_and_plots_show_each_quantity_against_its_band(tmp_path):
    """The page and the PNGs of `eol-cal msa type1 --out/--plots` (eol_cal/msa/type1_page.py), without a
    database: a capable k6 with its reference and band, a c6 without a reference (no band, no ref line)."""
    from eol_cal.msa.study import document
    from eol_cal.msa.type1_page import line, write_page, write_pngs

    capable = type1_study(X, 10.0, 0.1, quantity="k6", unit="mN*m/A")
    no_ref = type1_study(list(np.linspace(3.0, 3.2, 25)), None, None, quantity="c6", unit="mN*m")
    results = [(capable, "limits"), (no_ref, "none")]
    titles = [f"R{i:03d}" for i in range(25)]
    doc = document(results, serial="M-42", runs=_Runs(25), min_n=10)
    page = write_page(tmp_path / "study.html", doc, results, title="eol.db", run_titles=titles).read_text()
    assert "master M-42" in page and "CAPABLE" in page and "NOT SHOWN" not in page
    # k6's chart: its points (hover: the run and its value), the reference, the band and the mean
    for gid in ("values-k6", "ref-k6", "band-k6", "mean-k6", "values-c6", "mean-c6"):
        assert gid in page, gid
    assert "ref-c6" not in page and "band-c6" not in page  # nothing to draw them from
    assert "R024: 10.004 mN*m/A" in page
    assert line(capable) == "n = 25, s = 0.00163, bias = 0.002, Cg 3.06, Cgk 2.45"
    pngs = write_pngs(results, tmp_path / "plots")
    assert [p.name for p in pngs] == ["type1-k6.png", "type1-c6.png"]
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000 for p in pngs)
