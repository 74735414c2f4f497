"""flakedb's command line (click): the group and its registration.

Each command lives in its own module of ``flakedb/cli/`` (one module per command) and is registered
below; the user-facing error type is :class:`flakedb.cli.errors.FlakedbError`.
"""

import importlib

import click

from flakedb import __version__
from flakedb.cli.errors import FlakedbError  # noqa: F401  (re-exported for scripts)
from flakedb.cli.failures import as_failure
from flakedb.process import Terminated, install_signal_handlers, tune_allocator

#: Every command and the module that defines it, imported only when that command runs or its help is
#: shown (click's lazily loaded subcommands): ``flakedb compose`` no longer imports Dask, distributed,
#: matplotlib and the build pipeline of ``flakedb build`` (measured: 1.2 s of imports for any command
#: before, docs/store.md "Timings").
COMMANDS = {
    "build": "flakedb.cli.build:build",
    "compare": "flakedb.cli.compare:compare",
    "compose": "flakedb.cli.compose:compose",
    "demo": "flakedb.cli.demo:demo",
    "export-mitsuba": "flakedb.cli.export_mitsuba:export_mitsuba",
    "info": "flakedb.cli.info:info",
    "match": "flakedb.cli.match:match",
    "render": "flakedb.cli.render:render",
    "species": "flakedb.cli.species:species",
    "verify": "flakedb.cli.build:verify",
}


class FlakedbGroup(click.Group):
    """The group: commands loaded on first use (:data:`COMMANDS`); an unexpected exception in a command
    becomes one line and exit status 1 (:func:`flakedb.cli.failures.as_failure`) unless ``--debug``
    asks for the traceback."""

    def list_commands(self, ctx):
        return sorted(COMMANDS)

    def get_command(self, ctx, name):
        target = COMMANDS.get(name)
        if target is None:
            return None
        module, attr = target.split(":")
        return getattr(importlib.import_module(module), attr)

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except Terminated as exc:  # SIGTERM / SIGHUP: the command's clean-up has run, as for Ctrl-C
            click.echo(f"flakedb: {exc}; stopped, temporary files removed, no partial outputs left", err=True)
            raise SystemExit(128 + exc.signum) from None
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


def main():
    tune_allocator()  # freed memory kept for reuse: page faults are most of a short solve's overhead
    install_signal_handlers()  # SIGTERM / SIGHUP clean up as SIGINT does (flakedb.process.Terminated)
    cli(prog_name="flakedb")


if __name__ == "__main__":
    main()
