"""The fault benchmark's scenarios of issue 36's classes 2-4 in the suite: every member
:mod:`eol_cal.sim.fuzz.scenarios_gate` declares (every bad value of every `gate set` option, stored
gate rows and baseline lines that are not what they claim, databases with triggers and views under
every command that opens them, `lot baseline` selections to refuse), not only the ones the class
tests pick. In process, as tests/test_fault_scenarios.py runs issue 23's: exit 2 with one line
starting ``error:``, no traceback, every file of the scenario unchanged.
"""

from __future__ import annotations

import pytest

from eol_cal.sim.fuzz.scenarios_gate import BUILDERS
from test_fault_scenarios import refused_in_process

CASES = [pytest.param(s, id=f"{s.kind}: {s.name}") for kind, build in BUILDERS.items() for s in build({})
         if s.expect == "refuse"]


@pytest.mark.parametrize("scenario", CASES)
def test_every_gate_database_and_baseline_scenario_is_refused_and_changes_nothing(tmp_path, scenario):
    refused_in_process(scenario, tmp_path / "s")


def test_the_scenario_set_covers_the_classes():
    counts = {kind: sum(1 for _ in build({})) for kind, build in BUILDERS.items()}
    assert counts["gate"] >= 50 and counts["database"] >= 60 and counts["baseline"] >= 10, counts
