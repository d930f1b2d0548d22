"""`eol-cal golden --check DIR` refuses a directory that is no vector set before it computes the
vector sets (a minute of work; from outside the project the default directory is missing)."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from cli.main import cli


@pytest.fixture(autouse=True)
def _no_vectors_computed(monkeypatch):
    """A refusal comes before any vector set is computed: computing one fails these tests."""
    from eol_cal.firmware import golden

    def computed(*args, **kwargs):
        raise AssertionError("the vector sets were computed before the directory was checked")

    monkeypatch.setattr(golden, "vector_sets", computed)


def _refused(args, *words):
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    for w in words:
        assert w in res.output, res.output
    return res.output


def test_a_missing_check_directory_is_refused_at_once(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # outside the project: the default directory is not here
    _refused(["golden", "--check"], "firmware_params/golden", "no such directory", "project's root")
    _refused(["golden", "--check", str(tmp_path / "nope")], str(tmp_path / "nope"), "no such directory")


def test_a_directory_without_a_readable_manifest_is_refused_naming_it(tmp_path):
    (tmp_path / "empty").mkdir()
    _refused(["golden", "--check", str(tmp_path / "empty")], str(tmp_path / "empty" / "manifest.json"))
    (tmp_path / "dir-manifest" / "manifest.json").mkdir(parents=True)
    _refused(["golden", "--check", str(tmp_path / "dir-manifest")], "manifest.json")
