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
from flakedb.cli.info import info
from flakedb.cli.match import match
from flakedb.cli.render import render
from flakedb.cli.species import species


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="flakedb")
def cli():
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
    cli(prog_name="flakedb")


if __name__ == "__main__":
    main()
