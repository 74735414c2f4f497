"""The end-to-end demo behind `make demo`: runs each stage that exists, names those that do not."""

import os
import time
from pathlib import Path

from flakedb import __version__
from flakedb.bsdf import open_bsdf
from flakedb.compose.orchestrate import compose
from flakedb.appearance.report import format_report
from flakedb.paint.catalog import load_catalog
from flakedb.paint.recipe import load_recipe
from flakedb.paint.species import optics_table
from flakedb.pipelines.build import build, request_for_recipe
from flakedb.render import look, quadrature
from flakedb.render.imageio import write_exr, write_png
from flakedb.render.plots import plot_optics
from flakedb.resources import RECIPES_DIR
from flakedb.store import versions as st


def run_demo(out_dir):
    """species optics → build the catalogue store → verify → compose from the store → preview.

    Nothing runs when the output directory cannot be made:

    >>> import tempfile
    >>> from pathlib import Path
    >>> blocked = Path(tempfile.mkdtemp()) / "out"
    >>> _ = blocked.write_text("a file, not a directory")
    >>> run_demo(blocked)
    Traceback (most recent call last):
    ...
    FileExistsError: [Errno 17] File exists: '.../out'
    """
    os.makedirs(out_dir, exist_ok=True)

    t_all = time.perf_counter()
    print(f"flakedb {__version__}: demo, outputs in {out_dir}/")

    # Stage 1: particle optics of a catalogue species (same code as `flakedb species show`).

    catalog = load_catalog()
    for name in ("pearlescent", "titanium-white"):
        print()
        print(optics_table(name, catalog))
        print(f"plot: {plot_optics(name, out_dir, catalog)}")

    # Stage 2: build the default catalogue into a versioned store (same code as `flakedb build`).
    print()
    store_url = _build_demo_store(out_dir, catalog)

    # Stage 3: compose an example recipe from the store (same code as `flakedb compose --store`).
    print()
    res = _compose_demo(out_dir, catalog, store_url)

    # Stage 4: a preview render of the composed paint (same code as `flakedb render`).
    print()
    _render_demo(res.paths["bsdf"], out_dir)
    print()
    print(f"demo done in {time.perf_counter() - t_all:.0f} s")


def _build_demo_store(out_dir, catalog):
    """`flakedb build --recipe` for the demo recipe: exactly its species, α's, bands, binder index and n."""
    url = os.path.join(out_dir, "flakedb-store")
    recipe = load_recipe(RECIPES_DIR / f"{DEMO_RECIPE}.yaml", catalog)
    req = request_for_recipe(recipe)
    n = req.resolutions[0]
    print(f"build what {DEMO_RECIPE} needs ({', '.join(sorted(req.species))}; n = {n}, η_top = {req.eta_top}, "
          f"{len(req.wavelength_nm)} bands) into {url}")
    t0 = time.perf_counter()
    res = build(req, url, scheduler="threads", workers=None, progress=True)
    print(f"  {res['status']}: version {res['version']} ({res['tasks_run']} of {res['tasks_total']} tasks run, "
          f"{time.perf_counter() - t0:.1f} s)")
    problems = st.verify_store(url)
    print(f"  verify: {'OK' if not problems else problems}")
    if problems:
        raise SystemExit(1)
    v = st.open_version(url, verify=False)
    for name in sorted(req.species):
        for a in v.alphas(name):
            i = v.flake_info(name, n, a)
            print(f"  {name} α = {a:g}: spectral rank {i['rank']} of {i['numerical_rank']} (max error "
                  f"{i['max_error']:.1e} of max R), {i['orders']} orders, storage ratio {i['storage_ratio']:.1f}")
    return url


def _render_demo(bsdf_path, out_dir):
    bsdf = open_bsdf(bsdf_path)
    result = quadrature.render_sphere_quadrature(bsdf, look.softbox_studio(), None, size=DEMO_PREVIEW_PX)
    stem = Path(bsdf_path).stem
    exr = write_exr(Path(out_dir) / f"{stem}.exr", result.image)
    scale = look.auto_exposure(result.image, result.coverage >= 1.0)
    png = write_png(Path(out_dir) / f"{stem}.png", look.tone_map(result.image, scale))
    print(f"preview {DEMO_PREVIEW_PX}×{DEMO_PREVIEW_PX} rendered in {result.seconds:.1f} s: {exr}, {png}")


#: The example recipe the demo composes, at its own settings (bands, resolution), from the store.
DEMO_RECIPE = "tri-coat-pearl-white"
DEMO_PREVIEW_PX = 256


def _compose_demo(out_dir, catalog, store_url=None):
    path = RECIPES_DIR / f"{DEMO_RECIPE}.yaml"
    recipe = load_recipe(path, catalog)
    print(f"compose {path.name} at its own settings from the store's projected kernel factors")
    res = compose(recipe, out_dir, catalog=catalog, store=store_url, log=lambda s: print(f"  {s}"))
    print(format_report(res.report))
    for k in ("bsdf", "h5", "json"):
        print(f"{k}: {res.paths[k]}")
    print(f"compose time: {sum(res.timings_s.values()):.1f} s")
    return res
