"""Issue 34 (b): a fit on a bench file nobody identified on the bench is flagged, never a silent ok.

Where the bench file came from (``identified``, ``simulated`` by the plant's own claim, or
``assumed``), what the default limits make of an assumed one that the speed bands could not verify
(``max_bench_assumed``, judged at the fit stage), and ``eol-cal fit``'s warning in the same words.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from click.testing import CliRunner

from eol_cal.analysis.fit.model_check import bench_provenance
from eol_cal.capture.data import Capture
from eol_cal.domain.bench_mechanics import SIMULATED_BENCH_KEY, load_mechanics, model_digest
from eol_cal.records.limits import BY_KEY, LIMIT_KEYS, Measured, bench_assumed, failed, judge, parse_limits
from test_station_limits import GOOD  # a variant's limits, every key of the fit stage set


MOTOR = Measured(k6=0.85e-3, ci_k6=8.8e-6, ci_phase_k6_deg=0.5, ci_c6_nm=4.6e-4, fit_r2=0.57, fit_rms_nm=0.021,
                 hall_deviation_deg=1.2, hall_source="measured")


def _capture(**metadata) -> Capture:
    return Capture(t=np.arange(4) * 1e-4, channels={}, metadata={"serial": "M-1", **metadata})


def test_the_digest_is_the_torque_path_not_the_name():
    paper = load_mechanics("paper")
    assert model_digest(dataclasses.replace(paper, name="other", source="x.toml")) == model_digest(paper)
    assert model_digest(dataclasses.replace(paper, K_shaft=paper.K_shaft * 1.01)) != model_digest(paper)
    assert model_digest(load_mechanics("resonant-250")) != model_digest(paper)


def test_provenance_identified_simulated_or_assumed(tmp_path):
    paper = load_mechanics("paper")
    mine = _capture(**{SIMULATED_BENCH_KEY: model_digest(paper)})
    other = _capture(**{SIMULATED_BENCH_KEY: model_digest(load_mechanics("resonant-250"))})
    real = _capture(source="dyno")
    assert bench_provenance(paper, [mine, mine]) == "simulated"
    # a plant on another bench, one capture without the claim, no captures, a rigid fit: assumptions
    assert bench_provenance(paper, [other]) == "assumed"
    assert bench_provenance(paper, [mine, real]) == "assumed"
    assert bench_provenance(paper, []) == "assumed"
    assert bench_provenance(None, [mine]) == "assumed"
    text = (tmp_path / "b.toml")
    text.write_text('J_dyno = 0.02\nK_shaft = 2000.0\nshaft_zeta = 0.3\ndyno_bw_hz = 5.0\ndyno_zeta = 0.8\n'
                    '[identification]\nmaster_serial = "M"\n')
    assert bench_provenance(load_mechanics(text), [real]) == "identified"


def test_an_unverified_assumption_is_what_counts():
    assert bench_assumed({"status": "insensitive", "bench": "assumed"})
    assert bench_assumed({"status": "not checked", "bench": "assumed"})
    # the bands vouch for the file (ok), or the data contradict it (mismatch: the fit's own status)
    assert not bench_assumed({"status": "ok", "bench": "assumed"})
    assert not bench_assumed({"status": "mismatch", "bench": "assumed"})
    assert not bench_assumed({"status": "insensitive", "bench": "identified"})
    assert not bench_assumed({"status": "not checked", "bench": "simulated"})
    # a result from before the provenance: only what it said then (insensitive)
    assert bench_assumed({"status": "insensitive"}) and not bench_assumed({"status": "not checked"})
    assert not bench_assumed(None)


def test_the_default_limits_fail_an_assumed_bench_at_the_fit_with_what_to_do():
    lim = parse_limits(GOOD, "x.toml")["A"]
    assert "max_bench_assumed" in LIMIT_KEYS and BY_KEY["max_bench_assumed"].stage == "fit"
    assert lim.value("max_bench_assumed") == 0.0  # judged although the file leaves it out
    assert failed(judge(MOTOR, lim, "fit")) == []
    assumed = dataclasses.replace(MOTOR, bench_assumed=1.0, bench_source="bench paper",
                                  model_check_note="the speed bands agree, but could see only below 180 Hz")
    (reason,) = failed(judge(assumed, lim, "fit"))
    assert "bench paper" in reason and "eol-cal bench identify" in reason and "180 Hz" in reason
    # a line that accepts the assumption says so in its limits file
    accept = parse_limits(GOOD + "max_bench_assumed = 1\n", "x.toml")["A"]
    assert failed(judge(assumed, accept, "fit")) == []


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Two speeds at two loads each and reverse, the captures written as files twice: as a real DAQ writes them
    (no claim) and with the claim of a plant that simulated a rigid coupling (``--bench none``)."""
    from eol_cal.capture.io import write_capture
    from eol_cal.capture.synthetic import synthetic_capture

    d = tmp_path_factory.mktemp("provenance")
    out: dict[str, list[str]] = {"real": [], "claimed": []}
    # the analytic generator writes the shaft torque straight from the ripple model: a rigid coupling
    digest = "none"
    # tests/test_fit_cli.py's points: two speeds, two loads, and reverse
    for i, (rpm, iq) in enumerate([(120.0, 20.0), (120.0, 65.0), (240.0, 20.0), (240.0, 65.0), (-120.0, -20.0),
                                   (-120.0, -65.0)]):
        c = synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=i, theta_r0=0.7 * i, serial="M-0009",
                              k6=0.00062, phase_k6=0.3, c6=0.004, phase_c6=1.1)
        for kind in out:
            if kind == "claimed":
                c = dataclasses.replace(c, metadata={**c.metadata, SIMULATED_BENCH_KEY: digest})
            p = d / f"{kind}{i}.csv"
            write_capture(c, p)
            out[kind].append(str(p))
    return out


def test_eol_cal_fit_warns_on_an_assumed_bench_and_not_on_the_plant_s_own(captures, tmp_path):
    import json

    from cli.main import cli

    runner = CliRunner()
    for kind, warned in (("real", True), ("claimed", False)):
        out = tmp_path / f"{kind}.json"
        res = runner.invoke(cli, ["fit", *captures[kind], "--bench", "none", "-o", str(out)])
        assert res.exit_code == 0, res.output
        (motor,) = json.loads(out.read_text())["motors"]
        check = motor["model_check"]
        assert motor["status"] == "ok" and check["status"] in ("insensitive", "not checked", "ok")
        assert check["bench"] == ("assumed" if warned else "simulated")
        assert bench_assumed(check) == warned
        assert ("max_bench_assumed" in res.stderr and "eol-cal bench identify" in res.stderr) == warned, res.stderr
