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
