"""The production spread as data (eol_cal/spreads/default.toml, eol_cal.plant.spread): the same
motors as the hard-coded spread drew, seed for seed, and every key of a spread file checked on
load (file, key, reason)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from eol_cal.errors import InputError
from eol_cal.plant.presets import paper
from eol_cal.plant.spread import PARAMETERS, load_spread
from eol_cal.plant.variation import draw_motor

DEFAULT = (Path(__file__).resolve().parent.parent / "eol_cal" / "spreads" / "default.toml").read_text()


def _hard_coded(seed: int):
    """The spread as eol_cal/plant/variation.py drew it before it became a file (commit 5501b57)."""
    from eol_cal.firmware.kinematics import draw_sensor_errors

    base = paper()
    rng = np.random.default_rng(seed)
    u = lambda: float(rng.uniform(0.0, 2.0 * math.pi))  # noqa: E731
    k6 = max(0.0, float(rng.normal(0.00062, 0.15 * 0.00062)))
    spec = base.replace(
        serial=f"SIM-{seed:06d}",
        k6=k6, phase_k6=float(rng.normal(0.0, 0.15)),
        c6=float(rng.uniform(0.002, 0.008)), phase_c6=u(),
        c12=float(rng.uniform(0.004, 0.016)), phase_c12=u(),
        k12=abs(float(rng.normal(0.0, 0.00004))), phase_k12=u(),
        c18=float(rng.uniform(0.0, 0.004)), phase_c18=u(), k18=0.0, phase_k18=0.0,
        unb1=float(rng.rayleigh(0.005)), phase_unb1=u(),
        R_s_scale=float(rng.normal(1.0, 0.03)), temp_degC=float(rng.uniform(20.0, 40.0)),
    )
    err = draw_sensor_errors(rng, base.motor.N_enc)
    return spec.replace(
        enc_edge_err_deg=tuple(float(v) for v in np.degrees(err.edge_error)),
        hall_err_deg=tuple(float(v) for v in np.degrees(np.asarray(err.hall_offset).ravel())),
        grid_offset_deg=float(np.degrees(err.grid_offset)),
    )


def test_the_default_spread_draws_the_hard_coded_motors():
    for seed in list(range(200)) + [10**6, 2**31 - 1]:
        assert draw_motor(seed) == _hard_coded(seed), seed


def test_mech23_adds_orders_2_and_3_to_the_default_motors():
    # issue 34: the orders are drawn after the sensors, so every earlier draw of a seed is kept
    spread = load_spread("mech23")
    for seed in (1, 2, 77):
        a, b = draw_motor(seed), draw_motor(seed, spread=spread)
        assert b.replace(unb2=0.0, phase_unb2=0.0, unb3=0.0, phase_unb3=0.0) == a
        assert 0.002 <= b.unb2 <= 0.004 and 0.002 <= b.unb3 <= 0.004
        assert a.unb2 == a.unb3 == 0.0


def test_a_spread_file_varies_the_motors(tmp_path: Path):
    # the encoder supplier's pitch error doubled: only the pulse placement changes, twice as wide
    doubled = tmp_path / "pitch2x.toml"
    doubled.write_text(DEFAULT.replace("edge_sigma_mech_deg = 0.1", "edge_sigma_mech_deg = 0.2").replace(
        'name = "default"', 'name = "pitch2x"'))
    spread = load_spread(doubled)
    assert spread.name == "pitch2x" and spread.sensors["edge_sigma_mech_deg"] == 0.2
    a, b = draw_motor(5), draw_motor(5, spread=spread)
    # the same draws (the pulses' normal draws scaled), so the rest of the motor is the same motor
    assert a.k6 == b.k6 and a.hall_err_deg == b.hall_err_deg and a.grid_offset_deg == b.grid_offset_deg
    assert np.allclose(np.array(b.enc_edge_err_deg), 2 * np.array(a.enc_edge_err_deg))
    # a parameter left out keeps the base preset's value, and the others are drawn as before
    fewer = tmp_path / "no_k12.toml"
    fewer.write_text(DEFAULT.replace('[k12]            # N*m/A\ndist = "half_normal"\nsigma = 0.00004\n', ""))
    c = draw_motor(5, spread=load_spread(fewer))
    assert c.k12 == paper().k12 and c.k6 == a.k6 and c.c6 == a.c6


@pytest.mark.parametrize("edit, field, words", [
    (("[k6]", "[k7]"), "k7", "unknown spread parameter"),
    (('dist = "rayleigh"', 'dist = "weibull"'), "unb1.dist", "unknown distribution"),
    (("scale = 0.005", "scale = -0.005"), "unb1.scale", ">= 0"),
    (("low = 0.002", "low = 0.009"), "c6.low", "above high"),
    (("sigma_rel = 0.15\nmin = 0.0", "sigma_rel = 0.5"), "k6", "amplitude"),
    (("sigma_rel = 0.15", "sigma_rel = 0.15\nsigma = 0.1"), "k6.sigma", "one of sigma and sigma_rel"),
    (("mean = 1.0\nsigma = 0.03", "mean = 1.0\nsigma = 0.3"), "R_s_scale", "leave the range"),
    (("low = 20.0", 'low = "20"'), "temp_degC.low", "finite number"),
    (("low = 20.0", "low = nan"), "temp_degC.low", "finite number"),
    (("high = 40.0", "high = 40.0\nmode = 30.0"), "temp_degC.mode", "not a key of a uniform"),
    (("[c18]            # N*m\ndist = \"uniform\"\nlow = 0.0\n", "[c18]\ndist = \"uniform\"\n"), "c18.low", "missing"),
    (("hall_max_elec_deg = 2.0", "hall_max_elec_deg = 0.1"), "sensors.hall_max_elec_deg", "at least half"),
    (("edge_sigma_mech_deg = 0.1", "edge_sigma = 0.1"), "sensors.edge_sigma", "unknown sensor key"),
    (('name = "default"', "name = 3"), "name", "must be a string"),
])
def test_every_key_is_checked_on_load(tmp_path: Path, edit, field, words):
    old, new = edit
    assert old in DEFAULT
    path = tmp_path / "bad.toml"
    path.write_text(DEFAULT.replace(old, new, 1))
    with pytest.raises(InputError) as exc:
        load_spread(path)
    assert exc.value.file == str(path) and exc.value.field == field and words in exc.value.reason, exc.value


def test_unknown_names_and_bad_files_are_refused(tmp_path: Path):
    with pytest.raises(InputError, match="unknown spread 'nope'; known: default"):
        load_spread("nope")
    bad = tmp_path / "x.toml"
    bad.write_text("k6 = [")
    with pytest.raises(InputError, match="not valid TOML"):
        load_spread(bad)
    flat = tmp_path / "flat.toml"
    flat.write_text("k6 = 0.0006\n")
    with pytest.raises(InputError) as exc:
        load_spread(flat)
    assert exc.value.field == "k6" and "must be a table" in exc.value.reason
    assert set(load_spread("default").params) == set(PARAMETERS)
