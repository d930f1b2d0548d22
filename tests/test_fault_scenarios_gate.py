"""The fault benchmark's scenarios of issue 36's classes 2-4 in the suite: every member
:mod:`eol_cal.fuzz.scenarios_gate` declares (every bad value of every `gate set` option, stored
gate rows and baseline lines that are not what they claim, databases with triggers and views under
every command that opens them, `lot baseline` selections to refuse), not only the ones the class
tests pick. In process, as tests/test_fault_scenarios.py runs issue 23's: exit 2 with one line
starting ``error:``, no traceback, every file of the scenario unchanged.
"""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.fuzz.scenarios_gate import BUILDERS
from test_fault_scenarios import _env

CASES = [pytest.param(s, id=f"{s.kind}: {s.name}") for kind, build in BUILDERS.items() for s in build({})
         if s.expect == "refuse"]


@pytest.mark.parametrize("scenario", CASES)
def test_every_gate_database_and_baseline_scenario_is_refused_and_changes_nothing(tmp_path, scenario):
    d = tmp_path / "s"
    scenario.lay_out(d)
    before = scenario.digests(d)
    res = CliRunner().invoke(cli, scenario.argv(d), input=scenario.stdin or None, env=_env(scenario.env))
    assert "Traceback" not in res.output, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert res.exit_code == 2, res.output
    assert res.stderr.strip().splitlines()[-1].startswith("error:"), res.output
    assert scenario.digests(d) == before


def test_the_scenario_set_covers_the_classes():
    counts = {kind: sum(1 for _ in build({})) for kind, build in BUILDERS.items()}
    assert counts["gate"] >= 50 and counts["database"] >= 60 and counts["baseline"] >= 10, counts
