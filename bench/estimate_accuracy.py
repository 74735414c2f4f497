"""How well the colour report's discretisation estimate predicts the true error (docs/resolution.md, "The report's
own estimate"; docs/compose-overhead.md).

For each case (a recipe, its mode, a node count n): the colour reports of the solve at n, at n/2, at 3n/4 (the
second solves :func:`flakedb.solve.resolution.discretisation_error` can use) and at 2n; the true error is
max ΔE00(n, 2n) over the report geometries, the quantity the estimate stands for.  Printed per case: the
estimate from each second solve (its ΔE00(n', n) times (1 − 2^−p)/(r^p − 1), p =
:data:`flakedb.solve.resolution.DISCRETISATION_ORDER`), its ratio to the true error, and the order observed
from n/2, n, 2n (log2 of ΔE00(n/2, n) / ΔE00(n, 2n)).  Slow (a solve at 2n per case): run by hand,
``PYTHONPATH=. python bench/estimate_accuracy.py [out.json]`` (``ONLY='silver|RGB 200'``: the cases whose
"label n" contains one of the substrings); results in bench/estimate_accuracy.json.
"""

import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from flakedb.appearance.report import colour_report
from flakedb.bsdf.convert import stack_to_table
from flakedb.colour.colorimetry import delta_E_2000
from flakedb.paint.mapping import build_paint, solve_paint
from flakedb.paint.recipe import parse_recipe
from flakedb.solve.resolution import DISCRETISATION_ORDER

ROOT = Path(__file__).resolve().parent.parent
RECIPES = ROOT / "flakedb" / "catalog" / "recipes"

def _rgb(text):
    """The recipe text in RGB mode (its ``spectral:`` line replaced)."""
    i = text.index("spectral:")
    return text[:i] + "spectral: {mode: rgb}\n" + text[text.index("\n", i) + 1:]


#: cadmium yellow (41 bands) under a rough α 0.1 coat, the recipe docs/compose-overhead.md measures
CADMIUM_ROUGH = (RECIPES / "particle-cadmium-yellow.yaml").read_text().replace(
    "roughness: 0}", "roughness: 0.1}").replace("name: particle-cadmium-yellow", "name: cadmium-yellow-rough-coat")

#: coated aluminium (Al α 0.1 under a smooth coat, auto n = 176) in RGB mode (ΔE00(144, 288) 0.0949 against 0.095
#: in 41 bands, docs/resolution.md): the catalogue's one auto n above 96
COATED_AL_RGB = _rgb((RECIPES / "coated-aluminium.yaml").read_text())

#: particle pearlescent in RGB mode (flakes: RGB is their worst case, docs/resolution.md), for n ≥ 96 where 41 bands
#: at 2n are slow
PEARL_RGB = _rgb((RECIPES / "particle-pearlescent.yaml").read_text())

CASES = [  # (label, recipe text, n)
    ("rough 0.1 / HG / Lambertian, RGB", (ROOT / "bench/recipes/rough-hg-lambertian-rgb.yaml").read_text(), 64),
    ("rough 0.1 / HG / Lambertian, RGB", (ROOT / "bench/recipes/rough-hg-lambertian-rgb.yaml").read_text(), 128),
    ("rough 0.1 / HG / Lambertian, RGB", (ROOT / "bench/recipes/rough-hg-lambertian-rgb.yaml").read_text(), 200),
    ("metallic silver", (RECIPES / "metallic-silver.yaml").read_text(), 48),
    ("metallic silver", (RECIPES / "metallic-silver.yaml").read_text(), 96),
    ("metallic silver", (RECIPES / "metallic-silver.yaml").read_text(), 128),
    ("particle pearlescent", (RECIPES / "particle-pearlescent.yaml").read_text(), 40),
    ("particle pearlescent, RGB", PEARL_RGB, 128),
    ("cadmium yellow under a rough 0.1 coat", CADMIUM_ROUGH, 64),
    ("cadmium yellow under a rough 0.1 coat", CADMIUM_ROUGH, 128),
    ("coated aluminium, RGB", COATED_AL_RGB, 176),
]


def lab_at(paint, n):
    """(6, 3) L*a*b* at the report geometries of the solve at n (as :func:`flakedb.solve.pipeline.second_report`)."""
    s = solve_paint(paint, n, threads=os.cpu_count() or 1)
    table = stack_to_table(s.scattered(), paint.channels, paint.eta, None, paint.delta, {})
    rep = colour_report(table, paint.mode, paint.wavelength_nm, s.x, s.albedo(include_delta=False),
                        paint.eta if paint.delta else None, "")
    return np.array([[g["L"], g["a"], g["b"]] for g in rep["geometries"]])


def n_half(n):
    return max(8, 2 * int(round(n / 4)))


def n_three_quarters(n):
    return max(8, 2 * int(round(3 * n / 8)))


def estimate(d, n, n2, p=DISCRETISATION_ORDER):
    r = n / n2
    return d * (1 - 2.0**-p) / (r**p - 1)


def measure(label, text, n):
    paint = build_paint(parse_recipe(text))
    t0 = time.process_time()
    ns = {"n": n, "half": n_half(n), "three_quarters": n_three_quarters(n), "double": 2 * n}
    lab = {k: lab_at(paint, v) for k, v in ns.items()}
    true = float(delta_E_2000(lab["n"], lab["double"]).max())
    out = {"case": label, "n": n, "true_dE00_n_2n": true, "cpu_s": time.process_time() - t0}
    for k in ("half", "three_quarters"):
        d = float(delta_E_2000(lab[k], lab["n"]).max())
        e = estimate(d, n, ns[k])
        out[k] = {"n_second": ns[k], "dE00_second_n": d, "estimate": e, "estimate_over_true": e / true}
    dh = out["half"]["dE00_second_n"]
    out["observed_order"] = math.log2(dh / true) if true > 0 and dh > 0 else None
    return out


def main():
    rows = []
    only = [o for o in os.environ.get("ONLY", "").split("|") if o]  # substrings of "label n", any of them
    for label, text, n in CASES:
        if only and not any(o in f"{label} {n}" for o in only):
            continue
        r = measure(label, text, n)
        rows.append(r)
        print(f"{label:40s} n {n:4d}: true {r['true_dE00_n_2n']:.4f}; n/2 est {r['half']['estimate']:.4f} "
              f"({r['half']['estimate_over_true']:.2f}x); 3n/4 est {r['three_quarters']['estimate']:.4f} "
              f"({r['three_quarters']['estimate_over_true']:.2f}x); order {r['observed_order']}; "
              f"{r['cpu_s']:.0f} cpu s", flush=True)
    if len(sys.argv) > 1:
        Path(sys.argv[1]).write_text(json.dumps({"created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                                                 "order_assumed": DISCRETISATION_ORDER, "cases": rows}, indent=1))


if __name__ == "__main__":
    main()
