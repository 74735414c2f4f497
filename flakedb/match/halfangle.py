"""Which colour a specular-flake paint can give at a set of geometries: the half-angle test (docs/validation.md §4a).

A flake that reflects specularly sends light from the light to the viewer only when its normal is the half
vector h of the two directions *inside the binder* (refracted at the clear coat); it then sees the light at
the difference angle θ_d' = ∠(ω_i', h).  Its reflectance spectrum (thin films, interference, the thickness
spread) depends on θ_d' alone; the orientation density only scales how much of it arrives (Ergun et al. §3,
docs/model.md §3).  So at geometries with the same θ_d' the singly reflected light has one spectrum, and the
colours differ only in lightness.  :func:`common_chromaticity_worst_de00` is the least worst-angle ΔE00 that any
colour sharing one chromaticity across given geometries can reach against measured colours there: a measured
paint whose colour at equal θ_d' changes hue (a diffraction grating does: its colour moves with the
angle off the specular) is out of reach of such a paint by that amount.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from flakedb.colour import cie_tables
from flakedb.colour.colorimetry import XYZ_to_Lab, delta_E_2000

__all__ = ["binder_half_angles_deg", "common_chromaticity_worst_de00", "lab_to_XYZ_d65"]


def binder_half_angles_deg(geometries_deg, n_binder=1.5) -> tuple[np.ndarray, np.ndarray]:
    """(θ_h', θ_d') [deg], each (G,), of in-plane geometries (G, 2) (illumination θ_i, aspecular γ; viewer at
    θ_v = θ_i − γ, the specular at γ = 0, ASTM E2194's sign as :mod:`flakedb.match.targets`) after refraction
    into a smooth coat of real index ``n_binder``: θ' = asin(sin θ / n) for both directions (Snell), then the
    half vector of the refracted pair and the angle between it and the refracted light."""
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


def lab_to_XYZ_d65(lab) -> np.ndarray:
    """XYZ (Y = 1 for white) of CIELAB under D65 / 2° as :func:`flakedb.colour.colorimetry.XYZ_to_Lab` with
    white "D65" (CIE 15:2004 §8.2.1 inverted: t = f³ above 24/116, else (f − 16/116) · 108/841)."""
    lab = np.asarray(lab, dtype=float)
    x, y = cie_tables.D65_XY_2DEG
    white = np.array([x / y, 1.0, (1.0 - x - y) / y])
    fy = (lab[..., 0] + 16.0) / 116.0
    f = np.stack([fy + lab[..., 1] / 500.0, fy, fy - lab[..., 2] / 200.0], axis=-1)
    return np.where(f > 24.0 / 116.0, f ** 3, (f - 16.0 / 116.0) * 108.0 / 841.0) * white


def common_chromaticity_worst_de00(lab, starts=24, seed=0) -> tuple[float, np.ndarray]:
    """(least worst ΔE00, its chromaticity xy (2,)) over one CIE xy shared by colours (G, 3), each keeping its
    own luminance Y: min over xy of max_g ΔE00(lab_g, Lab(Y_g, xy)).  Nelder–Mead from ``starts`` seeded points
    in the gamut of real colours' neighbourhood (x, y in 0.2-0.45); the max of ΔE00 is continuous in xy, a
    local search from many starts finds its minimum (an upper estimate of the true minimum: a miss can only make
    the number larger).  One colour, or colours of one chromaticity, give 0."""
    lab = np.atleast_2d(np.asarray(lab, dtype=float))
    Y = lab_to_XYZ_d65(lab)[:, 1]

    def worst(xy):
        x, y = xy
        if not (x > 0 and y > 0.01 and x + y < 1):
            return 1e3
        xyz = Y[:, None] * np.array([x / y, 1.0, (1.0 - x - y) / y])[None, :]
        return float(delta_E_2000(lab, XYZ_to_Lab(xyz)).max())

    rng = np.random.default_rng(seed)
    x0s = np.vstack([[cie_tables.D65_XY_2DEG], rng.uniform(0.2, 0.45, (max(1, starts) - 1, 2))])
    best = min((minimize(worst, x0, method="Nelder-Mead", options=dict(xatol=1e-7, fatol=1e-9, maxiter=2000))
                for x0 in x0s), key=lambda r: r.fun)
    return float(best.fun), np.asarray(best.x)
