"""RGB mode versus spectral mode on the catalogue's paints (issue #4): the colour difference ΔE00
between composing a recipe per spectral band (then converting to colour) and the paper's RGB mode
(converting flake R/T and pigment parameters to RGB before the solve), at the multi-angle
spectrophotometer geometries of the colour report.

    python -m figures.rgb_vs_spectral [--n 32] [--step-nm 10] [--out docs/figures/rgb-vs-spectral.json]
"""

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from flakedb.atomic import atomic_write_text
from flakedb.colour.colorimetry import delta_E_2000
from flakedb.colour.settings import resolve
from flakedb.compose.orchestrate import compose
from flakedb.paint.catalog import load_catalog
from flakedb.paint.recipe import parse_recipe
from flakedb.resources import RECIPES_DIR

RECIPES = ["particle-metallic", "particle-pearlescent", "particle-gray-mirror", "particle-cadmium-yellow",
           "particle-titanium-white", "particle-iron-black", "metallic-silver", "tri-coat-pearl-white",
           "fig7-pearlescent-tio2-100nm"]


def compare(name, n, step_nm, catalog):
    """ΔE00 per aspecular angle between spectral and RGB mode for one recipe (pure wiring)."""
    path = RECIPES_DIR / f"{name}.yaml"
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    labs, times = {}, {}
    for mode in ("spectral", "rgb"):
        d = dict(doc)
        d["spectral"] = {**doc["spectral"], "mode": mode, "step_nm": step_nm}
        recipe = parse_recipe(yaml.safe_dump(d, sort_keys=False), source=path, catalog=catalog)
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            # both modes under D65/2°: the RGB mode's only conditions (flakedb.colour.settings)
            res = compose(recipe, tmp, n=n, catalog=catalog, colour_settings=resolve("2", "D65", mode=mode))
            times[mode] = time.perf_counter() - t0
        labs[mode] = {g["aspecular_deg"]: (g["L"], g["a"], g["b"]) for g in res.report["geometries"]}
    angles = sorted(labs["spectral"])
    de = [float(delta_E_2000(np.array(labs["spectral"][a]), np.array(labs["rgb"][a]))) for a in angles]
    return {"recipe": name, "aspecular_deg": angles, "delta_E00": de, "max_delta_E00": max(de),
            "lab_spectral": [labs["spectral"][a] for a in angles], "lab_rgb": [labs["rgb"][a] for a in angles],
            "compose_s": times}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=32)
    ap.add_argument("--step-nm", type=float, default=10.0)
    ap.add_argument("--out", default="docs/figures/rgb-vs-spectral.json")
    ap.add_argument("--only", default=None, help="comma-separated recipe names")
    args = ap.parse_args(argv)

    catalog = load_catalog()
    names = args.only.split(",") if args.only else RECIPES
    rows = []
    for name in names:
        row = compare(name, args.n, args.step_nm, catalog)
        rows.append(row)
        print(f"{name:32s} max ΔE00 {row['max_delta_E00']:6.2f}   per angle "
              + " ".join(f"{v:5.2f}" for v in row["delta_E00"]))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"what": "CIEDE2000 between spectral-mode and RGB-mode compose, 45° illumination, aspecular angles",
           "n": args.n, "step_nm": args.step_nm, "rows": rows}
    atomic_write_text(out, json.dumps(doc, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
