"""Every capture accounted for (issue 34, item 5): a capture that gives the fit no segment is named
with its real cause in the result and on stderr, and a refusal says which captures it lost."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.analysis.fit.capture import left_out_reason
from eol_cal.analysis.fit.motors import FitOptions, fit_motors
from eol_cal.analysis.motor_result import MotorResult
from eol_cal.capture.io import write_capture
from eol_cal.capture.synthetic import synthetic_capture
from eol_cal.errors import InputError
from eol_cal.schemas import validator


def _caps(points, seconds):
    out = []
    for i, (rpm, iq) in enumerate(points):
        c = synthetic_capture(rpm=rpm, i_qo=iq, seconds=seconds, seed=i)
        out.append(dataclasses.replace(c, source=f"cap_{rpm:g}rpm_{iq:g}A.csv"))
    return out


def test_short_captures_at_two_speeds_are_refused_for_their_real_cause():
    # 0.5 s at 60 rpm (3 Hz electrical): after 0.1 s settling no whole revolution is left, so only
    # the 120 rpm captures remain; the refusal says so instead of a bare "single speed"
    caps = _caps([(60, 20), (60, 65), (120, 20), (120, 65)], 0.5)
    with pytest.raises(InputError) as err:
        fit_motors(caps, FitOptions(capture_metrics=False, frame="offline"))
    text = str(err.value)
    assert "single speed" in text and "all at 120 rpm" in text
    for src in ("cap_60rpm_20A.csv", "cap_60rpm_65A.csv"):
        assert f"{src} left out: too short" in text
    assert "cap_120rpm_20A.csv left out" not in text


def test_a_capture_left_out_is_named_in_the_result(tmp_path):
    caps = _caps([(120, 20), (120, 65), (-120, 65)], 0.6) + _caps([(60, 40)], 0.45)
    res = fit_motors(caps, FitOptions(capture_metrics=False, frame="offline"))
    (result,) = res.results
    assert result.left_out is not None and [src for src, _ in result.left_out] == ["cap_60rpm_40A.csv"]
    assert "too short" in result.left_out[0][1]
    assert "cap_60rpm_40A.csv" not in {s["source"] for s in result.segments}
    doc = res.to_json()
    validator("fit-result").validate(doc)
    (rec,) = doc["motors"]
    assert rec["captures_left_out"] == [{"source": "cap_60rpm_40A.csv", "reason": result.left_out[0][1]}]
    back = MotorResult.from_json(json.loads(json.dumps(rec)))
    assert back.left_out == result.left_out


@pytest.mark.slow  # ~3 s on a quiet machine (CONTRIBUTING.md, "Fast or slow")
def test_fit_cli_names_the_left_out_capture_on_stderr(tmp_path):
    paths = []
    for c in _caps([(120, 20), (120, 65), (-120, 65)], 0.6) + _caps([(60, 40)], 0.45):
        p = tmp_path / c.source
        write_capture(c, p)
        paths.append(str(p))
    out = tmp_path / "fit.json"
    r = CliRunner().invoke(cli, ["fit", *paths, "-o", str(out), "--frame", "offline", "--allow-untraced"])
    assert r.exit_code in (0, 1), r.output
    assert "cap_60rpm_40A.csv left out of the fit: " in r.stderr and "too short" in r.stderr
    doc = json.loads(out.read_text())
    assert [e["source"] for e in doc["motors"][0]["captures_left_out"]] == [paths[-1]]


def test_reason_for_a_shaft_that_does_not_turn():
    t = np.arange(2000) / 1e4
    why = left_out_reason(t, np.zeros_like(t), np.zeros_like(t), np.full_like(t, 20.0), 3)
    assert "does not turn" in why
