"""Test profiles: built-ins, tick arrays, and refusal of bad profile files."""

import numpy as np
import pytest

from eol_cal.errors import InputError
from eol_cal.plant.profile import builtin_profiles, constant, load_profile, parse_profile

KT = 0.75 * 6 * 0.0109


def test_builtins_load():
    names = builtin_profiles()
    assert {"eol-default", "paper", "paper-ramp"} <= set(names)
    for name in names:
        prof = load_profile(name)
        assert prof.name == name
        assert prof.seconds > 0


def test_eol_default_is_fit_ready():
    prof = load_profile("eol-default")
    speeds = {abs(s.speed_rpm) for s in prof.segments}
    loads = {abs(s.i_qo(KT)) for s in prof.segments}
    assert len(speeds) >= 2
    assert len(loads) >= 3
    assert any(s.speed_rpm > 0 for s in prof.segments) and any(s.speed_rpm < 0 for s in prof.segments)


def test_ticks_hold_and_ramp():
    text = """
name = "t"
[[segment]]
speed_rpm = 60.0
iq = 10.0
seconds = 0.5
[[segment]]
speed_rpm = 120.0
torque_nm = 1.0
seconds = 0.5
ramp_s = 0.25
"""
    prof = parse_profile(text, "t.toml")
    speed, iq = prof.ticks(1000.0, KT)
    assert speed.shape == iq.shape == (1000,)
    assert np.all(speed[:500] == 60.0) and np.all(iq[:500] == 10.0)
    ramp = speed[500:750]
    assert np.all(np.diff(ramp) > 0) and ramp[-1] == pytest.approx(120.0)
    assert np.all(speed[750:] == 120.0)
    assert iq[-1] == pytest.approx(1.0 / KT)
    assert prof.segment_bounds(1000.0) == [(0, 500), (500, 1000)]


def test_constant_profile():
    prof = constant(-30.0, 2.0, torque_nm=-1.5)
    speed, iq = prof.ticks(20000.0, KT)
    assert len(speed) == 40000 and speed[0] == -30.0
    assert iq[0] == pytest.approx(-1.5 / KT)


@pytest.mark.parametrize(
    "body, field, words",
    [
        ("[[segment]]\nspeed_rpm = 60.0\niq = 1.0\n", "segment[0].seconds", "missing"),
        ("[[segment]]\nspeed_rpm = 60.0\niq = 1.0\ntorque_nm = 1.0\nseconds = 1.0\n", "segment[0].iq", "exactly one"),
        ("[[segment]]\nspeed_rpm = 60.0\niq = 1.0\nseconds = -1.0\n", "segment[0].seconds", "outside"),
        ("[[segment]]\nspeed_rpm = 60.0\niq = 1.0\nseconds = 1.0\nramp_s = 2.0\n", "segment[0].ramp_s", "longer"),
        ("[[segment]]\nspeed_rpm = 'fast'\niq = 1.0\nseconds = 1.0\n", "segment[0].speed_rpm", "finite number"),
        ("[[segment]]\nspeed_rpm = 60.0\niq = 1.0\nseconds = 1.0\nsped = 3\n", "segment[0].sped", "unknown key"),
        ("name = 'x'\n", "segment", "at least one"),
        ("[[segment]\nspeed_rpm = 60.0\n", None, "not valid TOML"),
    ],
)
def test_bad_profile_file_refused(tmp_path, body, field, words):
    path = tmp_path / "bad.toml"
    path.write_text(body)
    with pytest.raises(InputError) as info:
        load_profile(str(path))
    err = info.value
    assert err.file == str(path)
    assert err.field == field
    assert words in err.reason


def test_unknown_profile_name():
    with pytest.raises(InputError) as info:
        load_profile("no-such-profile")
    assert "eol-default" in info.value.reason
