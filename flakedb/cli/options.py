"""Checks of command-line options that several commands share (one message, one limit)."""

from flakedb.cli.errors import FlakedbError
from flakedb.paint.checks import MAX_RESOLUTION

#: ``--raw`` of the commands that compose (compose, compare, match).
RAW_HELP = ("With --store: the flakes' spectral factors at their full numerical rank (a version built with "
            "`flakedb build --raw`) instead of the truncated ones.  Without a store the optics are always "
            "computed directly; the flag is recorded.")


def check_node_count(n):
    """Refuse a ``--n`` the solver cannot use (even, 8 ≤ n ≤ MAX_RESOLUTION), before any work."""
    if n is not None and (n < 8 or n % 2 or n > MAX_RESOLUTION):
        raise FlakedbError(f"--n {n}: the node count must be even, 8 ≤ n ≤ {MAX_RESOLUTION} (n/2 nodes per "
                           f"hemisphere), e.g. --n 64")
