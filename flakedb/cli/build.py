"""`flakedb build` (the precompute, issue #5) and `flakedb verify STORE`.  Thin: the work is in
flakedb/pipelines/build.py and flakedb/store/versions.py."""

import math
from pathlib import Path

import click

from flakedb.cli.errors import FlakedbError
from flakedb.colour.colorimetry import spectral_grid
from flakedb.paint.catalog import CatalogError, load_catalog
from flakedb.paint.limits import node_count_problem
from flakedb.paint.recipe import RecipeError, load_recipe
from flakedb.pipelines.build import DEFAULT_N, make_request, request_for_recipe
from flakedb.rt.scattering.microflake import FLAKE_ALPHA_RANGE
from flakedb.pipelines.build import build as run_build
from flakedb.store import versions as st

#: Largest φ_d sample count (--m) and uncompressed size of one build [bytes] (64 GiB).
MAX_M = 4096
MAX_BUILD_BYTES = 64 * 1024 ** 3


#: Band spacing [nm] and range of a build: finer than 1 nm is below the CIE tables' resolution (and multiplies
#: every array); up to the whole 360-780 nm range (coarse grids serve quick tests), the CIE x D65 tables'
#: common domain.
STEP_NM_RANGE = (1.0, 420.0)
RANGE_NM_LIMITS = (360.0, 780.0)


def check_spectral_options(range_nm, step_nm):
    """Refuse a --range-nm / --step-nm outside the recipe's limits (with their reason), before planning."""
    lo, hi = STEP_NM_RANGE
    if not (math.isfinite(step_nm) and lo <= step_nm <= hi):
        raise FlakedbError(f"--step-nm {step_nm:g}: the band spacing must be in {lo:g} ≤ step ≤ {hi:g} nm (finer than "
                           f"1 nm is below the CIE tables' resolution and multiplies every stored array), e.g. "
                           f"--step-nm 5")
    a, b = range_nm
    if not (all(math.isfinite(x) for x in range_nm) and RANGE_NM_LIMITS[0] <= a < b <= RANGE_NM_LIMITS[1]):
        raise FlakedbError(f"--range-nm {a:g} {b:g}: first < last, both in {RANGE_NM_LIMITS[0]:g}-"
                           f"{RANGE_NM_LIMITS[1]:g} nm (the CIE x D65 tables' common domain), e.g. --range-nm 380 780")


def check_store_dir(url):
    """Refuse to build into an existing local directory that is not a flakedb store (it would get a
    ``latest`` file and a ``versions/`` directory among the user's own files, and ``latest`` may be
    theirs)."""
    if "://" in str(url):
        return
    p = Path(url)
    if p.exists() and not p.is_dir():
        raise FlakedbError(f"--store {url}: exists and is not a directory (hint: choose a store directory)")
    if p.is_dir() and any(p.iterdir()) and not (p / "versions").is_dir() and not (p / "latest").is_file():
        raise FlakedbError(f"--store {url}: an existing directory that is not a flakedb store (no versions/ or "
                           f"latest); nothing was written (hint: choose a new or empty directory)")


def check_build_sizes(n, m):
    """Refuse node counts compose cannot use and φ_d counts outside the allowed range, before planning.

    >>> check_build_sizes((32, 64), None)
    >>> check_build_sizes((32, 33), None)
    Traceback (most recent call last):
    ...
    flakedb.cli.errors.FlakedbError: --n 33: the node count must be even, 8 ≤ n ≤ 512 (n/2 nodes per hemisphere), e.g. 64 (the range compose accepts)
    """
    for x in n:
        problem = node_count_problem(x)
        if problem:
            raise FlakedbError(f"--n {problem} (the range compose accepts)")
    if m is not None and not (2 <= m <= MAX_M):
        raise FlakedbError(f"--m {m}: the φ_d sample count must be in 2 ≤ m ≤ {MAX_M} (default: = n)")


@click.command()
@click.option("--store", default=None, help="store path or fsspec URL [default: $FLAKEDB_STORE or ./flakedb-store]")
@click.option("--recipe", "recipe_path", default=None, type=click.Path(dir_okay=False),
              help="build exactly what this recipe needs (its species, α's, wavelengths, binder index, and n: --n or "
                   "the recipe's own resolution)")
@click.option("--workers", type=int, default=None, help="local worker count (threads, or processes with --processes)")
@click.option("--processes", is_flag=True, help="local processes instead of threads")
@click.option("--scheduler", default=None, help="address of a dask.distributed scheduler, e.g. tcp://host:8786")
@click.option("--dry-run", is_flag=True, help="print what would be built and its size, build nothing")
@click.option("--n", "n", type=int, multiple=True, help="node count in air (even); repeat for several [32]")
@click.option("--species", "species", multiple=True, help="species name (repeatable) [default: the whole catalogue]")
@click.option("--alpha", "alpha", multiple=True, metavar="SPECIES=ALPHA",
              help="also project flake SPECIES for orientation spread ALPHA (repeatable) [default: the catalogue's "
                   "α and those the shipped recipes use]")
@click.option("--range-nm", type=float, nargs=2, default=(380.0, 780.0), show_default=True,
              help="first and last wavelength (nm) of the store")
@click.option("--step-nm", type=float, default=5.0, show_default=True, help="wavelength step (nm)")
@click.option("--eta-top", default="1.5", show_default=True,
              help="relative index of the paints' smooth top (clear-coat) interface: the nodes are the solver's "
                   "node set inside the binder below it and the optics use it as the binder index; 1 = no "
                   "interface / index-matched; 'none' = plain Radau nodes with the catalogue binder's index")
@click.option("--top", "top", type=click.Choice(["smooth", "rough"]), default="smooth", show_default=True,
              help="the paints' top interface at --eta-top: smooth (Snell-mapped nodes) or rough (rough coats: "
                   "the air-side nodes inside); --recipe chooses from the recipe")
@click.option("--rank-tol", type=float, default=None,
              help="truncation of the flakes' spectral SVD: the dropped part changes no R(c) by more than this "
                   "fraction of max R [1e-5]")
@click.option("--raw", is_flag=True, help="keep the spectral SVD at its numerical rank (compose --raw needs it)")
def build(store, recipe_path, workers, processes, scheduler, dry_run, n, species, alpha, range_nm, step_nm, eta_top,
          top, rank_tol, raw):
    """Build (or reuse) the projected-kernel store and point `latest` at it."""
    url = store or st.default_store()
    check_build_sizes(n or DEFAULT_N, None)
    check_spectral_options(range_nm, step_nm)
    if workers is not None and not 1 <= workers <= 1024:
        raise FlakedbError(f"--workers {workers}: give 1 ≤ workers ≤ 1024")
    if rank_tol is not None and not (math.isfinite(rank_tol) and 0 < rank_tol < 1):
        raise FlakedbError(f"--rank-tol {rank_tol:g}: a fraction of max R, 0 < rank-tol < 1 (e.g. 1e-5)")
    if str(eta_top).strip().lower() in ("none", "null"):
        eta = None
    else:
        try:
            eta = float(eta_top)
        except ValueError:
            raise FlakedbError(f"--eta-top {eta_top}: give a number ≥ 1 (e.g. 1.5) or 'none'") from None
        if not (math.isfinite(eta) and 1.0 <= eta <= 3.0):
            raise FlakedbError(f"--eta-top {eta_top}: a clear coat's relative index is in 1 ≤ eta ≤ 3 (binders are "
                               f"1.3-1.7), or 'none'")
    alphas = None
    if alpha:
        alphas = {}
        for a in alpha:
            name, _, val = a.partition("=")
            try:
                v = float(val)
            except ValueError:
                raise FlakedbError(f"--alpha {a}: give SPECIES=ALPHA with ALPHA a number > 0, e.g. metallic=0.2") from None
            if not (math.isfinite(v) and FLAKE_ALPHA_RANGE[0] <= v <= FLAKE_ALPHA_RANGE[1]):
                raise FlakedbError(f"--alpha {a}: the flake orientation spread must be in {FLAKE_ALPHA_RANGE[0]:g} ≤ α ≤ "
                                   f"{FLAKE_ALPHA_RANGE[1]:g} (the recipe's "
                                   f"orientation_alpha range: a narrower lobe than any quadrature resolves)")
            alphas.setdefault(name.strip(), []).append(v)
    try:
        if recipe_path is not None:
            if len(n) > 1:
                raise ValueError(f"--recipe builds one node count; got --n {' '.join(map(str, n))}")
            rec = load_recipe(recipe_path, load_catalog())
            req = request_for_recipe(rec, n=n[0] if n else None, store_raw=raw)
        else:
            if alphas is not None:
                base = make_request(species=species or None, n=n or DEFAULT_N).alphas
                for k, v in alphas.items():
                    base[k] = sorted({*base.get(k, []), *v})
                alphas = base
            req = make_request(species=species or None, n=n or DEFAULT_N, alphas=alphas,
                               wavelength_nm=spectral_grid(tuple(range_nm), step_nm), store_raw=raw, eta_top=eta,
                               rank_tol=rank_tol, top=top)
        plan = st.plan_build(req)
    except (RecipeError, CatalogError) as exc:
        raise FlakedbError(str(exc)) from exc
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
    check_store_dir(url)
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
