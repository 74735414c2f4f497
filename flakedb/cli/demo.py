"""`flakedb demo`: run what exists end to end and say plainly what is not built yet.

>>> import tempfile
>>> from pathlib import Path
>>> from click.testing import CliRunner
>>> from flakedb.cli.main import cli
>>> blocked = Path(tempfile.mkdtemp()) / "out"
>>> _ = blocked.write_text("a file, not a directory")
>>> result = CliRunner().invoke(cli, ["demo", "--out", str(blocked)])
>>> result.exit_code, result.output.splitlines()[-1]
(2, "Error: Invalid value for '--out': Directory '.../out' is a file.")
"""

import click

from flakedb.cli.demo_run import run_demo
from flakedb.cli.failures import check_plan
from flakedb.outputs import OutputPlan


@click.command()
@click.option("--out", "out_dir", default="out", show_default=True, type=click.Path(file_okay=False),
              help="Directory for the demo's outputs.")
def demo(out_dir):
    """Run the end-to-end demo with what flakedb can do today."""
    plan = OutputPlan()
    plan.add_dir(out_dir)
    check_plan(plan)   # a writable --out before any work
    run_demo(out_dir)
