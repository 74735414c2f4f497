"""flakedb's command line (click).  Commands are thin: they import the core inside the function.

Each command lives in its own module under ``flakedb/commands/`` and is registered below.
"""

import click

from flakedb import __version__


class FlakedbError(click.ClickException):
    """A user-facing error: printed without a traceback, exit status 2."""

    exit_code = 2


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="flakedb")
def cli():
    """flakedb: predict a car paint's BSDF from what is in it."""


# --- command registration (one line per command module) ---------------------------------------
from flakedb.commands.build import build, verify  # noqa: E402
from flakedb.commands.compare import compare  # noqa: E402
from flakedb.commands.compose import compose  # noqa: E402
from flakedb.commands.demo import demo  # noqa: E402
from flakedb.commands.export import export_mitsuba  # noqa: E402
from flakedb.commands.info import info  # noqa: E402
from flakedb.commands.match import match  # noqa: E402
from flakedb.commands.render import render  # noqa: E402
from flakedb.commands.species import species  # noqa: E402

cli.add_command(build)
cli.add_command(verify)
cli.add_command(compare)
cli.add_command(compose)
cli.add_command(demo)
cli.add_command(export_mitsuba)
cli.add_command(info)
cli.add_command(match)
cli.add_command(render)
cli.add_command(species)
# --- end of command registration --------------------------------------------------------------


def main():
    cli(prog_name="flakedb")


if __name__ == "__main__":
    main()
