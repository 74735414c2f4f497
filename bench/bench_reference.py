"""Throughput of the Monte Carlo reference (flakedb.reference.montecarlo), in paths per second.

Representative case (the brief's): an HG slab, τ = 1, g = 0.7, albedo 0.9, under a smooth η = 1.5
clear coat over a Lambertian primer of albedo 0.8, incidence 45°.  A second case adds translucent
micro-flakes (delta tracking with null collisions) to the same slab.  Numba threads: numba's default
(all cores); the kernel's results do not depend on the thread count.
"""

import time

import numpy as np

from flakedb.reference.montecarlo import (
    FlakeMedium,
    HenyeyGreenstein,
    Lambertian,
    PhaseMedium,
    Problem,
    Slab,
    Smooth,
    simulate,
)

N_PATHS = 400_000
MU_I = float(np.cos(np.radians(45.0)))


def _hg_problem():
    return Problem(slabs=(Slab(10.0, (PhaseMedium(0.1, 0.9, HenyeyGreenstein(0.7)),)),),
                   top=Smooth(1.5), bottom=Lambertian(0.8))


def _flake_problem():
    cg = np.linspace(0.0, 1.0, 33)
    flakes = FlakeMedium(0.2, 0.2, 0.3 + 0.2 * cg, 0.4 * (1 - cg), c_grid=cg)
    return Problem(slabs=(Slab(10.0, (flakes, PhaseMedium(0.1, 0.9, HenyeyGreenstein(0.7)))),),
                   top=Smooth(1.5), bottom=Lambertian(0.8))


def _setup(make):
    def setup():
        p = make()
        simulate(p, MU_I, 1000, seed=0)  # JIT compile / load the cache outside the timing
        return p
    return setup


def _run(p):
    t0 = time.perf_counter()
    r = simulate(p, MU_I, N_PATHS, seed=1)
    dt = time.perf_counter() - t0
    return {"paths_per_s": N_PATHS / dt, "events_per_path": float(r.events_per_path[0]),
            "albedo": float(r.albedo[0]), "albedo_se": float(r.albedo_se[0])}


BENCHMARKS = [
    ("reference_mc_hg_slab_smooth_coat_lambertian", _setup(_hg_problem), _run,
     {"n_paths": N_PATHS, "mu_i": MU_I, "units": "paths/s in paths_per_s",
      "case": "HG tau=1 g=0.7 albedo=0.9 | smooth eta=1.5 | Lambertian 0.8"}),
    ("reference_mc_flakes_hg_slab_smooth_coat_lambertian", _setup(_flake_problem), _run,
     {"n_paths": N_PATHS, "mu_i": MU_I, "units": "paths/s in paths_per_s",
      "case": "flakes a_rho=0.2/um alpha=0.2 + HG tau=1 | smooth eta=1.5 | Lambertian 0.8"}),
]
