"""The command line's user-facing error: printed as one line without a traceback, exit status 2."""

import click


class FlakedbError(click.ClickException):
    """A user-facing error: printed without a traceback, exit status 2."""

    exit_code = 2
