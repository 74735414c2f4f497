"""Measures the metal-base lobe envelope METAL_LOBE_ERROR of flakedb/paint/mapping.py (docs/resolution.md
"Metal base"): normal-incidence reflection of a rough conductor under a smooth coat (η 1.5) or none,
binned in 5° θ_o bins from the solver's flux cells, against n = 384.  Run: PYTHONPATH=. python
bench/metal_lobe_envelope.py (about 5 minutes on 2 cores).  Not a benchmark: bench/run.py runs bench_*.py only."""
import numpy as np
from flakedb.rt.adding.stack import Smooth, RoughConductor, SolverSettings, solve_stack
from flakedb.rt.boundaries.microfacet import flux_cell_edges
N = np.array([1.2 + 7.0j])
edges_deg = np.arange(0, 90.01, 5.0)
mu_edges = np.sort(np.cos(np.radians(edges_deg)))
def binned(eta, alpha, n):
    r = solve_stack(None if eta == 1 else Smooth(eta), [], RoughConductor(N, alpha), SolverSettings.product(n))
    S0 = r.Rt[0, 0]
    k = len(r.x) - 1  # normal incidence (largest node, Radau includes mu=1)
    flux = S0[:, k] / (r.w[k] * r.x[k]) * 0 + S0[:, k]  # flux per cell (relative)
    C = flux_cell_edges(r.x, r.w)
    cum = np.concatenate([[0], np.cumsum(flux)])
    # cumulative flux vs mu: linear in mu^2 within cells
    cb = np.interp(mu_edges**2, C**2, cum)
    b = np.diff(cb)
    return b / b.sum(), float(r.x[k])
for eta in (1.5, 1.0):
    for alpha in (0.05, 0.1, 0.2, 0.3):
        ref, _ = binned(eta, alpha, 384)
        row = []
        for n in (16, 24, 32, 48, 64, 96, 128, 192):
            b, x = binned(eta, alpha, n)
            row.append((n, n // 2 * alpha, float(np.abs(b - ref).max())))
        print(eta, alpha, " ".join(f"n{n}:hα{ha:.2f}:{e:.4f}" for n, ha, e in row), flush=True)
