"""Checks of command-line options that several commands share (one message, one limit)."""

import click

from flakedb.cli.errors import FlakedbError
from flakedb.paint.limits import NODE_COUNT_MAX, NODE_COUNT_MIN, node_count_problem

#: ``--raw`` of the commands that compose (compose, compare, match).
RAW_HELP = ("With --store: the flakes' spectral factors at their full numerical rank (a version built with "
            "`flakedb build --raw`) instead of the truncated ones.  Without a store the optics are always "
            "computed directly; the flag is recorded.")


def check_node_count(n):
    """Refuse a ``--n`` the solver cannot use (:func:`flakedb.paint.limits.node_count_problem`), before any work.

    >>> check_node_count(None), check_node_count(64)
    (None, None)
    >>> check_node_count(7)
    Traceback (most recent call last):
    ...
    flakedb.cli.errors.FlakedbError: --n 7: the node count must be even, 8 ≤ n ≤ 512 (n/2 nodes per hemisphere), e.g. 64
    """
    problem = None if n is None else node_count_problem(n)
    if problem:
        raise FlakedbError(f"--n {problem}")


def prediction_options(fn):
    """``--n``, ``--store``, ``--raw``, ``--catalog``: how ``compare`` and ``match`` compose (one
    definition; the decorated function takes ``n, store, raw, catalog_path`` last)."""
    for opt in reversed([
        click.option("--n", "n", default=None, type=int, help=f"Node count (even, {NODE_COUNT_MIN}-{NODE_COUNT_MAX}); overrides the recipe's."),
        click.option("--store", "store", default=None, envvar="FLAKEDB_STORE",
                     help="Precomputed species store (path or URL; default $FLAKEDB_STORE)."),
        click.option("--raw", is_flag=True, help=RAW_HELP),
        click.option("--catalog", "catalog_path", default=None, type=click.Path(dir_okay=False, exists=True),
                     help="Particle catalogue YAML (default: catalog/particles.yaml or $FLAKEDB_CATALOG)."),
    ]):
        fn = opt(fn)
    return fn
