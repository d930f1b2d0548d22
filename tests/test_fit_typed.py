"""Typed fit results (issue 39, item 3): ``fit_motors`` gives :class:`MotorResult` s that keep the
solver's result, the ``eol-cal/fit-result/1`` document is made from them only at the file's edge,
and the files ``eol-cal fit`` writes are the ones it wrote before the results were typed.

``fixtures/fit_typed/*.json`` were written by ``eol-cal fit --json`` at commit 662b4d7 (the
document built as a dict, parsed back into ``MotorResult`` where the station needed one) over the
captures :func:`write_captures` makes, and written again when the model check's test changed (issue
34: the bands' covariance and the 6th's own noise; only ``model_check``'s figures moved), and when
the mechanical orders' intervals changed (issue 34: the noise at each order and the segments'
jackknife; only ``mech.orders[].c.ci95`` and ``phase_c.ci95`` moved), when the fit's angle
took out the encoder errors' mechanical orders 1-2 measured against the halls (issue 34: the
model check's false mismatches; ``angle_correction`` says so, the estimates moved by the orders'
noise on these ideal encoders, k6 by 1e-5 relative), and when a fit of fewer than 3 segments
stopped giving the orders an interval and the intervals took the segments' scatter from 7
segments on (``one_load.json``: null intervals and a ``no_interval`` reason), and when the
mechanical switch's margin took the fingerprint's measured error (threshold 0.03; ``mech.margin``
and its reason only), and when an order not resolved from zero got an amplitude interval that
reaches it and no phase bound (issue 34: ``two_motors.json``'s synthetic captures have no
mechanical orders; only ``mech.orders[].c.ci95`` and ``phase_c.ci95`` moved), and when the
orders' jackknife took the electrical quantities' Student's t (Welch-Satterthwaite; only
``mech.orders[].c.ci95`` moved), and when a segment of whole electrical revolutions, a sample
short of a mechanical order's period, carried the order again (issue 34, ``model.MECH_SPAN_TOL``:
the estimates moved, k6 by 0.1-0.3 %), and when the switch's fingerprint error became a jackknife
over the stretches and the switch gated on the predicted cosine (0.29) over a margin of 0 (issue 34:
``mech.margin`` and its reason only; the intervals at each harmonic's own noise, the same change,
leave these fits of fewer than 7 segments as they were but for the last bit), and when an order's
pair covariance took the scatter's excess per direction and its region Hotelling's T^2 (issue 34:
only ``two_motors.json``'s ``mech.orders[].c.ci95`` moved, 13-15 % wider on M-0007, its orders not
resolved; a resolved order's amplitude and phase kept the pair's trace rule), and when ``mech.margin``
recorded the switch's least cosine beside its least margin (``min_score``, added; nothing moved); write
them again only for a change that means to change the file (``python tests/test_fit_typed.py DIR``,
then copy ``DIR/*.json``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import Any

import pytest

from eol_cal.capture.io import write_capture
from eol_cal.capture.synthetic import synthetic_capture

GOLDEN = Path(__file__).resolve().parent.parent / "fixtures" / "fit_typed"
TRUTH = dict(k6=0.00062, phase_k6=0.3, c6=0.004, phase_c6=1.1)
#: the capture files: (name, serial, rpm, i_qo A, noise N*m, seed); M-0009 is noisy, its intervals too wide
CAPTURES = (
    *((f"a{i}.csv", "M-0007", rpm, iq, 0.002, i) for i, (rpm, iq) in
      enumerate([(120.0, 20.0), (120.0, 65.0), (240.0, 20.0), (240.0, 65.0), (-120.0, -20.0), (-120.0, -65.0)])),
    *((f"b{i}.csv", "M-0009", rpm, iq, 0.05, 10 + i) for i, (rpm, iq) in
      enumerate([(120.0, 20.0), (120.0, 65.0), (240.0, 65.0), (-120.0, -65.0)])),
)
#: golden file -> (the captures' name prefixes, eol-cal fit's options): usable and too wide, not
#: converged, one load point without c6 (no phase interval: nulls inside an ok result)
RUNS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "two_motors.json": (("a", "b"), ("--bench", "none")),
    "not_converged.json": (("a",), ("--max-steps", "1")),
    "one_load.json": (("a1", "a3"), ("--no-c6", "--delay", "0", "--bench", "none", "--max-ci-k6", "0.1",
                                       "--max-ci-phase", "10")),
}


def write_captures(d: Path) -> None:
    for name, serial, rpm, iq, noise, seed in CAPTURES:
        write_capture(synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=seed, theta_r0=0.7 * seed, serial=serial,
                                        noise=noise, **TRUTH), d / name)


def fit_args(golden: str, out: str) -> list[str]:
    prefixes, options = RUNS[golden]
    files = [name for name, *_ in CAPTURES if name.startswith(prefixes)]
    return ["fit", *files, "-o", out, *options, "--json"]


#: numbers' relative tolerance. The fingerprint and the orders' intervals come out of least squares
#: whose conditioning turns BLAS's last-bit differences between processors into ~4e-12 relative
#: (measured: AMD EPYC against the processor that wrote the files, ``mech.fingerprint[0]`` 2.9e-12,
#: ``mech.orders[0].c.ci95`` 3.7e-12); any change the files are about moves a number by 1e-6 or more.
REL_TOL = 1e-9


def _same(a: Any, b: Any, where: str = "") -> None:
    """``a`` and ``b`` identical as parsed JSON: keys in order, types, strings and nulls exactly;
    numbers to :data:`REL_TOL` (the captures are remade and refitted: the last bits of a float
    may differ on another processor)."""
    assert type(a) is type(b), (where, a, b)
    if isinstance(a, dict):
        assert list(a) == list(b), (where, list(a), list(b))
        for k in a:
            _same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), (where, len(a), len(b))
        if a and all(type(x) is float for x in a + b):
            # one solution's entries share its absolute error: a near-zero entry is held to the vector's scale
            scale = max(abs(y) for y in b)
            for i, (x, y) in enumerate(zip(a, b, strict=True)):
                assert abs(x - y) <= REL_TOL * scale, (f"{where}[{i}]", x, y, scale)
            return
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, float):
        assert math.isclose(a, b, rel_tol=REL_TOL, abs_tol=1e-300), (where, a, b)
    else:
        assert a == b, (where, a, b)


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    d = tmp_path_factory.mktemp("typed")
    write_captures(d)
    return d


@pytest.mark.slow  # three CLI fits
@pytest.mark.parametrize("golden", sorted(RUNS))
def test_eol_cal_fit_writes_the_file_it_wrote_before_the_results_were_typed(golden, captures, tmp_path, monkeypatch):
    from click.testing import CliRunner

    from cli.main import cli

    monkeypatch.chdir(captures)  # the sources as the golden files name them
    out = tmp_path / golden
    res = CliRunner().invoke(cli, fit_args(golden, str(out)), catch_exceptions=False)
    assert res.exit_code in (0, 1), res.output
    before = json.loads((GOLDEN / golden).read_text())
    for doc in (json.loads(out.read_text()), json.loads(res.stdout)):
        assert doc.pop("created") and before.get("created")
        _same(doc, {k: v for k, v in before.items() if k != "created"})
    # the golden runs hold every status the files name but model_mismatch, and an ok fit with nulls
    assert golden != "two_motors.json" or [m["status"] for m in before["motors"]] == ["ok", "ci_too_wide"]


@pytest.mark.slow  # two fits
def test_the_results_are_typed_and_equal_what_the_file_reads_back(captures):
    from eol_cal.analysis.fit.motors import FitOptions, fit_motors
    from eol_cal.analysis.motor_result import FitStatus, MotorResult
    from eol_cal.capture.io import read_capture

    caps = [read_capture(captures / name) for name, *_ in CAPTURES]
    fitted = fit_motors(caps, FitOptions(mechanics=None))
    ok, wide = fitted.results
    assert (ok.status, wide.status) == (FitStatus.OK, FitStatus.CI_TOO_WIDE)
    # the solver's result kept, by optimistix's name
    assert ok.solver_result == wide.solver_result == "successful"
    # what a reader of the file gets is what the fit gave (but the solver's result, which the file
    # keeps only as fit.converged)
    doc = json.loads(json.dumps(fitted.to_json(), allow_nan=False))
    for res, entry in zip(fitted.results, doc["motors"], strict=True):
        assert MotorResult.from_json(entry) == dataclasses.replace(res, solver_result=None)
    # a solver stopped at its step limit: the status says not converged, the result says why
    (stopped,) = fit_motors(caps[:6], FitOptions(mechanics=None, spec=dataclasses.replace(
        FitOptions().spec, max_steps=1))).results
    assert stopped.status == FitStatus.NOT_CONVERGED and stopped.estimates is None
    assert stopped.solver_result == "nonlinear_max_steps_reached"


if __name__ == "__main__":  # write the golden files with the eol-cal this Python imports: DIR
    from click.testing import CliRunner

    from cli.main import cli

    target = Path(sys.argv[1]).resolve()
    target.mkdir(parents=True, exist_ok=True)
    write_captures(target)
    import os

    os.chdir(target)
    for name in RUNS:
        result = CliRunner().invoke(cli, fit_args(name, str(target / name)), catch_exceptions=False)
        print(name, result.exit_code, file=sys.stderr)
