"""The end-to-end demo behind `make demo`: runs each stage that exists, names those that do not."""

import os


def run_demo(out_dir):
    os.makedirs(out_dir, exist_ok=True)
    from flakedb import __version__

    print(f"flakedb {__version__}: demo, outputs in {out_dir}/")
    print("not built yet: species optics, solver, catalogue build, compose, preview")
