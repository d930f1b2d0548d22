"""``eol-cal fit`` / ``eol-cal analyze`` on a joined dyno capture (``eol-cal acquire``): windows, not one angle."""

from __future__ import annotations

import inspect
import json
import logging
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.capture.data import Capture
from eol_cal.capture.synthetic import synthetic_capture
from eol_cal.capture.windows import split_windows, window_spans
from eol_cal.dyno.sim_dyno import DynoSim, DynoSimThread
from eol_cal.dyno.sim_capture import synthetic_source

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

# two loads x both directions: k6, c6 and the transducer delay are all identifiable
PROFILE = """
name = "windows"
[[segment]]
speed_rpm = 120.0
iq = 20.0
seconds = 0.6

[[segment]]
speed_rpm = 120.0
iq = 65.0
seconds = 0.6

[[segment]]
speed_rpm = -120.0
iq = 65.0
seconds = 0.6

[[segment]]
speed_rpm = -120.0
iq = 20.0
seconds = 0.6
"""


@pytest.fixture(scope="module")
def joined(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("win")
    prof = d / "p.toml"
    prof.write_text(PROFILE)
    out = d / "cap.mf4"
    with DynoSimThread(DynoSim(synthetic_source, serial="M-WIN")) as th:
        r = CliRunner().invoke(cli, ["acquire", "--dyno", f"127.0.0.1:{th.port}", "--profile", str(prof), "-o", str(out),
                                     "--split-windows", "--json"])
    assert r.exit_code == 0, r.output
    return out


def _fit(tmp: Path, name: str, files: list[Path]) -> dict:
    out = tmp / f"{name}.json"
    # 0.6 s windows: intervals a little wider than the production limits; acquired without the
    # ECU's bus (the dyno's synthetic source runs no ECU): untraced on purpose
    r = CliRunner().invoke(cli, ["fit", *map(str, files), "-o", str(out), "--max-ci-k6", "0.1", "--max-ci-phase", "6",
                                 "--allow-untraced"])
    assert r.exit_code == 0, r.output
    (m,) = json.loads(out.read_text())["motors"]
    return m


@pytest.mark.slow
def test_fit_of_the_joined_capture_matches_the_fit_of_its_windows(joined: Path, tmp_path: Path):
    windows = sorted(joined.parent.glob("cap.w*.mf4"))
    assert len(windows) == 4
    whole = _fit(tmp_path, "whole", [joined])
    split = _fit(tmp_path, "split", windows)
    assert whole["status"] == "ok" and whole["fit"]["converged"]
    assert whole["fit"]["n_segments"] == split["fit"]["n_segments"] == 4
    assert whole["model"]["angle_frame"] == "firmware"
    for key in ("k6", "phase_k6", "c6", "phase_c6", "delay_s"):
        assert whole[key]["value"] == pytest.approx(split[key]["value"], rel=1e-6, abs=1e-9), key
    assert whole["fit"]["rms"] == pytest.approx(split["fit"]["rms"], rel=1e-6)
    assert [s["source"] for s in whole["segments"]] == [f"{joined}#{k}" for k in range(1, 5)]
    # and it finds the k6 the dyno's synthetic source puts in (synthetic_capture's default)
    truth_k6 = inspect.signature(synthetic_capture).parameters["k6"].default
    assert abs(whole["k6"]["value"] - truth_k6) <= 2 * whole["k6"]["ci95"]


def test_analyze_reports_a_joined_capture_per_window(joined: Path):
    r = CliRunner().invoke(cli, ["analyze", str(joined), "--json"])
    assert r.exit_code == 0, r.output
    assert "no record of the ECU state" in r.stderr  # acquired without the ECU's bus: a warning
    doc = json.loads(r.stdout)
    assert [c["file"] for c in doc["captures"]] == [f"{joined}#{k}" for k in range(1, 5)]
    speeds = [c["speed_rpm"] for c in doc["captures"]]
    assert speeds == pytest.approx([120.0, 120.0, -120.0, -120.0], rel=2e-3)
    assert all(c["angle"]["hall_residual_rms_deg"] < 1.0 for c in doc["captures"])


def test_window_spans_tolerate_the_rounded_starts_and_find_gaps():
    # starts written to the microsecond, one rounded up by 0.4 us, one down
    t = np.concatenate([np.arange(100) / 1e4, 3.7975246 + np.arange(120) / 1e4, 5.2000004 + np.arange(80) / 1e4])
    meta = {"serial": "S", "segment_starts": "0.000000,3.797525,5.200000", "segments": 3}
    cap = Capture(t, {"torque": np.arange(300.0)}, meta, source="x")
    assert window_spans(cap) == [(0, 100), (100, 220), (220, 300)]
    no_meta = Capture(t, cap.channels, {"serial": "S"}, source="x")
    assert window_spans(no_meta) == [(0, 100), (100, 220), (220, 300)]
    pieces = split_windows(cap)
    assert [p.source for p in pieces] == ["x#1", "x#2", "x#3"] and pieces[2].metadata["segments"] == 1
    continuous = Capture(np.arange(50) / 1e4, {"torque": np.zeros(50)}, {"serial": "S"})
    assert split_windows(continuous) == [continuous]


@pytest.mark.slow
def test_chunked_estimator_is_run_jax_with_one_program_for_every_length(monkeypatch):
    from eol_cal.analysis.firmware_angle import firmware_config
    from eol_cal.firmware import estimator as est
    from eol_cal.numerics import exported

    monkeypatch.setattr(exported, "_DIR", None)  # the traced programs counted, none read from a cache

    caps = [synthetic_capture(rpm=rpm, seconds=s, fs=10000.0, seed=k) for k, (rpm, s) in enumerate([(120.0, 0.3),
                                                                                                   (-60.0, 0.53)])]
    cfg = firmware_config(caps[0])
    assert firmware_config(caps[1]) == cfg  # the mean rates differ in their last bits, the config does not
    est._scan_chunk.cache_clear()
    for c in caps:  # 3000 samples: one padded chunk; 5300: a chunk, the state carried, a padded one
        got = est.run_jax_chunked(cfg, c["enc_a"], c["enc_b"], c["hall"])
        ref = est.run_jax(cfg, c["enc_a"], c["enc_b"], c["hall"])
        assert len(got.theta_hat) == len(c.t)
        np.testing.assert_array_equal(got.status, np.asarray(ref.status))
        assert np.abs(np.angle(np.exp(1j * (got.theta_hat - np.asarray(ref.theta_hat))))).max() < 1e-4
        assert got.omega_hat == pytest.approx(np.asarray(ref.omega_hat), rel=1e-5, abs=1e-3)
    assert est._scan_chunk.cache_info().currsize == 1 and est._scan_chunk(cfg)._cache_size() == 1


def test_the_angle_of_a_joined_capture_is_refused_not_guessed(joined: Path):
    from eol_cal.analysis.angle import capture_angle
    from eol_cal.analysis.metrics import capture_ripple_pp
    from eol_cal.capture import read_capture
    from eol_cal.errors import InputError

    cap = read_capture(joined)
    for analysis in (capture_angle, capture_ripple_pp):
        with pytest.raises(InputError) as err:
            analysis(cap)
        assert err.value.field == "segment_starts" and "4 capture windows" in err.value.reason
    assert all(abs(capture_angle(w).speed_rpm) == pytest.approx(120.0, rel=2e-3) for w in split_windows(cap))


def _drop(cap: Capture, keep: np.ndarray) -> Capture:
    return Capture(cap.t[keep], {k: v[keep] for k, v in cap.channels.items()}, dict(cap.metadata), dict(cap.truth),
                   source=cap.source)


def test_a_dropped_sample_is_bridged_a_lost_stretch_is_a_join(monkeypatch):
    from eol_cal.analysis.angle import capture_angle
    from eol_cal.capture.synthetic import synthetic_capture

    cap = synthetic_capture(rpm=120.0, seconds=0.5, seed=3)
    n = len(cap.t)
    # one sample missing, and two missing a little later: a DAQ hiccup, not a join
    keep = np.ones(n, bool)
    keep[[4000, 6001, 6002]] = False
    hiccup = _drop(cap, keep)
    assert window_spans(hiccup) == [(0, n - 3)]
    a_full, a_hic = capture_angle(cap), capture_angle(hiccup)
    assert np.max(np.abs(a_hic.theta_r - a_full.theta_r[keep])) < np.radians(1.0)
    # 40 ms missing at 120 rpm: about 20 quadrature counts, the count is lost: a join
    keep = np.ones(n, bool)
    keep[4000:4800] = False
    lost = _drop(cap, keep)
    assert window_spans(lost) == [(0, 4000), (4000, n - 800)]
    # a short gap across which the encoder moved two counts (ambiguous direction): a join too
    pos = (cap["enc_a"].astype(int), cap["enc_b"].astype(int))
    changes = np.flatnonzero((np.diff(pos[0]) != 0) | (np.diff(pos[1]) != 0))
    c1, c2 = changes[changes > 5000][:2]  # two consecutive count changes
    keep = np.ones(n, bool)
    keep[c1 + 1 : c2 + 1] = False  # the samples of the count between them are gone
    two = _drop(cap, keep)
    assert len(window_spans(two)) == 2
    # ... also where the gap alone would pass for a dropped sample: the two counts decide it
    import eol_cal.capture.windows as windows

    monkeypatch.setattr(windows, "BRIDGE_EDGE_FRACTION", 10.0)
    assert len(window_spans(two)) == 2
    assert window_spans(hiccup) == [(0, n - 3)]
    # without the encoder's B channel nothing can be told: every gap is a join
    no_b = Capture(hiccup.t, {k: v for k, v in hiccup.channels.items() if k != "enc_b"}, dict(hiccup.metadata))
    assert len(window_spans(no_b)) == 3
