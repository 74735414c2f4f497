"""`flakedb build` (the precompute, issue #5) and `flakedb verify STORE`.  Thin: the work is in
flakedb/pipelines/build.py and flakedb/store/versions.py."""

import click

from flakedb.cli.errors import FlakedbError
from flakedb.colour.colorimetry import spectral_grid
from flakedb.paint.checks import MAX_RESOLUTION
from flakedb.pipelines.build import DEFAULT_N, make_request
from flakedb.pipelines.build import build as run_build
from flakedb.store import versions as st

#: Largest φ_d sample count (--m) and uncompressed size of one build [bytes] (64 GiB).
MAX_M = 4096
MAX_BUILD_BYTES = 64 * 1024 ** 3


def check_build_sizes(n, m):
    """Refuse node counts compose cannot use and φ_d counts outside the allowed range, before planning."""
    for x in n:
        if x < 8 or x % 2 or x > MAX_RESOLUTION:
            raise FlakedbError(f"--n {x}: the node count must be even, 8 ≤ n ≤ {MAX_RESOLUTION} (the range compose "
                               f"accepts; n/2 nodes per hemisphere), e.g. --n 32")
    if m is not None and not (2 <= m <= MAX_M):
        raise FlakedbError(f"--m {m}: the φ_d sample count must be in 2 ≤ m ≤ {MAX_M} (default: = n)")


@click.command()
@click.option("--store", default=None, help="store path or fsspec URL [default: $FLAKEDB_STORE or ./flakedb-store]")
@click.option("--workers", type=int, default=None, help="local worker count (threads, or processes with --processes)")
@click.option("--processes", is_flag=True, help="local processes instead of threads")
@click.option("--scheduler", default=None, help="address of a dask.distributed scheduler, e.g. tcp://host:8786")
@click.option("--dry-run", is_flag=True, help="print what would be built and its size, build nothing")
@click.option("--n", "n", type=int, multiple=True, help="μ node count (even); repeat for several resolutions [32]")
@click.option("--m", "m", type=int, default=None, help="φ_d samples on [0, π] [default: = n]")
@click.option("--rank", type=int, default=8, show_default=True, help="rank r of the √R SVD")
@click.option("--species", "species", multiple=True, help="species name (repeatable) [default: the whole catalogue]")
@click.option("--range-nm", type=float, nargs=2, default=(400.0, 700.0), show_default=True,
              help="first and last wavelength (nm) of the bands")
@click.option("--step-nm", type=float, default=20.0, show_default=True, help="wavelength step (nm)")
@click.option("--eta-top", default="1.5", show_default=True,
              help="relative index of the paints' smooth top (clear-coat) interface: the μ grid is the solver's "
                   "node set inside the binder below it and the optics use it as the binder index; 1 = no "
                   "interface / index-matched; 'none' = plain Radau nodes with the catalogue binder's index")
@click.option("--raw", is_flag=True, help="also store the raw R samples (compose --raw needs them)")
def build(store, workers, processes, scheduler, dry_run, n, m, rank, species, range_nm, step_nm, eta_top, raw):
    """Build (or reuse) the compressed reflectance store and point `latest` at it."""
    url = store or st.default_store()
    check_build_sizes(n or DEFAULT_N, m)
    if str(eta_top).strip().lower() in ("none", "null"):
        eta = None
    else:
        try:
            eta = float(eta_top)
        except ValueError:
            raise FlakedbError(f"--eta-top {eta_top}: give a number ≥ 1 (e.g. 1.5) or 'none'") from None
    try:
        req = make_request(species=species or None, n=n or DEFAULT_N, m=m, rank=rank,
                           wavelength_nm=spectral_grid(tuple(range_nm), step_nm), store_raw=raw, eta_top=eta)
        plan = st.plan_build(req)
    except ValueError as exc:
        raise FlakedbError(str(exc)) from exc
    if plan.nbytes() > MAX_BUILD_BYTES:
        raise FlakedbError(f"the build would hold {plan.nbytes() / 2**30:,.1f} GiB uncompressed; the limit is "
                           f"{MAX_BUILD_BYTES / 2**30:.0f} GiB (hint: fewer --species, a smaller --n or --m, or "
                           f"no --raw)")
    if dry_run:
        click.echo(f"store {url}: version state {st.version_state(url, plan.version)}")
        click.echo(plan.describe())
        return
    local = None if scheduler else ("processes" if processes else "threads")
    res = run_build(req, url, scheduler=scheduler or local, workers=workers, progress=True)
    click.echo(f"{res['status']}: version {res['version']} in {res['store']} "
               f"({res['tasks_run']} of {res['tasks_total']} tasks run, {res['seconds']:.1f} s)")


@click.command()
@click.argument("store", required=False)
@click.option("--all", "all_versions", is_flag=True, help="check every version, not only `latest`")
def verify(store, all_versions):
    """Check a store: completeness, schema, every chunk's sha256.  Exit 1 listing the problems."""
    url = store or st.default_store()
    problems = st.verify_store(url, all_versions=all_versions)
    if problems:
        for p in problems:
            click.echo(p, err=True)
        click.echo(f"{url}: {len(problems)} problem(s)", err=True)
        raise SystemExit(1)
    click.echo(f"{url}: OK (latest = {st.read_latest(url)})")
