"""The fits of issue 39 item 1 as whole processes: a 3-loading match, an orientation-α fit and a 2-panel calibrate,
each with the fit's reuse cache (:mod:`flakedb.rt.common.reuse`, the product's path) or without it (``--today``: every
evaluation computes every species' optics and projection afresh, the path before the cache, and a calibrate composes
once per Jacobian column instead of chaining its absorption columns).  Code shared by both paths (the Mie
phase function's double series, the recipe check's copies on lookup) speeds both: its gain shows against
main's code run beside (docs/fit-speed.md), not in this pair's ratio.

    python bench/fit_cases.py prepare DIR            # the base recipes, targets and ladder (true recipes composed)
    python bench/fit_cases.py run CASE DIR [--today] # CASE: match3 | alpha | calibrate2; prints one JSON line

The targets are made by flakedb from the true recipes (:data:`TRUE`), so every fit can reach ΔE00 ≈ 0; each run
prints its compose calls, iterations, the worst ΔE00 at the fit and the fitted values.  ``bench/bench_match.py``
times both paths in turn (its ``fit/…`` rows).
"""

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from flakedb.process import blas_one_thread, tune_allocator  # noqa: E402  (imports no numpy)

if __name__ == "__main__":  # the process as `flakedb match` / `calibrate` runs (flakedb.cli.main.main), before numpy
    blas_one_thread()
    tune_allocator()

import numpy as np  # noqa: E402
import yaml  # noqa: E402

#: The product's default spectral grid (380–780 nm every 10 nm, 41 bands) and ``resolution: auto``, as a colour
#: engineer composes.
SPECTRAL = {"mode": "spectral", "range_nm": [380, 780], "step_nm": 10}


def _recipe(name, particles, thickness_um=15.0, primer="gray", resolution="auto"):
    return {"flakedb": 1, "name": name, "spectral": dict(SPECTRAL), "resolution": resolution,
            "layers": [{"clearcoat": {"thickness_um": 40, "ior": 1.5, "roughness": 0}},
                       {"basecoat": {"thickness_um": thickness_um, "ior": 1.5, "particles": particles}},
                       {"primer": {"color": primer}}]}


#: match3: three volume fractions free, true values and starts off by factors 2 (and 0.5).
MATCH3_TRUE = (0.05, 0.03, 0.004)
MATCH3_START = (0.1, 0.015, 0.008)
MATCH3_SPECIES = ("metallic", "cadmium-yellow", "iron-black")
#: alpha: the metallic flakes' orientation spread free (true 0.2, start 0.1), over a yellow.
ALPHA_TRUE, ALPHA_START = 0.2, 0.1
#: calibrate2: cadmium yellow's absorption (degree-2 Legendre factor) and size from a masstone and a 1:5 let-down
#: with titanium white, the truth ln k-factor 0.3 − 0.25 x and 20 % larger particles (tests/match/test_calibrate.py).
CAL_SPECIES = "cadmium-yellow"
CAL_Z_TRUE = (0.3, -0.25, 0.0, float(np.log(1.2)))
CAL_PANELS = ((0.1, 0.0, "masstone"), (0.02, 0.1, "letdown-1-5"))


def _match3_doc(values):
    return _recipe("match3", [{"species": s, "volume_fraction": v} for s, v in zip(MATCH3_SPECIES, values)])


def _alpha_doc(alpha):
    return _recipe("alpha", [{"species": "metallic", "volume_fraction": 0.05, "orientation_alpha": alpha},
                             {"species": "cadmium-yellow", "volume_fraction": 0.03}])


def _panel_doc(vp, vw, name):
    parts = [{"species": CAL_SPECIES, "volume_fraction": vp}]
    if vw:
        parts.append({"species": "titanium-white", "volume_fraction": vw})
    return _recipe(name, parts, thickness_um=30.0, primer="black")


def prepare(out):
    from flakedb.match import calibrate as cal
    from flakedb.match.fit import predict, recipe_from_doc
    from flakedb.match.targets import E2194_GEOMETRIES, E2539_GEOMETRIES, write_target
    from flakedb.paint.catalog import load_catalog

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    catalog = load_catalog(None)

    def target(doc, path, cat=catalog, geometries=E2539_GEOMETRIES):
        pr = predict(recipe_from_doc(doc, catalog=cat), geometries, catalog=cat)
        write_target(path, pr.geometries, reflectance=pr.rf, wavelength_nm=pr.wavelength_nm, name=path.stem)

    target(_match3_doc(MATCH3_TRUE), out / "match3.csv")
    bounds = ((0.01, 0.2), (0.003, 0.1), (0.0005, 0.05))
    (out / "match3.yaml").write_text(yaml.safe_dump(_match3_doc(
        [{"fit": list(b), "start": s} for b, s in zip(bounds, MATCH3_START)]), sort_keys=False))
    target(_alpha_doc(ALPHA_TRUE), out / "alpha.csv")
    (out / "alpha.yaml").write_text(yaml.safe_dump(_alpha_doc({"fit": [0.05, 0.5], "start": ALPHA_START}),
                                                   sort_keys=False))
    base = catalog["particles"][CAL_SPECIES]
    truth = cal._catalog_with(catalog, CAL_SPECIES, cal.calibrated_entry(base, cal.free_parameters(base), CAL_Z_TRUE))
    panels = []
    for vp, vw, name in CAL_PANELS:
        doc = _panel_doc(vp, vw, name)
        (out / f"{name}.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        target(doc, out / f"{name}.csv", truth, E2194_GEOMETRIES)
        panels.append({"recipe": f"{name}.yaml", "target": f"{name}.csv"})
    (out / "ladder.yaml").write_text(yaml.safe_dump({"species": CAL_SPECIES, "name": "cy-lab", "panels": panels}))


def run(case, folder, today=False):
    """One fit, as `flakedb match` / `flakedb calibrate` run it; ``today``: without the reuse cache."""
    from flakedb.match import calibrate as cal
    from flakedb.match.cxf import load_target
    from flakedb.match.fit import match
    from flakedb.paint.catalog import load_catalog

    folder = Path(folder)
    catalog = load_catalog(None)
    t0 = time.perf_counter()
    if case in ("match3", "alpha"):
        fit = match.__wrapped__ if today else match  # the undecorated fit: no reuse scope
        res = fit(yaml.safe_load((folder / f"{case}.yaml").read_text()), load_target(folder / f"{case}.csv"),
                  catalog=catalog)
        row = {"compose_calls": res.n_compose, "iterations": res.iterations, "max_dE00_fit": float(res.de_fit.max()),
               "values": [float(v) for v in res.values]}
    elif case == "calibrate2":
        species, _, free, panels = cal.read_ladder(folder / "ladder.yaml")
        fit = cal.calibrate.__wrapped__ if today else cal.calibrate
        res = fit(species, panels, catalog, free=free, band_jacobian=not today)  # today: a compose per column
        row = {"compose_calls": res.n_compose, "nfev": res.nfev,
               "max_dE00_fit": float(max(np.max(d) for d in res.de_fit)), "z": [float(v) for v in res.z]}
    else:
        raise SystemExit(f"unknown case {case!r}: match3, alpha or calibrate2")
    row.update(case=case, path="today" if today else "reuse", fit_s=time.perf_counter() - t0)
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare")
    p.add_argument("dir")
    r = sub.add_parser("run")
    r.add_argument("case", choices=("match3", "alpha", "calibrate2"))
    r.add_argument("dir")
    r.add_argument("--today", action="store_true", help="without the fit's reuse cache")
    a = ap.parse_args(argv)
    if a.cmd == "prepare":
        prepare(a.dir)
    else:
        print(json.dumps(run(a.case, a.dir, a.today)), flush=True)


if __name__ == "__main__":
    main()
