"""The fault benchmark's targeted scenarios of classes 1, 6 and 7 (issue 23) in the suite:
every member the benchmark tries (:mod:`eol_cal.sim.fuzz.scenarios`: an output over an input through
every writing option and setting, settings values, serials, mechanical parts, limit rows and
ECU states that must be refused, refit's bad input), not only the ones the class tests pick.

In process (``CliRunner``), so the whole set costs seconds: each must end exit 2 with one line
starting ``error:``, no traceback, every file of the scenario unchanged, and no new file where an
output would have gone over an input. ``bench/bench_faults.py --section scenarios`` runs the same
set in child processes with a time and memory bound.
"""

from __future__ import annotations

import os

import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.sim import fuzz
from eol_cal.sim.fuzz import scenarios as S

BASES = fuzz.base_files()
CASES = [pytest.param(s, id=f"{s.kind}: {s.name}") for kind in ("paths", "refusals", "exits")
         for s in S.BUILDERS[kind](BASES) if s.expect == "refuse"]


def _env(extra: dict[str, str]) -> dict[str, str | None]:
    env: dict[str, str | None] = {k: None for k in os.environ if k.startswith("EOL_CAL_") and k != "EOL_CAL_JAX_CACHE"}
    env.update(extra)
    return env


def refused_in_process(scenario, d, first_words: tuple[str, ...] = ("error:",)) -> None:
    """Run ``scenario`` laid out in ``d`` through the CLI in process: it must end exit 2 with one
    line starting with ``first_words``, no traceback, every file of the scenario unchanged."""
    scenario.lay_out(d)
    before = scenario.digests(d)
    res = CliRunner().invoke(cli, scenario.argv(d), input=scenario.stdin or None, env=_env(scenario.env))
    assert "Traceback" not in res.output, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert res.exit_code == 2, res.output
    assert res.stderr.strip().splitlines()[-1].startswith(first_words), res.output
    assert scenario.digests(d) == before


@pytest.mark.parametrize("scenario", CASES)
def test_every_scenario_that_must_be_refused_is_refused_and_changes_nothing(tmp_path, scenario):
    refused_in_process(scenario, tmp_path / "s")


def test_the_scenario_set_covers_the_classes():
    """Each kind holds several members: a class is tried by more than its example."""
    counts = {kind: sum(1 for _ in S.BUILDERS[kind](BASES)) for kind in ("paths", "refusals", "exits")}
    assert counts["paths"] >= 20 and counts["refusals"] >= 40 and counts["exits"] >= 5, counts
    assert any("station --lot" in s.name for s in S.BUILDERS["paths"](BASES))
    assert any("--log-file" in s.name for s in S.BUILDERS["paths"](BASES))



# issue 36: the dbfiles (class 1) and round3 (class 9) scenarios, in process as above (the oemkey,
# signals and dynoclear ones need child processes and time bounds: bench/bench_faults.py runs them)
from eol_cal.sim.fuzz import scenarios_harden as H  # noqa: E402 - the second part of this module

CASES_36 = [pytest.param(s, id=f"{s.kind}: {s.name}") for kind in ("dbfiles", "round3")
            for s in H.BUILDERS[kind](BASES) if s.expect == "refuse"]


@pytest.mark.slow  # 120 commands in process: a minute
@pytest.mark.parametrize("scenario", CASES_36)
def test_every_issue_36_scenario_that_must_be_refused_is_refused_and_changes_nothing(tmp_path, scenario, monkeypatch):
    d = tmp_path / "s"
    d.mkdir()
    monkeypatch.chdir(d)  # a command that writes where it runs writes into the scenario
    refused_in_process(scenario, d, ("error:", "Error:"))  # click's usage error is a refusal too


def test_the_issue_36_scenarios_cover_every_class_with_several_members():
    counts = {kind: sum(1 for _ in build(BASES)) for kind, build in H.BUILDERS.items()}
    assert sum(counts.values()) >= 300 and min(counts.values()) >= 10, counts
    assert set(S.all_builders()) >= set(H.BUILDERS) | set(S.BUILDERS)
