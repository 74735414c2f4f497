"""The end-to-end demo behind `make demo`: runs each stage that exists, names those that do not."""

import os


def run_demo(out_dir):
    os.makedirs(out_dir, exist_ok=True)
    from flakedb import __version__

    print(f"flakedb {__version__}: demo, outputs in {out_dir}/")

    # Stage 1: particle optics of a catalogue species (same code as `flakedb species show`).
    from flakedb.species import load_catalog, optics_table, plot_optics

    catalog = load_catalog()
    for name in ("pearlescent", "titanium-white"):
        print()
        print(optics_table(name, catalog))
        print(f"plot: {plot_optics(name, out_dir, catalog)}")

    # Stage 2: compose an example recipe (same code as `flakedb compose`), at demo settings.
    print()
    _compose_demo(out_dir, catalog)
    print()
    print("not built yet: solver, catalogue build, preview")


#: The example recipe the demo composes, and the demo's lighter settings (the recipe's own are
#: 10 nm bands and resolution auto; `flakedb compose` uses those).
DEMO_RECIPE = "tri-coat-pearl-white"
DEMO_STEP_NM = 20
DEMO_N = 48


def _compose_demo(out_dir, catalog):
    import yaml

    from flakedb.export import compose
    from flakedb.recipe import parse_recipe
    from flakedb.report import format_report
    from flakedb.species import repo_root

    path = repo_root() / "catalog" / "recipes" / f"{DEMO_RECIPE}.yaml"
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    doc["spectral"] = {**doc.get("spectral", {}), "step_nm": DEMO_STEP_NM}
    recipe = parse_recipe(yaml.safe_dump(doc, sort_keys=False), source=path, catalog=catalog)
    print(f"compose {path.name} (demo settings: {DEMO_STEP_NM} nm bands, n = {DEMO_N}; "
          f"`flakedb compose` uses the recipe's own); species optics computed directly from the catalogue")
    res = compose(recipe, out_dir, n=DEMO_N, catalog=catalog, log=lambda s: print(f"  {s}"))
    print(format_report(res.report))
    for k in ("bsdf", "h5", "json"):
        print(f"{k}: {res.paths[k]}")
    print(f"compose time: {sum(res.timings_s.values()):.1f} s")
