"""Checks of command-line options that several commands share (one message, one limit)."""

import click

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


def prediction_options(fn):
    """``--n``, ``--store``, ``--raw``, ``--catalog``: how ``compare`` and ``match`` compose (one
    definition; the decorated function takes ``n, store, raw, catalog_path`` last)."""
    for opt in reversed([
        click.option("--n", "n", default=None, type=int, help="Node count (even, >= 8); overrides the recipe's."),
        click.option("--store", "store", default=None, envvar="FLAKEDB_STORE",
                     help="Precomputed species store (path or URL; default $FLAKEDB_STORE)."),
        click.option("--raw", is_flag=True, help=RAW_HELP),
        click.option("--catalog", "catalog_path", default=None, type=click.Path(dir_okay=False, exists=True),
                     help="Particle catalogue YAML (default: catalog/particles.yaml or $FLAKEDB_CATALOG)."),
    ]):
        fn = opt(fn)
    return fn
