"""Compose timings (see bench/run.py for the BENCHMARKS protocol).

``flakedb compose`` of two example recipes at n = 64 (the recipes' own 10 nm spectral grid, 41
bands), into a temporary directory: metallic-silver (one flake species, aluminium / MgF2) and
tri-coat-pearl-white (pearl flakes over a TiO2 basecoat: two slabs, Mie optics).  Timed: the whole
compose (species optics computed directly — compose does not read the store yet — , the solve, the
tables, the colour report and the three files).  The extra columns split the time into stages and
record the paint's L*45 so a change of results shows up beside a change of speed.

The paper's Table 1 times its adding-doubling per particle type (RGB mode, n = m = 200); these runs
are spectral and at n = 64, so they are not that comparison (which belongs to the store's bench).
"""

import tempfile
from pathlib import Path

RECIPES = Path(__file__).resolve().parents[1] / "flakedb" / "catalog" / "recipes"
N = 64


def _setup(name):
    def setup():
        from flakedb.paint.recipe import load_recipe

        return load_recipe(RECIPES / f"{name}.yaml")

    return setup


def _run(arg):
    from flakedb.compose.orchestrate import compose

    with tempfile.TemporaryDirectory(prefix="flakedb-bench-") as out:
        res = compose(arg, out, n=N)
    extra = {f"stage_{k}_s": v for k, v in res.timings_s.items()}
    extra["L45"] = res.report["geometries"][3]["L"]
    extra["flop_index"] = res.report["flop_index"]
    extra["bsdf_bytes"] = res.bsdf_summary["size"]
    return extra


BENCHMARKS = [
    (f"compose {name} n={N} spectral 10nm", _setup(name), _run,
     {"recipe": name, "n": N, "bands": 41, "unit": "s per compose"})
    for name in ("metallic-silver", "tri-coat-pearl-white")
]
