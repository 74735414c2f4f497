"""The light assembler (issue #11; docs/store.md): compose from projected, compressed kernel factors
against the direct path, in one run (the machine is shared and noisy: compare the ratios).

* ``store/3-species n=N``: bench/bench_solver.py's smooth-coated three-species basecoat (two flake
  species + one HG pigment, 16 channels, 15 µm, Lambertian 0.5) solved from precomputed factors (the
  flakes' spectral SVD × projected blocks from :func:`flakedb.rt.scattering.stored.flake_factors`, the pigment's
  Legendre moments g^k, untimed in setup) and directly (:class:`flakedb.rt.scattering.media.Mixture`, projected per
  solve).  Extra columns: the direct solve's time in the same run, the ratio, max |Δf| / max f, and
  the profile split (projection / contraction / doubling / adding / I/O, cProfile cumulative times).
* ``store/tri-coat n=N``: ``flakedb compose`` of catalog/recipes/tri-coat-pearl-white.yaml at its own
  bands (41) from a store built for it (``build --recipe``, untimed), whole compose (optics, solve,
  table, report, files; checksums of what it reads verified), run in a subprocess for its peak RSS;
  the direct compose in the same run for the ratio (n = 32 only: at n = 100 the direct path takes
  minutes).
"""

import cProfile
import json
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CHANNELS = 16

#: function name → profile bucket (cumulative time of the outermost call of each)
BUCKETS = {
    "projection": ("project_kernel_basis",),
    "contraction": ("_contract_factors", "LegendreKernel.blocks"),
    "doubling": ("double_symmetric", "thin_slab_diamond", "eigen_slab"),  # homogeneous slabs (eigen or doubling)
    "adding": ("reflection_over", "reflection_under_smooth", "add_reflection_only"),
    "io": ("read",),
}


def _profile_split(fn):
    pr = cProfile.Profile()
    t0 = time.perf_counter()
    pr.enable()
    out = fn()
    pr.disable()
    total = time.perf_counter() - t0
    stats = pstats.Stats(pr).stats
    split = {}
    for bucket, names in BUCKETS.items():
        t = 0.0
        for (file, _, func), (_, _, _, ct, _) in stats.items():
            qual = func
            if func == "blocks" and "legendre" in file:
                qual = "LegendreKernel.blocks"
            if qual in names and ("flakedb" in file):
                t += ct
        split[bucket] = t
    split["total"] = total
    split["matrices_fraction"] = (split["doubling"] + split["adding"]) / total if total > 0 else None
    return out, split


def _three_species(n):
    from flakedb.rt.basis.legendre import LEGENDRE_TOL, truncate_legendre
    from flakedb.rt.scattering.media import FlakeMedium, Mixture, PhaseMedium
    from flakedb.rt.scattering.microflake import FlakeOptics
    from flakedb.rt.basis.quadrature import default_tir_nodes, radau_hemisphere, snell_mapped_quadrature
    from flakedb.rt.adding.stack import Lambertian, Slab, Smooth, SolverSettings, solve_stack
    from flakedb.rt.scattering.stored import FlakeFactors, StoredFlakeMedium, StoredMixture, StoredPigmentMedium, flake_factors

    def setup():
        c = np.linspace(0, 1, 33)
        R1 = np.tile(0.2 + 0.6 * (1 - c) ** 5, (CHANNELS, 1))
        T1 = np.tile(0.5 * c, (CHANNELS, 1))
        o2 = FlakeOptics.constant(np.full(CHANNELS, 0.7), np.zeros(CHANNELS))
        alb = np.linspace(0.3, 0.95, CHANNELS)
        direct = Mixture([FlakeMedium(0.2, FlakeOptics(c, R1, T1), 1.0), FlakeMedium(0.3, o2, 0.5),
                          PhaseMedium(np.full(CHANNELS, 2.0), alb, ("hg", 0.5))])
        q = radau_hemisphere(n // 2)
        qi = snell_mapped_quadrature(q, 1.5, default_tir_nodes(q.h, 1.5))
        t0 = time.perf_counter()
        parts = []
        for (cc, R, T, a), load in (((c, R1, T1, 0.2), 1.0), ((o2.c, o2.R, o2.T, 0.3), 0.5)):
            f = flake_factors(cc, R, T, a, qi.x, qi.w, max_orders=2 * n)
            V = f["V"].astype(np.float32)
            ff = FlakeFactors(qi.x, f["U"], (lambda V: lambda l0, l1: V[:, l0:l1])(V), V.shape[1], f["sigma_t"],
                              f["sigma_s"], f["projected_area"], "bench factors")
            parts.append(StoredFlakeMedium(ff, load, np.eye(CHANNELS)))
        chi, _ = truncate_legendre(0.5 ** np.arange(400)[None], LEGENDRE_TOL)  # HG: χ_k = g^k
        parts.append(StoredPigmentMedium(np.full(CHANNELS, 2.0), 2.0 * alb, np.repeat(chi, CHANNELS, 0)))
        t_pre = time.perf_counter() - t0
        settings = SolverSettings.product(n)
        bottom = Lambertian(np.full(CHANNELS, 0.5))
        return direct, StoredMixture(parts), settings, bottom, t_pre, solve_stack, Slab, Smooth

    def run(arg):
        direct, stored, settings, bottom, t_pre, solve_stack, Slab, Smooth = arg
        t0 = time.perf_counter()
        rs, split = _profile_split(lambda: solve_stack(Smooth(1.5), [Slab(15.0, stored)], bottom, settings,
                                                       channels=CHANNELS))
        t_store = time.perf_counter() - t0
        t0 = time.perf_counter()
        rd = solve_stack(Smooth(1.5), [Slab(15.0, direct)], bottom, settings, channels=CHANNELS)
        t_direct = time.perf_counter() - t0
        phi = np.linspace(0, np.pi, 9)
        fs, fd = rs.eval_nodes(phi), rd.eval_nodes(phi)
        return {"store_s_profiled": t_store, "direct_s": t_direct, "direct_over_store": t_direct / t_store,
                "max_rel_f_diff": float(np.abs(fs - fd).max() / np.abs(fd).max()), "orders": rs.info["orders"],
                "precompute_s": t_pre, "profile_s": split}

    return (f"store/3-species n={n} (store + direct in one run)", setup, run,
            {"n": n, "channels": CHANNELS, "what": "solve from precomputed factors vs direct; timed = both",
             "targets_s": {"store": 1.0 if n == 100 else 5.0, "direct": 5.0}})


_CHILD = r"""
import json, sys, time
from flakedb.compose.orchestrate import compose
from flakedb.paint.recipe import load_recipe
def hwm():  # this process's peak RSS in kB (VmHWM: reset by exec, unlike ru_maxrss)
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return float(line.split()[1])
rec = load_recipe(sys.argv[1])
t0 = time.perf_counter()
res = compose(rec, sys.argv[2], n=int(sys.argv[3]), store=None if sys.argv[4] == "-" else sys.argv[4])
t = time.perf_counter() - t0
info = res.stack.info
print(json.dumps({"seconds": t, "stages": res.timings_s, "orders": info.get("orders"),
                  "peak_rss_MB": hwm() / 1024,
                  "lab": [[g["L"], g["a"], g["b"]] for g in res.report["geometries"]]}))
"""


def _tri_coat(n):
    recipe = ROOT / "flakedb" / "catalog" / "recipes" / "tri-coat-pearl-white.yaml"

    def setup():
        from flakedb.paint.recipe import load_recipe
        from flakedb.pipelines.build import build, request_for_recipe

        url = str(Path(tempfile.mkdtemp(prefix="flakedb-bench-store-")) / "store")
        t0 = time.perf_counter()
        res = build(request_for_recipe(load_recipe(recipe), n=n), url, scheduler="threads")
        return url, time.perf_counter() - t0, res["tasks_total"]

    def child(store):
        with tempfile.TemporaryDirectory() as out:
            p = subprocess.run([sys.executable, "-c", _CHILD, str(recipe), out, str(n), store or "-"],
                               capture_output=True, text=True, check=True, cwd=ROOT)
        return json.loads(p.stdout.strip().splitlines()[-1])

    def run(arg):
        from flakedb.colour.colorimetry import delta_E_2000

        url, t_build, tasks = arg
        s = child(url)
        out = {"store_compose_s": s["seconds"], "store_stages_s": s["stages"], "peak_rss_MB": s["peak_rss_MB"],
               "orders": s["orders"], "build_s": t_build, "build_tasks": tasks}
        if n <= 32:
            d = child(None)
            out.update({"direct_compose_s": d["seconds"], "direct_over_store": d["seconds"] / s["seconds"],
                        "direct_peak_rss_MB": d["peak_rss_MB"],
                        "dE00_store_vs_direct": float(delta_E_2000(np.array(s["lab"]), np.array(d["lab"])).max())})
        return out

    return (f"store/tri-coat-pearl-white n={n} 41 bands (subprocess compose)", setup, run,
            {"n": n, "bands": 41, "targets": {"store_compose_s": 3.0, "peak_rss_MB": 1536}})


BENCHMARKS = [_three_species(100), _three_species(200), _tri_coat(32), _tri_coat(100)]
