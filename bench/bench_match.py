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

``fit/…`` (issue 39 item 1): the three fits of bench/fit_cases.py — three loadings free, the flakes' orientation
α, a two-panel calibrate — each as two whole processes in turn, today's path (every evaluation computes every
species' optics and projection; a calibrate composes once per Jacobian column) and the product's (the fit's reuse
cache, :mod:`flakedb.rt.common.reuse`, and a calibrate's chained absorption columns), with the ratio today / reuse
of the pair.  Code both paths share (the Mie double series) speeds both; docs/fit-speed.md compares with main.  Each pair takes minutes on 2 cores (timed once: ``--long``).
"""

import json
import os
import subprocess
import sys
import tempfile
import time
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


def _fit_setup():
    """The issue-39 fits' inputs (bench/fit_cases.py prepare: the targets composed from the true recipes)."""
    folder = Path(tempfile.mkdtemp(prefix="flakedb-bench-fits-"))
    subprocess.run([sys.executable, str(FIT_CASES), "prepare", str(folder)], check=True, env=_env())
    return folder


def _env():
    return {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}


def _whole(case, folder, today):
    """One whole process (bench/fit_cases.py run): (wall s, CPU s, its JSON line)."""
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, str(FIT_CASES), "run", case, str(folder)] + (["--today"] if today else []),
                         stdout=subprocess.PIPE, env=_env())
    out = p.stdout.read()
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    if status:
        raise RuntimeError(f"bench/fit_cases.py run {case}{' --today' if today else ''} failed (status {status})")
    return wall, ru.ru_utime + ru.ru_stime, json.loads(out.decode().strip().splitlines()[-1])


def _fit_run(case):
    def run(folder):
        """Today's path (no reuse cache) and the product's in turn, as whole processes; the ratio today / reuse
        of the pair (the machine's load moves both)."""
        t_today, cpu_today, r_today = _whole(case, folder, today=True)
        t_reuse, cpu_reuse, r_reuse = _whole(case, folder, today=False)
        return {"reuse_s": t_reuse, "today_s": t_today, "ratio_today_over_reuse": t_today / t_reuse,
                "reuse_cpu_s": cpu_reuse, "today_cpu_s": cpu_today, "compose_calls": r_reuse["compose_calls"],
                "compose_calls_today": r_today["compose_calls"], "max_dE00_fit": r_reuse["max_dE00_fit"]}

    return run


FIT_CASES = Path(__file__).resolve().parent / "fit_cases.py"

BENCHMARKS = [
    (f"match/4-param n={N} 16 bands store", _setup, _run,
     {"n": N, "bands": 16, "geometries": 11, "parameters": 4, "store": "compressed",
      "issue_target_s": 60}),
    ("fit/match 3 loadings, 41 bands, auto n: whole process, reuse vs today", _fit_setup, _fit_run("match3"),
     {"bands": 41, "geometries": 11, "parameters": 3, "issue_target_s": 10,
      "what": "bench/fit_cases.py run match3 [--today], whole processes in turn"}),
    ("fit/match orientation alpha, 41 bands, auto n: whole process, reuse vs today", _fit_setup, _fit_run("alpha"),
     {"bands": 41, "geometries": 11, "parameters": 1, "issue_target_s": 20,
      "what": "bench/fit_cases.py run alpha [--today], whole processes in turn"}),
    ("fit/calibrate 2 panels, 4 parameters, 41 bands, auto n: whole process, reuse vs today", _fit_setup,
     _fit_run("calibrate2"),
     {"bands": 41, "geometries": 6, "parameters": 4, "panels": 2, "issue_target_s": 20,
      "what": "bench/fit_cases.py run calibrate2 [--today], whole processes in turn"}),
]
