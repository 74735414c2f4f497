"""The command line: guards against a broken entry point (`flakedb`, `python -m flakedb`)."""

import subprocess
import sys

from click.testing import CliRunner

from flakedb import __version__
from flakedb.cli.main import cli


def test_version_and_help():
    r = CliRunner().invoke(cli, ["--version"])
    assert r.exit_code == 0 and __version__ in r.output
    r = CliRunner().invoke(cli, ["--help"])
    assert r.exit_code == 0 and "demo" in r.output


def test_python_dash_m():
    r = subprocess.run([sys.executable, "-m", "flakedb", "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and __version__ in r.stdout
