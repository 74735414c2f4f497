"""The command line's user-facing error: printed as one line without a traceback, exit status 2."""

import click


class FlakedbError(click.ClickException):
    """A user-facing error: printed without a traceback, exit status 2.

    >>> from click.testing import CliRunner
    >>> @click.command()
    ... def paint():
    ...     raise FlakedbError("--n 33: the node count must be even")
    >>> result = CliRunner().invoke(paint, [])
    >>> result.exit_code, result.output.splitlines()
    (2, ['Error: --n 33: the node count must be even'])
    """

    exit_code = 2
