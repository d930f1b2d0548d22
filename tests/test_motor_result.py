"""MotorResult: the round trip of real ``eol-cal fit`` output, its JSON Schema, and the refusals of bad values."""

from __future__ import annotations

import json

import jsonschema
import pytest
from click.testing import CliRunner

from cli.main import cli
from eol_cal.analysis.motor_result import MotorResult
from eol_cal.capture.io import write_capture
from eol_cal.capture.synthetic import synthetic_capture
from eol_cal.errors import ResultFormatError
from eol_cal.schemas import load_schema

POINTS = [(120.0, 20.0), (120.0, 65.0), (240.0, 20.0), (240.0, 65.0), (-120.0, -20.0), (-120.0, -65.0)]
TRUTH = dict(k6=0.00062, phase_k6=0.3, c6=0.004, phase_c6=1.1)


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """Real fit output: one usable result and one that did not converge."""
    d = tmp_path_factory.mktemp("motor_result")
    files = []
    for i, (rpm, iq) in enumerate(POINTS):
        p = d / f"c{i}.csv"
        write_capture(synthetic_capture(rpm=rpm, i_qo=iq, seconds=0.35, seed=i, theta_r0=0.7 * i, serial="M-0007", **TRUTH), p)
        files.append(str(p))
    ok, bad = d / "ok.json", d / "not_converged.json"
    assert CliRunner().invoke(cli, ["fit", *files, "-o", str(ok), "--bench", "none"]).exit_code == 0
    assert CliRunner().invoke(cli, ["fit", *files, "-o", str(bad), "--bench", "none", "--max-steps", "1"]).exit_code == 1
    return ok, bad


def test_round_trip_is_identical(results):
    for path in results:
        text = path.read_text()
        doc = json.loads(text)
        again = dict(doc, motors=[MotorResult.from_json(m, str(path)).to_json() for m in doc["motors"]])
        assert json.dumps(again, indent=2, allow_nan=False) + "\n" == text


def test_real_fit_output_matches_its_schema(results):
    schema = load_schema("fit-result")
    jsonschema.Draft202012Validator.check_schema(schema)
    for path in results:
        jsonschema.validate(json.loads(path.read_text()), schema)
    # and the schema is not vacuous: the refusals below are refused by it too
    doc = json.loads(results[0].read_text())
    doc["motors"][0]["k6"]["value"] = -5
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(doc, schema)


@pytest.mark.parametrize(("field", "value", "reason"), [
    ("k6", True, "got a boolean"),
    ("k6", "0.0006", "got a string"),
    ("k6", -5, "outside the physical bounds"),
    ("c6", 1e30, "outside the physical bounds"),
    ("k6.value", -5, "outside the physical bounds"),
    ("c6.value", 1e30, "outside the physical bounds"),
    ("k6.value", float("nan"), "not a finite number"),
    ("delay_s.ci95", float("inf"), "not a finite number"),
    ("kt", None, "got null"),
    ("k6", "<missing>", "missing"),
    ("operating_point.speed_rpm", "<missing>", "missing"),
])
def test_table_refuses_a_bad_value_with_file_and_field(results, tmp_path, field, value, reason):
    doc = json.loads(results[0].read_text())
    *parents, key = field.split(".")
    target = doc["motors"][0]
    for p in parents:
        target = target[p]
    if value == "<missing>":
        del target[key]
    else:
        target[key] = value
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))  # NaN/Infinity as Python's json writes them: what a hand edit could leave
    out = tmp_path / "b.bin"
    res = CliRunner().invoke(cli, ["table", str(bad), "-o", str(out)])
    assert res.exit_code == 2, res.output
    assert str(bad) in res.stderr and f"motors[0].{field}" in res.stderr and reason in res.stderr
    assert not out.exists()
    with pytest.raises(ValueError):  # ResultFormatError is a ValueError too
        MotorResult.from_json(doc["motors"][0], str(bad))


def test_unusable_result_must_not_carry_estimates(results):
    m = json.loads(results[1].read_text())["motors"][0]
    assert MotorResult.from_json(m).estimates is None
    m["k6"] = {"value": 0.0006, "ci95": 0.0}
    with pytest.raises(ResultFormatError, match="must be null"):
        MotorResult.from_json(m, "r.json")


def test_real_json_outputs_of_the_commands_match_their_schemas(results, tmp_path):
    """fit result, table --json, block show --json and analyze --json against eol_cal/schemas/."""
    from eol_cal.schemas import validator

    ok, _ = results
    block = tmp_path / "b.bin"
    docs = {"fit-result": [json.loads(ok.read_text())]}
    for name, args in (("block", ["table", str(ok), "-o", str(block), "--json"]),
                       ("block", ["block", "show", str(block), "--json"]),
                       ("analyze", ["analyze", str(ok.parent / "c1.csv"), str(ok.parent / "c3.csv"), "--json"])):
        res = CliRunner().invoke(cli, args)
        assert res.exit_code in (0, 2), res.output
        docs.setdefault(name, []).append(json.loads(res.stdout))
    for name, found in docs.items():
        check = validator(name)
        for doc in found:
            check.validate(doc)
    # a refusal is a refusal: a table document without its block does not pass
    with pytest.raises(jsonschema.ValidationError):
        validator("block").validate({"file": "b.bin", "bytes": 2152})
