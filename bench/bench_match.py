"""Colour matching (issue #14; see bench/run.py for the BENCHMARKS protocol).

``match/4-param n=48 16 bands store``: :func:`flakedb.colour.match.match` fitting four fields of a
spectral recipe (400–700 nm every 20 nm, 16 bands, n = 48, smooth 1.5 coat over a gray primer): the
volume fractions of metallic flakes, cadmium yellow and iron black, and the basecoat thickness, to a
target made by flakedb from the true recipe at the ASTM E2539 set (11 geometries), starting from
loadings off by factors 2–3 and the thickness off by 47 %.  (The flakes' orientation spread α is not
fitted from a store: a store serves the α's it was built for; docs/store.md.)  Catalogue species' reflectance
functions come from a store version built for it in the (untimed) setup, compressed factors.
Extra columns: compose calls, seconds per compose call (the time of
:func:`flakedb.colour.match.compose_table` + evaluation at the geometries; the rest of a fit is
bookkeeping), iterations, max ΔE00 at the start and at the fit, and the worst relative error of the
recovered parameters.
"""

import tempfile
from pathlib import Path

import numpy as np

N = 48
RANGE_NM, STEP_NM = (400.0, 700.0), 20.0
SPECIES = ("metallic", "cadmium-yellow", "iron-black")
TRUE = {"vf_metallic": 0.05, "vf_yellow": 0.03, "vf_black": 0.004, "thickness": 15.0}
START = {"vf_metallic": 0.15, "vf_yellow": 0.01, "vf_black": 0.01, "thickness": 22.0}

RECIPE = """\
flakedb: 1
name: bench-match
spectral: {{mode: spectral, range_nm: [400, 700], step_nm: 20}}
resolution: {n}
layers:
  - clearcoat: {{thickness_um: 40, ior: 1.5, roughness: 0}}
  - basecoat:
      thickness_um: {thickness}
      ior: 1.5
      particles:
        - {{species: metallic, volume_fraction: {vf_metallic}}}
        - {{species: cadmium-yellow, volume_fraction: {vf_yellow}}}
        - {{species: iron-black, volume_fraction: {vf_black}}}
  - primer: {{color: gray}}
"""


def _setup():
    import yaml

    from flakedb.colour.colorimetry import spectral_grid
    from flakedb.match.fit import predict, recipe_from_doc
    from flakedb.match.targets import E2539_GEOMETRIES, format_target, read_target
    from flakedb.paint.catalog import load_catalog
    from flakedb.pipelines.build import build, make_request
    from flakedb.store import versions as st

    url = str(Path(tempfile.mkdtemp(prefix="flakedb-bench-match-")) / "store")
    build(make_request(species=list(SPECIES), n=N, wavelength_nm=spectral_grid(RANGE_NM, STEP_NM),
                       eta_top=1.5), url, scheduler="sync")
    version = st.open_version(url)
    catalog = load_catalog(None)
    true_doc = yaml.safe_load(RECIPE.format(n=N, **TRUE))
    pred = predict(recipe_from_doc(true_doc, catalog=catalog), E2539_GEOMETRIES, catalog=catalog, store=version)
    target = read_target(format_target(pred.geometries, reflectance=pred.rf, wavelength_nm=pred.wavelength_nm))
    fit = {k: f"{{fit: [{lo}, {hi}], start: {START[k]}}}" for k, (lo, hi) in
           {"vf_metallic": (0.01, 0.2), "vf_yellow": (0.003, 0.1), "vf_black": (0.0005, 0.05),
            "thickness": (8.0, 30.0)}.items()}
    base = yaml.safe_load(RECIPE.format(n=N, **fit))
    return base, target, catalog, version


def _run(arg):
    from flakedb.match.fit import match

    base, target, catalog, version = arg
    res = match(base, target, catalog=catalog, store=version)
    def true_value(name):  # parameters come in the recipe's order: thickness, then the particles
        if name.endswith("thickness_um"):
            return TRUE["thickness"]
        return [TRUE["vf_metallic"], TRUE["vf_yellow"], TRUE["vf_black"]][int(name.split("particles[")[1][0])]

    true = np.array([true_value(p.name) for p in res.params])
    return {"compose_calls": res.n_compose, "s_per_compose_call": res.compose_s_per_call,
            "compose_s_total": res.compose_s, "iterations": res.iterations,
            "max_dE00_start": float(res.de_start.max()), "max_dE00_fit": float(res.de_fit.max()),
            "parameters": [p.name for p in res.params],
            "max_rel_param_error": float(np.max(np.abs(res.values / true - 1.0)))}


BENCHMARKS = [
    (f"match/4-param n={N} 16 bands store", _setup, _run,
     {"n": N, "bands": 16, "geometries": 11, "parameters": 4, "store": "compressed",
      "issue_target_s": 60}),
]
