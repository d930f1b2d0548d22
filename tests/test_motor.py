import math

import pytest

from eol_cal.errors import InputError
from eol_cal.domain.motor_params import load_motor


def test_paper_preset_is_table_one():
    m = load_motor("paper")
    assert m.poles == 6 and m.N_enc == 64
    assert m.R_s == pytest.approx(0.023) and m.L_d == pytest.approx(68e-6)
    # kt = 3P/4 psi_f: 65 A gives the paper's 3.2 N*m
    assert m.kt == pytest.approx(0.75 * 6 * 0.0109)
    assert 65 * m.kt == pytest.approx(3.19, abs=0.01)


def test_toml_override(tmp_path):
    f = tmp_path / "m.toml"
    f.write_text("R_s = 0.03\nN_enc = 200\n")
    m = load_motor("paper", f)
    assert m.R_s == 0.03 and m.N_enc == 200 and m.poles == 6


@pytest.mark.parametrize("text,field", [("R_s = -1\n", "R_s"), ("foo = 1\n", "foo"), ("poles = 5\n", "poles"),
                                        ("N_enc = 1.5\n", "N_enc")])
def test_bad_override_names_file_and_field(tmp_path, text, field):
    f = tmp_path / "m.toml"
    f.write_text(text)
    with pytest.raises(InputError) as exc:
        load_motor("paper", f)
    assert str(f) in str(exc.value) and field in str(exc.value)


def test_resistance_temperature():
    m = load_motor()
    assert m.R_s_at(70.0) == m.R_s
    assert m.R_s_at(20.0) == pytest.approx(0.023 * (1 - 0.00393 * 50))
    assert not math.isnan(m.R_s_at(-40))
