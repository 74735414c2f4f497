"""Formulation units of one paint layer: weight ↔ volume fractions, PVC and a CPVC estimate (pure functions).

Usage: ``volume_fractions(phi, w, rho, rho_binder)`` → φ (particles given by weight converted);
``weight_fractions(phi, rho, rho_binder)`` → w; ``cpvc_oil_absorption(phi, rho, oa)`` → CPVC.  Densities
in g/cm³, fractions as fractions (0.02 = 2 %), oil absorption in g oil / 100 g pigment.

Definitions (docs/formulation.md states them once; the dry film is the layer: binder and particles)
---------------------------------------------------------------------------------------------------
* Volume fraction φ_i: the particles' volume per layer volume, the model's loading (docs/model.md §3).
* Weight fraction w_i: the particles' mass per dry-film mass, w_i = ρ_i φ_i / M with the film's
  density M = ρ_b (1 − Σ_k φ_k) + Σ_k ρ_k φ_k (binder ρ_b fills what the particles leave).
* Some particles given by weight (set W) and the rest by volume (set V): from w_i M = ρ_i φ_i,

      M = [ρ_b (1 − Σ_V φ_j) + Σ_V ρ_j φ_j] / [1 − Σ_W w_i (1 − ρ_b / ρ_i)],   φ_i = w_i M / ρ_i,

  exact (no iteration); a layer given wholly by weight reduces to φ_i = (w_i/ρ_i) / (w_b/ρ_b + Σ w_k/ρ_k)
  with w_b = 1 − Σ w.  The denominator is ≥ 1 − Σ_W w_i > 0 whenever Σ_W w_i < 1.
* PVC = Σ_i φ_i, every particle (flakes included): the pigment volume concentration of the dry film.
* CPVC estimate from oil absorption (W. K. Asbeck, M. Van Loo, "Critical pigment volume relationships",
  Ind. Eng. Chem. 41, 1470 (1949); in the form CPVC = 1 / (1 + ρ OA / 93.5), 93.5 = 100 × the density
  of linseed oil, R. Lewarchik, UL Prospector Knowledge Center 2014): OA/100 g of oil wets 1 g of
  pigment, so ρ OA / 93.5 is the oil (binder) volume one pigment volume holds at the CPVC.  A blend:
  those volumes averaged with the blend's volume fractions (the oil absorption of a non-flocculated
  mix, as that article does), CPVC = 1 / (1 + Σ φ_i ρ_i OA_i / (93.5 Σ φ_i)).  An estimate: a
  measured oil absorption of the blend (better packing of mixed sizes) gives a higher CPVC.
"""

from __future__ import annotations

import numpy as np

#: 100 × the density of linseed oil (g/cm³), the oil of the oil-absorption test (module docstring).
LINSEED_OIL_100_DENSITY = 93.5


def volume_fractions(volume_fraction, weight_fraction, density_g_cm3, binder_density_g_cm3) -> np.ndarray:
    """φ (P,) of a layer's particles: each given either by volume (``volume_fraction``, NaN where given
    by weight) or by weight (``weight_fraction``, NaN where given by volume); ``density_g_cm3`` (P,)
    (NaN allowed only for a particle given by volume in a layer with none by weight).  Module docstring:
    the exact formula.  Raises ValueError when a needed density is missing or Σ w ≥ 1.

    Hand check: 10 % by weight of a 4.23 g/cm³ pigment in a 1.18 g/cm³ binder is
    (0.1/4.23) / (0.1/4.23 + 0.9/1.18) = 0.0236407 / 0.786353 = 0.030064 by volume:

    >>> round(float(volume_fractions([np.nan], [0.1], [4.23], 1.18)[0]), 6)
    0.030064
    """
    phi = np.asarray(volume_fraction, float).copy()
    w = np.asarray(weight_fraction, float)
    rho = np.asarray(density_g_cm3, float)
    by_w = ~np.isnan(w)
    if not by_w.any():
        return phi
    if np.any(np.isnan(rho[by_w | ~np.isnan(phi)])):
        raise ValueError("a density is needed for every particle of a layer that has one given by weight")
    if w[by_w].sum() >= 1.0:
        raise ValueError(f"the weight fractions add up to {w[by_w].sum():.4g}; they must stay below 1")
    rb = float(binder_density_g_cm3)
    by_v = ~by_w
    M = (rb * (1.0 - phi[by_v].sum()) + (rho[by_v] * phi[by_v]).sum()) / (1.0 - (w[by_w] * (1.0 - rb / rho[by_w])).sum())
    phi[by_w] = w[by_w] * M / rho[by_w]
    return phi


def film_density_g_cm3(volume_fraction, density_g_cm3, binder_density_g_cm3) -> float:
    """M = ρ_b (1 − Σ φ) + Σ ρ φ: the dry film's density (g/cm³)."""
    phi = np.asarray(volume_fraction, float)
    return float(binder_density_g_cm3) * (1.0 - phi.sum()) + float(np.dot(np.asarray(density_g_cm3, float), phi))


def weight_fractions(volume_fraction, density_g_cm3, binder_density_g_cm3) -> np.ndarray:
    """w_i = ρ_i φ_i / M (P,), the inverse of :func:`volume_fractions` (module docstring)."""
    phi = np.asarray(volume_fraction, float)
    return np.asarray(density_g_cm3, float) * phi / film_density_g_cm3(phi, density_g_cm3, binder_density_g_cm3)


def cpvc_oil_absorption(volume_fraction, density_g_cm3, oil_absorption_g_100g) -> float:
    """CPVC estimate of a blend from its particles' oil absorptions (module docstring, Asbeck & Van Loo 1949).

    Lewarchik's rutile example (OA 20, ρ 4.2 g/cm³): 1 / (1 + 84 / 93.5) = 0.5268:

    >>> round(cpvc_oil_absorption([0.1], [4.2], [20.0]), 4)
    0.5268
    """
    phi = np.asarray(volume_fraction, float)
    oil_per_volume = np.asarray(density_g_cm3, float) * np.asarray(oil_absorption_g_100g, float) / LINSEED_OIL_100_DENSITY
    return float(1.0 / (1.0 + np.dot(phi, oil_per_volume) / phi.sum()))
