"""`flakedb demo`: run what exists end to end and say plainly what is not built yet."""

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
