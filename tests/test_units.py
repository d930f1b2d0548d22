"""One display unit per quantity (eol_cal.rendering.display): each factor is pint's, and the places people
read a k6 (report, lot page, lot diff, CSV, tables) show it in mN*m/A."""

from __future__ import annotations

import pytest

from eol_cal.capture.units import unit_registry
from eol_cal.rendering.display import DISPLAY, display_unit, to_display


@pytest.mark.parametrize("stored", sorted(DISPLAY))
def test_each_display_factor_is_pints(stored):
    shown, factor = DISPLAY[stored]
    assert unit_registry().Quantity(1.0, stored).to(shown).magnitude == pytest.approx(factor, rel=1e-12)


def test_units_without_a_display_unit_are_shown_as_stored():
    assert display_unit("%") == ("%", 1.0) and to_display(2.5, "%") == 2.5
    assert to_display(1.2e-3, "N*m/A") == pytest.approx(1.2) and to_display(None, "N*m/A") != to_display(None, "N*m/A")


def test_a_database_url_is_shown_as_typed_with_its_password_masked():
    from eol_cal.records.connect import db_label, db_shown

    assert db_label("postgresql://eolcal:s3cret@db.plant:5432/eol") == "postgresql://eolcal:***@db.plant:5432/eol"
    assert db_shown("/var/lib/eol/results.sqlite") == "/var/lib/eol/results.sqlite"
    assert db_label("postgres://eolcal@127.0.0.1:5432/eol") == "postgres://eolcal@127.0.0.1:5432/eol"
    assert db_label("/var/lib/eol/results.sqlite") == "results.sqlite"
