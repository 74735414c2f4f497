"""Which colour a specular-flake paint can give at a set of geometries: the half-angle test (docs/validation.md §4a).

A flake that reflects specularly sends light from the light to the viewer only when its normal is the half
vector h of the two directions *inside the binder* (refracted at the clear coat); it then sees the light at
the difference angle θ_d' = ∠(ω_i', h).  Its reflectance spectrum (thin films, interference, the thickness
spread) depends on θ_d' alone; the orientation density only scales how much of it arrives (Ergun et al. §3,
docs/model.md §3).  So at geometries with the same θ_d' the singly reflected light has one spectrum, and the
colours differ only in lightness.  :func:`common_chromaticity_worst_de00` is the least worst-angle ΔE00 that any
colour sharing one chromaticity across given geometries can reach against measured colours there: a measured
paint whose colour at equal θ_d' changes hue (a diffraction grating does: its colour moves with the
angle off the specular) is out of reach of such a paint by that amount.  A flake *population* is one stack with
its thickness spread and one orientation law; a paint of two populations whose orientation laws differ mixes
two spectra in proportions that change with θ_h': :func:`two_spectra_worst_de00` bounds that case (any two
chromaticities, any proportions per geometry).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from flakedb.colour import cie_tables
from flakedb.colour.colorimetry import Lab_to_XYZ, XYZ_to_Lab, delta_E_2000

__all__ = ["binder_half_angles_deg", "common_chromaticity_worst_de00", "two_spectra_worst_de00"]


def binder_half_angles_deg(geometries_deg, n_binder=1.5) -> tuple[np.ndarray, np.ndarray]:
    """(θ_h', θ_d') [deg], each (G,), of in-plane geometries (G, 2) (illumination θ_i, aspecular γ; viewer at
    θ_v = θ_i − γ, the specular at γ = 0, ASTM E2194's sign as :mod:`flakedb.match.targets`) after refraction
    into a smooth coat of real index ``n_binder``: θ' = asin(sin θ / n) for both directions (Snell), then the
    half vector of the refracted pair and the angle between it and the refracted light.

    At the specular the half vector is the normal and θ_d' is the refracted 45°, asin(sin 45° / 1.5):

    >>> th, td = binder_half_angles_deg([(45.0, 0.0)])
    >>> round(float(th[0]), 9), bool(np.isclose(td[0], np.degrees(np.arcsin(np.sin(np.radians(45.0)) / 1.5))))
    (0.0, True)
    """
    g = np.atleast_2d(np.asarray(geometries_deg, dtype=float))
    ti = np.arcsin(np.sin(np.radians(g[:, 0])) / n_binder)
    tv = np.arcsin(np.sin(np.radians(g[:, 0] - g[:, 1])) / n_binder)
    wi = np.stack([-np.sin(ti), np.zeros_like(ti), np.cos(ti)], axis=1)       # towards the light
    wo = np.stack([np.sin(tv), np.zeros_like(tv), np.cos(tv)], axis=1)        # towards the viewer
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    th = np.degrees(np.arccos(np.clip(h[:, 2], -1, 1)))
    td = np.degrees(np.arccos(np.clip(np.sum(wi * h, axis=1), -1, 1)))
    return th, td


def common_chromaticity_worst_de00(lab, grid_step=0.005, refine=5) -> tuple[float, np.ndarray]:
    """(least worst ΔE00, its chromaticity xy (2,)) over one CIE xy shared by colours (G, 3), each keeping its
    own luminance Y: min over xy of max_g ΔE00(lab_g, Lab(Y_g, xy)).  Global by a grid over x, y in 0.10-0.60
    (``grid_step``; every chromaticity a reflecting surface under D65 shows with C* up to ~60 lies inside), then
    Nelder–Mead from the ``refine`` best grid points and D65; the max of ΔE00 is continuous in xy, so the grid's
    best point is within one grid cell of the minimum and the local search finishes it.  One colour, or colours
    of one chromaticity, give 0."""
    lab = np.atleast_2d(np.asarray(lab, dtype=float))
    Y = Lab_to_XYZ(lab)[:, 1]

    def lab_at(xy):                                                    # xy (..., 2) -> Lab (..., G, 3)
        x, y = xy[..., 0, None], xy[..., 1, None]
        xyz = np.stack([x / y, np.ones_like(x), (1.0 - x - y) / y], axis=-1) * Y[:, None]
        return XYZ_to_Lab(xyz)

    def worst(xy):
        xy = np.asarray(xy, float)
        if not (xy[0] > 0 and xy[1] > 0.01 and xy.sum() < 1):
            return 1e3
        return float(delta_E_2000(lab, lab_at(xy)).max())

    g = np.arange(0.10, 0.60 + 1e-12, float(grid_step))
    xy = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    xy = xy[xy.sum(axis=1) < 0.95]
    coarse = delta_E_2000(np.broadcast_to(lab, (len(xy),) + lab.shape), lab_at(xy)).max(axis=1)
    x0s = np.vstack([[cie_tables.D65_XY_2DEG], xy[np.argsort(coarse)[:max(1, refine)]]])
    best = min((minimize(worst, x0, method="Nelder-Mead", options=dict(xatol=1e-7, fatol=1e-9, maxiter=2000))
                for x0 in x0s), key=lambda r: r.fun)
    return float(best.fun), np.asarray(best.x)


def two_spectra_worst_de00(lab, starts=40, seed=0, n_mix=201) -> tuple[float, np.ndarray]:
    """(least worst ΔE00, the two chromaticities (2, 2)) of colours (G, 3) that are each an additive mixture, in
    any proportion, of two spectra of common chromaticities, each colour keeping its luminance Y: the mixtures
    of two lights lie on the segment between their xy (additive mixing is linear in XYZ), so
    min over xy_1, xy_2 of max_g min over the segment (``n_mix`` points, uniform in the XYZ weight of two unit-Y
    lights) of ΔE00.  Nelder–Mead from ``starts`` seeded points in 4-D: a local search, so the value is an
    upper estimate of the minimum (not proven global, unlike the grid of :func:`common_chromaticity_worst_de00`);
    never above that function's value, which is the degenerate segment."""
    lab = np.atleast_2d(np.asarray(lab, dtype=float))
    Y = Lab_to_XYZ(lab)[:, 1]
    t = np.linspace(0.0, 1.0, int(n_mix))[:, None]
    ref = np.repeat(lab[:, None, :], t.size, axis=1)

    def unit(xy):
        return np.array([xy[0] / xy[1], 1.0, (1.0 - xy[0] - xy[1]) / xy[1]])

    def worst(p):
        a, b = p[:2], p[2:]
        if min(a.min(), b.min()) <= 0 or min(a[1], b[1]) < 0.01 or max(a.sum(), b.sum()) >= 1:
            return 1e3
        mix = t * unit(a) + (1.0 - t) * unit(b)                         # (n_mix, 3), Y = 1 along it
        labs = XYZ_to_Lab(Y[:, None, None] * mix[None, :, :])           # (G, n_mix, 3)
        return float(delta_E_2000(ref, labs).min(axis=1).max())

    one, xy1 = common_chromaticity_worst_de00(lab)
    rng = np.random.default_rng(seed)
    x0s = np.vstack([np.r_[xy1, xy1 + 0.01], rng.uniform(0.15, 0.5, (max(1, starts) - 1, 4))])
    best = min((minimize(worst, x0, method="Nelder-Mead", options=dict(xatol=1e-6, fatol=1e-8, maxiter=4000))
                for x0 in x0s), key=lambda r: r.fun)
    return min(float(best.fun), one), np.asarray(best.x).reshape(2, 2)
