"""Why a TiO2 white is blue at the flop: the R-706 white basecoat's b* per geometry under isolated-sphere
Mie scattering and under dependent scattering (docs/validation.md, section 5, "Why the TiO2 white
turns blue at the flop").

    PYTHONPATH=$PWD python tools/white_flop_experiment.py        # ~1 min

Panel: 40 µm clear coat | 30 µm basecoat, titanium-white-r706 at 15 % by volume | white primer, n = 16,
D65 / 10°, 45° light.  Rows: the catalogue's Mie optics (number median 0.25 µm, gsd 1.4), then the
interference approximation of dependent scattering: the Mie phase function times the Percus–Yevick
hard-sphere structure factor S(q) at the paint's volume fraction (Wertheim 1963; Ashcroft & Lekner
1966), q = 2 k_binder sin(Θ/2), for a hard-sphere diameter d, renormalised, σ_s scaled by ∫ p S dΩ
(absorption unchanged).  An experiment, not an engine feature: the engine's pigments are independent
scatterers.  Then the same with the grade's 0.36 µm read as a number median.
"""

import sys

import numpy as np
import yaml

import flakedb.paint.components as components
from flakedb.match.fit import predict, recipe_from_doc
from flakedb.paint.catalog import load_catalog

ASPECULAR = [-15, 15, 25, 45, 75, 110]
PHI = 0.15


def percus_yevick_S(qd, phi):
    """Hard-sphere structure factor S(q) (Percus–Yevick, closed form) at q·d = qd (d the sphere diameter)
    and volume fraction phi; below qd 0.05 its q → 0 limit (1 − φ)⁴ / (1 + 2φ)² (the closed form loses
    digits there)."""
    A = np.maximum(np.asarray(qd, float), 0.05)
    al = (1 + 2 * phi) ** 2 / (1 - phi) ** 4
    be = -6 * phi * (1 + phi / 2) ** 2 / (1 - phi) ** 4
    ga = phi * al / 2
    s, c = np.sin(A), np.cos(A)
    G = (al / A**2 * (s - A * c) + be / A**3 * (2 * A * s + (2 - A**2) * c - 2)
         + ga / A**5 * (-A**4 * c + 4 * ((3 * A**2 - 6) * c + (A**3 - 6 * A) * s + 6)))
    return np.where(np.asarray(qd) < 0.05, (1 - phi) ** 4 / (1 + 2 * phi) ** 2, 1.0 / (1.0 + 24 * phi * G / A))


def with_structure_factor(pigment_optics, phi, d_um):
    """pigment_optics whose phase function and σ_s carry S(q) (see the module docstring)."""
    def optics(entry, wl, nb, mu=None, n_quad=None):
        po = pigment_optics(entry, wl, nb, mu=mu, n_quad=n_quad)
        if mu is None:
            return po
        k = 2 * np.pi * np.asarray(nb, float)[..., None] / (np.asarray(wl, float)[:, None] * 1e-3)   # 1/µm
        S = percus_yevick_S(2 * k * np.sqrt((1 - mu[None, :]) / 2) * d_um, phi)
        p = np.asarray(po.phase_function)
        f = np.trapezoid(p * S, mu, axis=1) / np.trapezoid(p, mu, axis=1)
        c_sca = np.asarray(po.c_sca_um2) * f
        return type(po)(np.asarray(po.c_ext_um2) - np.asarray(po.c_sca_um2) + c_sca, c_sca, po.g,
                        po.mean_volume_um3, p * S / f[:, None])
    return optics


def panel(median_um=None):
    white = {"species": "titanium-white-r706", "volume_fraction": PHI}
    if median_um is not None:
        white["median_diameter_um"] = median_um
    return {"flakedb": 1, "name": "white", "spectral": {"mode": "spectral", "range_nm": [380, 780], "step_nm": 10},
            "resolution": 16,
            "layers": [{"clearcoat": {"thickness_um": 40, "ior": 1.5, "roughness": 0}},
                       {"basecoat": {"thickness_um": 30, "ior": 1.5, "particles": [white]}},
                       {"primer": {"color": "white"}}]}


def main():
    cat = load_catalog(None)
    mie = components.pigment_optics
    print("aspecular " + " ".join(f"{a:>6d}" for a in ASPECULAR) + "   (b*)")
    for median in (None, 0.36):
        for d in (None, 0.25, 0.36):
            components.pigment_optics = mie if d is None else with_structure_factor(mie, PHI, d)
            try:
                lab = predict(recipe_from_doc(panel(median), catalog=cat), [(45.0, float(a)) for a in ASPECULAR],
                              n=16, catalog=cat).lab("10", "D65")
            finally:
                components.pigment_optics = mie
            tag = f"median {median or 0.25:g} µm, " + ("isolated Mie" if d is None else f"PY S(q), d {d:g} µm")
            print(f"{tag:34s}" + " ".join(f"{b:6.2f}" for b in lab[:, 2]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
