"""Bound on any GGX-lobe analytic material for metallic silver (issue 23): the smallest worst CIEDE2000 at the
ASTM E2194 geometries that ANY positive mix of one, two or three GGX metal lobes (F ~ 1, free per-channel
weights) plus a Lambertian term under the smooth 1.5 coat reaches against the exact BSDF (minimax by
reweighting, non-negative least squares per channel).  Usage: python tools/ggx_mixture_bound.py PAINT.bsdf

Measured 2026-12-04 on metallic-silver.bsdf (n = 48): one lobe 7.72, two 7.66, three 7.66 ΔE00: the goal of
2 is out of reach of every mixture-of-GGX material evaluated in air (OpenPBR, Principled, glTF, UsdPreviewSurface)."""
import itertools
import sys

import numpy as np
from scipy.optimize import nnls

from flakedb.bsdf import open_bsdf
from flakedb.colour.tolerance import delta_E_2000
from flakedb.export.openpbr import colour_grid, exact_rgb, file_directions, ggx_lobe
from flakedb.match.fit import channels_to_Lab, geometry_directions
from flakedb.match.targets import E2194_GEOMETRIES
from flakedb.optics.fresnel import fresnel_dielectric

b = open_bsdf(sys.argv[1])
g = np.asarray(E2194_GEOMETRIES, float)
gi, go, gp = geometry_directions(g)
y = exact_rgb(b, gi, go, gp)
wl = colour_grid(b)
lab = channels_to_Lab(np.pi * y, "rgb", wl)
wi, wo = file_directions(gi, go, gp)
T = (1 - fresnel_dielectric(np.clip(wi[..., 2], 1e-9, 1), 1.5).R) * (1 - fresnel_dielectric(np.clip(wo[..., 2], 1e-9, 1), 1.5).R)
def basis(r):
    lobe, cd = ggx_lobe(wi, wo, r * r)
    return T * lobe  # F ~ 1 for a bright metal at these angles (its colour in the weights)
rs = np.r_[np.linspace(0.05, 1.0, 39)]
B = {r: basis(r) for r in rs}
diff = T / np.pi
def minimax(cols):
    M = np.stack(cols, 1)
    u = np.ones(len(g)); best = 1e9
    for _ in range(30):
        f = np.stack([M @ nnls(M * np.sqrt(u / np.maximum(y[:, c], 1e-4) ** (4 / 3))[:, None],
                               y[:, c] * np.sqrt(u / np.maximum(y[:, c], 1e-4) ** (4 / 3)))[0] for c in range(3)], 1)
        de = delta_E_2000(channels_to_Lab(np.pi * f, "rgb", wl), lab)
        best = min(best, de.max())
        u = u * (de / de.max()) ** 2 + 1e-6
    return best
one = min((minimax([B[r], diff]), r) for r in rs)
print("one GGX lobe + diffuse:", one)
two = min((minimax([B[r1], B[r2], diff]), r1, r2) for r1, r2 in itertools.combinations(rs[::2], 2))
print("two GGX lobes + diffuse:", two)
three = min((minimax([B[a], B[c], B[d], diff]), a, c, d) for a, c, d in itertools.combinations(rs[::4], 3))
print("three GGX lobes + diffuse:", three)
