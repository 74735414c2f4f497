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


def test_listed_help_is_each_commands_own():
    """``--help`` lists :data:`SHORT_HELP` without importing the commands: each entry must be the command's own
    summary, or the listing lies (a renamed or re-documented command would keep its old line)."""
    import click

    from flakedb.cli.main import COMMANDS, SHORT_HELP

    ctx = click.Context(cli)
    assert set(SHORT_HELP) == set(COMMANDS)
    for name in COMMANDS:
        assert SHORT_HELP[name] == cli.get_command(ctx, name).get_short_help_str(limit=10**6), name


def test_help_imports_no_command_module():
    """``flakedb --help`` in a fresh process imports neither numpy nor any command module (start-up speed)."""
    code = ("import sys; from flakedb.cli.main import cli\n"
            "try:\n    cli(['--help'])\nexcept SystemExit:\n    pass\n"
            "bad = [m for m in sys.modules if m == 'numpy' or (m.startswith('flakedb.cli.') and m not in "
            "('flakedb.cli', 'flakedb.cli.main', 'flakedb.cli.errors', 'flakedb.cli.failures'))]\n"
            "print('IMPORTED', bad)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0 and "IMPORTED []" in r.stdout, r.stdout + r.stderr
