"""Reference table of the rough dielectric interface (η 1.5) from the microsurface random walk
(flakedb/reference/microsurface.py, Heitz et al. 2016), for tests/reference/test_rough_walk_table.py
(issue 36 item 6; docs/rough-interfaces.md, "Multiple scattering by the height chain").

For α 0.05, 0.1, 0.3, 0.5 and the n = 64 product rule's nodes nearest 0, 20, 45, 61, 70, 75, 80, 85°:
R from the air and T from the binder (into the air), each from its own walk of N paths (default 10⁶),
with their standard errors.  Where the node's flux cell lies within α (θ, radians) of the critical angle
(T from the binder changes there on the scale of the facet tilts, so the flux-cell average the solver carries is
not the point value: α 0.05, 44.9°: 0.0401 against 0.0358), also T from the binder averaged over the cell
(``T_binder_cell``: incident cosines drawn from μ dμ on the cell, ``walk_dielectric(cell=...)``).  The cell
edges are the solver's definition (``flux_cell_edges``), imported on purpose: the walk must average over the
cell the solver's node stands for; the walk itself shares nothing with the solver.  About 6 minutes on one
core for 10⁶.

    PYTHONPATH=$PWD python tools/rough_walk_table.py [N] > tests/reference/data/rough_walk_table.json
"""

import json
import sys

import numpy as np

from flakedb.reference import microsurface as ms
from flakedb.rt.basis.quadrature import radau_hemisphere
from flakedb.rt.boundaries.microfacet import flux_cell_edges

ETA = 1.5
ALPHAS = (0.05, 0.1, 0.3, 0.5)
ANGLES_DEG = (0.0, 20.0, 45.0, 61.0, 70.0, 75.0, 80.0, 85.0)
N_NODES = 64


def near_critical(lo, hi, alpha, eta=ETA):
    """Whether the cell [lo, hi] (cosines) lies within ``alpha`` (θ, radians) of the critical angle seen from
    the binder (η > 1): there T from the binder falls from its plateau to 0 across the facet tilts."""
    theta_c = np.arcsin(1.0 / eta)
    th_lo, th_hi = np.arccos(hi), np.arccos(lo)
    return bool(max(th_lo - theta_c, theta_c - th_hi, 0.0) <= alpha)


def main(n_paths):
    q = radau_hemisphere(N_NODES)
    x = q.x
    edges = flux_cell_edges(q.x, q.w)
    nodes = [int(np.argmin(np.abs(x - np.cos(np.radians(t))))) for t in ANGLES_DEG]
    rows = []
    for ia, alpha in enumerate(ALPHAS):
        for j, k in enumerate(nodes):
            mu = float(x[k])
            top = ms.walk_dielectric(mu, alpha, ETA, n_paths, 1000 + 100 * ia + j)
            bot = ms.walk_dielectric(mu, alpha, ETA, n_paths, 5000 + 100 * ia + j, from_below=True)
            rows.append({"alpha": alpha, "node": k, "mu": mu, "R_air": top["R"], "R_air_se": top["R_se"],
                         "T_binder": bot["T"], "T_binder_se": bot["T_se"], "lost": top["lost"] + bot["lost"]})
            cell = (float(edges[k]), float(edges[k + 1]))
            if near_critical(*cell, alpha):
                avg = ms.walk_dielectric(None, alpha, ETA, n_paths, 7000 + 100 * ia + j, from_below=True, cell=cell)
                rows[-1].update({"cell": list(cell), "T_binder_cell": avg["T"], "T_binder_cell_se": avg["T_se"]})
                rows[-1]["lost"] += avg["lost"]
            print(rows[-1], file=sys.stderr, flush=True)
    return {"eta": ETA, "n_nodes": N_NODES, "n_paths": n_paths, "walk": "flakedb.reference.microsurface.walk_dielectric",
            "seeds": "1000 + 100 i_alpha + j (air), 5000 + 100 i_alpha + j (binder), 7000 + 100 i_alpha + j (binder, cell)",
            "rows": rows}


if __name__ == "__main__":
    json.dump(main(int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000), sys.stdout, indent=1)
    print()
