import subprocess
import sys

from click.testing import CliRunner

from cli.main import cli
from eol_cal import __version__


def test_version_through_runner():
    result = CliRunner().invoke(cli, ["--version"])
    assert result.exit_code == 0
    assert __version__ in result.output


def test_version_as_subprocess():
    out = subprocess.run([sys.executable, "-m", "cli.main", "--version"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "eol-cal" in out.stdout


def test_tables_in_a_log_are_not_cut_to_80_columns(monkeypatch):
    # a station log or CI output is no terminal: rich's 80 columns cut the fit table's values
    import io

    from cli.common import LOG_WIDTH, _console

    monkeypatch.delenv("COLUMNS", raising=False)
    c = _console(file=io.StringIO())
    assert not c.is_terminal and c.width == LOG_WIDTH >= 120
    monkeypatch.setenv("COLUMNS", "100")
    assert _console(file=io.StringIO()).width == 100  # the user's word wins
