"""flakedb's command line (click): the group and its registration.

Each command lives in its own module of ``flakedb/cli/`` (one module per command) and is registered
below; the user-facing error type is :class:`flakedb.cli.errors.FlakedbError`.
"""

import click

from flakedb import __version__
from flakedb.cli.build import build, verify
from flakedb.cli.compare import compare
from flakedb.cli.compose import compose
from flakedb.cli.demo import demo
from flakedb.cli.errors import FlakedbError  # noqa: F401  (re-exported for scripts)
from flakedb.cli.export_mitsuba import export_mitsuba
from flakedb.cli.failures import as_failure
from flakedb.cli.info import info
from flakedb.cli.match import match
from flakedb.cli.render import render
from flakedb.cli.species import species
from flakedb.process import tune_allocator


class FlakedbGroup(click.Group):
    """The group: an unexpected exception in a command becomes one line and exit status 1
    (:func:`flakedb.cli.failures.as_failure`) unless ``--debug`` asks for the traceback."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort,
                KeyboardInterrupt, SystemExit):
            raise
        except Exception as exc:
            if ctx.params.get("debug"):
                raise
            raise as_failure(exc) from exc


@click.group(cls=FlakedbGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="flakedb")
@click.option("--debug", is_flag=True, help="Show the traceback of an unexpected error instead of one line.")
def cli(debug):
    """flakedb: predict a car paint's BSDF from what is in it."""


cli.add_command(build)
cli.add_command(compare)
cli.add_command(verify)
cli.add_command(compose)
cli.add_command(demo)
cli.add_command(export_mitsuba)
cli.add_command(info)
cli.add_command(match)
cli.add_command(render)
cli.add_command(species)


def main():
    tune_allocator()  # freed memory kept for reuse: page faults are most of a short solve's overhead
    cli(prog_name="flakedb")


if __name__ == "__main__":
    main()
