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
    print()
    print("not built yet: solver, catalogue build, compose, preview")
