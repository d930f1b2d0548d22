"""The master-motor gate's pure rules: the settings, the master check, when the check is due."""

from __future__ import annotations

import datetime as dt

import pytest

from eol_cal.errors import InputError
from eol_cal.msa.master import MasterRun, check_master, master_due, master_settings, shift_start

UTC = dt.UTC
BASE = {"master.serial": "MASTER-1", "master.reference.k6": 0.640, "master.tolerance.k6": 0.03,
        "master.reference.phase_k6": 179.0, "master.tolerance.phase_k6": 2.0, "master.every_h": 8.0}


def t(h: float, day: int = 23) -> dt.datetime:
    return dt.datetime(2026, 11, day, tzinfo=UTC) + dt.timedelta(hours=h)


def test_master_settings_and_their_refusals():
    m = master_settings(BASE, "station.toml")
    assert m.serial == "MASTER-1" and m.reference == {"k6": 0.640, "phase_k6": 179.0} and m.every_h == 8.0
    assert master_settings({"master.serial": None}, "s.toml") is None
    for values, key in (({**BASE, "master.tolerance.k6": None}, "master.tolerance.k6"),
                        ({**BASE, "master.tolerance.c6": 0.1}, "master.reference.c6"),
                        ({**BASE, "master.tolerance.k6": 0.0}, "master.tolerance.k6"),
                        ({**BASE, "master.every_h": None}, "master.every_h"),
                        ({**BASE, "master.shifts": "06:00"}, "master.every_h"),
                        ({**BASE, "master.every_h": None, "master.shifts": "6 o'clock"}, "master.shifts"),
                        ({**BASE, "master.timezone": "Mars/Olympus"}, "master.timezone"),
                        ({"master.reference.k6": 0.64}, "master.reference.k6")):
        with pytest.raises(InputError) as exc:
            master_settings(values, "station.toml")
        assert exc.value.field == key and exc.value.file == "station.toml"


def test_master_check_within_tolerance_and_on_the_circle():
    m = master_settings(BASE, "s")
    assert check_master({"k6": 0.655, "phase_k6": -179.5}, m) == (True, [])  # -179.5 deg is 1.5 deg from 179
    ok, reasons = check_master({"k6": 0.680, "phase_k6": 175.0}, m)
    assert not ok and len(reasons) == 2
    assert reasons[0] == "master k6 = 0.68 mN*m/A deviates +0.04 from its reference 0.64 (tolerance +-0.03)"
    assert check_master({"k6": 0.64}, m) == (False, ["master phase_k6: not measured"])


def test_master_due_every_n_hours():
    m = master_settings(BASE, "s")
    assert master_due(t(9), None, m).startswith("master check due: no run of the master MASTER-1")
    assert master_due(t(9), MasterRun(t(2), True), m) is None  # 7 h ago
    assert "9.0 h ago" in master_due(t(11), MasterRun(t(2), True), m)
    failed = master_due(t(3), MasterRun(t(2), False, verdict="fail"), m)
    assert failed.startswith("master check failed") and "(2026-11-23 02:00:00 UTC, fail)" in failed


def test_master_due_per_shift_in_the_plant_time_zone():
    m = master_settings({**BASE, "master.every_h": None, "master.shifts": "22:00,06:00,14:00",
                         "master.timezone": "Europe/Berlin"}, "s")
    # 2026-11-23 is CET (UTC+1): the 14:00 shift began at 13:00 UTC, the 06:00 one at 05:00 UTC
    assert shift_start(t(13.5), m) == t(13)
    assert shift_start(t(2), m) == t(21, day=22)  # 03:00 local: yesterday's night shift
    assert master_due(t(13.5), MasterRun(t(13.2), True), m) is None
    due = master_due(t(13.5), MasterRun(t(12), True), m)
    assert due.startswith("master check due: no passing run of MASTER-1 since the shift began (2026-11-23 14:00 CET")
