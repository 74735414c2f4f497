"""Kubelka–Munk (K, S) ↔ radiative-transfer (σ_a, σ_s, g) coefficients, and the KM reflectances.

Usage card::

    sigma_a, sigma_s = km_to_rt(K, S, g)          # 1/µm in, 1/µm out (any consistent length unit)
    K, S = rt_to_km(sigma_a, sigma_s, g)
    R_inf = km_reflectance_infinite(K, S)          # hemispherical reflectance of an opaque layer
    R = km_reflectance(K, S, thickness, R_g)       # a layer of thickness over a substrate of reflectance R_g
    a_phi, s_phi = relative_km_to_specific(K_rel, S_rel, S_ref, phi, g)   # database K, S relative to a white's S

All four broadcast over arrays (bands, concentrations).  Per unit concentration in, per unit
concentration out: the relations are linear in (σ_a, σ_s) ↔ (K, S), so published *specific* K and S
(per unit volume fraction) convert to a tinter's σ_a/φ and σ_s/φ (:mod:`flakedb.match.tinter`).

The conversion (``method="Star1988"``)
---------------------------------------
    K = 2 σ_a,        S = ¾ σ_s (1 − g) − ¼ σ_a

(Star, Marijnissen & van Gemert 1988, Phys. Med. Biol. 33, 437, eq. 9–10; the same as Gate 1974, Appl.
Opt. 13, 236, and Thennadil 2008, JOSA A 25, 1480, for diffuse illumination.)  Derivation: in a
diffuse light field the mean path per unit depth is 2 (Kubelka's "average path length" of a
Lambertian field), so K = 2 σ_a; and KM's attenuation exponent in depth, √(K (K + 2S)), equals the
diffusion-theory one, √(3 σ_a (σ_a + σ_s (1 − g))), when S = ¾ σ_s′ − ¼ σ_a (σ_s′ = σ_s (1 − g), the
reduced scattering coefficient).  Inverse: σ_a = K/2, σ_s = (S + K/8) · 4 / (3 (1 − g)).

Assumptions: a diffuse (Lambertian) light field inside the layer (far from the illuminated surface
and from collimated light), scattering much stronger than absorption (the diffusion limit), no
interfaces (index-matched; for a coated paint apply Saunderson's correction to measured data first),
and g known separately (KM sees only σ_s (1 − g): any g with the same reduced scattering gives nearly
the same diffuse reflectance, so g is a choice, not a result, when seeding from KM data).  The error
of the relation against the adding-doubling solver (diffuse albedo of an index-matched slab) is
measured in docs/calibration.md ("Kubelka–Munk data") and asserted in tests/optics/test_kubelka_munk.py.

The conversion ``method="R-inf-matched"`` (KM → RT only)
-------------------------------------------------------
    σ_a = K/2,   σ_s/σ_a such that R∞ of the radiative transfer equation (the adding-doubling solver: diffuse
    illumination, hemispherical reflectance, index-matched semi-infinite HG medium) equals KM's R∞.
Star's S relation holds where scattering dominates; where absorption does (dark masstones of strong organic
pigments, S ≪ K) it gives a medium that reflects up to 0.055 more than KM's R∞ (measured: docs/colourants.md)
and scatters at least σ_a/3 however transparent the pigment.  Matching R∞ keeps KM's K (the thin-layer
absorption) and KM's opaque colour exactly, at every albedo.

The KM reflectances (Kubelka 1948, JOSA 38, 448, eq. 5 and 15; a = 1 + K/S, b = √(a² − 1))
    R∞ = a − b,
    R(X; R_g) = (1 − R_g (a − b coth(bSX))) / (a − R_g + b coth(bSX)).
"""

from __future__ import annotations

import numpy as np

#: The conversions :func:`km_to_rt` knows (the registry the ``method=`` argument names): "Star1988" (closed
#: form, both ways) and "R-inf-matched" (from KM to RT only: it needs the solver's R∞ table).
KM_RT_METHODS = ("Star1988", "R-inf-matched")


def _check_method(method):
    if method not in KM_RT_METHODS:
        raise ValueError(f"unknown Kubelka-Munk conversion {method!r}; choose one of {', '.join(KM_RT_METHODS)}")


def rt_to_km(sigma_a, sigma_s, g=0.0, method="Star1988"):
    """(K, S) of a medium with absorption σ_a, scattering σ_s (1/length) and mean cosine g (module
    docstring: K = 2 σ_a, S = ¾ σ_s (1 − g) − ¼ σ_a).  S < 0 where σ_s (1 − g) < σ_a / 3: the relation
    is then outside its range (an absorber, not a diffuser) and the value says so.

    >>> K, S = rt_to_km(0.5, 10.0, 0.6)
    >>> float(K), float(S)
    (1.0, 2.875)
    """
    _check_method(method)
    if method != "Star1988":
        raise ValueError(f"rt_to_km: only 'Star1988' has a closed form from RT to KM, not {method!r}")
    sa, ss, g = (np.asarray(v, dtype=float) for v in (sigma_a, sigma_s, g))
    return 2.0 * sa, 0.75 * ss * (1.0 - g) - 0.25 * sa


def km_to_rt(K, S, g=0.0, method="Star1988", r_inf_table=None):
    """(σ_a, σ_s) from KM (K, S) (1/length) for a chosen mean cosine g < 1.  Both methods take σ_a = K/2
    (Kubelka's mean path 2 of a diffuse field: a thin layer absorbs alike in both models).

    * ``"Star1988"``: σ_s = (S + K/8) · 4 / (3 (1 − g)) (the inverse of :func:`rt_to_km`; the diffusion limit).
    * ``"R-inf-matched"``: σ_s = σ_a · q with q the ratio σ_s/σ_a at which the radiative-transfer R∞ (diffuse
      illumination, hemispherical, index-matched, HG g) equals KM's R∞ = a − b; ``r_inf_table`` = (q grid,
      R∞ grid) of the solver at this g, increasing (:func:`flakedb.paint.km_palette.semi_infinite_albedo`).
      Exact for the opaque masstone by construction, σ_s → 0 as S → 0 (a transparent absorber stays
      transparent, where Star's relation keeps σ_s(1 − g) ≥ σ_a/3), and Star's relation as S/K → ∞.

    >>> sa, ss = km_to_rt(*rt_to_km(0.3, 4.0, 0.5), 0.5)
    >>> round(float(sa), 12), round(float(ss), 12)
    (0.3, 4.0)
    >>> q = np.array([0.0, 1.0, 3.0]); R = np.array([0.0, 0.1, 0.3])      # a made-up table
    >>> [round(float(v), 12) for v in km_to_rt(2.0, 0.0, 0.2, "R-inf-matched", (q, R))]   # S = 0: no scattering
    [1.0, 0.0]
    """
    _check_method(method)
    K, S, g = (np.asarray(v, dtype=float) for v in (K, S, g))
    if np.any(g >= 1.0) or np.any(g <= -1.0):
        raise ValueError(f"km_to_rt: the mean cosine g must lie in (-1, 1), got {g!r}")
    if np.any(K < 0) or np.any(S < 0):
        raise ValueError("km_to_rt: K and S must be >= 0 (absorption and scattering coefficients)")
    if method == "Star1988":
        return 0.5 * K, (S + 0.125 * K) * 4.0 / (3.0 * (1.0 - g))
    if r_inf_table is None:
        raise ValueError("km_to_rt: method 'R-inf-matched' needs r_inf_table = (sigma_s/sigma_a grid, R_inf grid)")
    q_grid, r_grid = (np.asarray(v, dtype=float) for v in r_inf_table)
    r_km = km_reflectance_infinite(K, S)
    if np.any(r_km > r_grid[-1]):
        raise ValueError(f"km_to_rt: R_inf {float(r_km.max()):.6g} lies above the table's end {float(r_grid[-1]):.6g} "
                         f"(extend its sigma_s/sigma_a range)")
    # q(R) interpolated in log(q) (R∞ is smooth in log q; q = 0 ↔ R = 0 stays exact)
    logq = np.log(np.maximum(q_grid, 1e-300))
    q = np.where(r_km > 0.0, np.exp(np.interp(r_km, r_grid, logq)), 0.0)
    q = np.where(r_km >= r_grid[1], q, r_km / r_grid[1] * q_grid[1])   # below the first step: R ∝ q (single scattering)
    return 0.5 * K, 0.5 * K * q


def km_reflectance_infinite(K, S):
    """R∞ = 1 + K/S − √((K/S)² + 2 K/S) (Kubelka 1948 eq. 5), the hemispherical reflectance of an
    opaque layer; 1 for K = 0, 0 for S = 0.

    >>> round(float(km_reflectance_infinite(1.0, 4.5)), 6)
    0.519494
    """
    K, S = np.asarray(K, dtype=float), np.asarray(S, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(S > 0, K / np.where(S > 0, S, 1.0), np.inf)
        r = np.where(np.isfinite(q), 1.0 + q - np.sqrt(q * q + 2.0 * q), 0.0)
    return r


def km_reflectance(K, S, thickness, R_g):
    """Hemispherical reflectance of a KM layer of ``thickness`` (the unit of 1/K) over a substrate of
    reflectance ``R_g`` (Kubelka 1948 eq. 15; module docstring).  S > 0 required.

    Thick layers tend to R∞; a clear layer (K = 0) over a black substrate reflects S X / (1 + S X):

    >>> round(float(km_reflectance(1.0, 4.5, 1e3, 0.0)), 6), round(float(km_reflectance(1e-12, 2.0, 0.5, 0.0)), 6)
    (0.519494, 0.5)
    """
    K, S, X, Rg = (np.asarray(v, dtype=float) for v in (K, S, thickness, R_g))
    a = 1.0 + K / S
    b = np.sqrt(np.maximum(a * a - 1.0, 0.0))
    bsx = b * S * X
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # b coth(bSX), and its K → 0 limit 1/(SX)
        bcoth = np.where(bsx > 1e-8, b / np.tanh(np.maximum(bsx, 1e-300)), 1.0 / (S * X))
    return (1.0 - Rg * (a - bcoth)) / (a - Rg + bcoth)




def relative_km_to_specific(K_rel, S_rel, S_ref, phi_pigment, g=0.0, method="Star1988", r_inf_table=None):
    """(σ_a/φ, σ_s/φ) per unit pigment volume fraction (the unit of ``S_ref``, e.g. 1/µm) of a paint
    whose KM K and S are given *relative* to a reference paint's S (the reference's S is 1 at every
    band, as in two-constant databases normalised to their white), its pigment at volume fraction
    ``phi_pigment``:

        K = K_rel · S_ref,  S = S_rel · S_ref   (absolute, per band; S_ref the reference's absolute S)
        (σ_a, σ_s) = km_to_rt(K, S, g) / φ      (:func:`km_to_rt`, ``method`` as there)

    Star1988: linear in (K_rel, S_rel) and S_ref, inverse in φ: an error in the reference's S or the pigment
    fraction scales both coefficients alike (K/S, hence the opaque masstone, is unchanged).

    >>> a, s = relative_km_to_specific(2.0, 0.5, 4.0, 0.1, 0.0)
    >>> round(float(a), 12), round(float(s), 12)      # K = 8, S = 2: σ_a = 4, σ_s = (2 + 1) · 4/3 = 4
    (40.0, 40.0)
    """
    phi = np.asarray(phi_pigment, dtype=float)
    if np.any(phi <= 0) or np.any(phi > 1):
        raise ValueError(f"relative_km_to_specific: the pigment volume fraction must lie in (0, 1], got {phi!r}")
    S_ref = np.asarray(S_ref, dtype=float)
    sa, ss = km_to_rt(np.asarray(K_rel, float) * S_ref, np.asarray(S_rel, float) * S_ref, g, method=method,
                      r_inf_table=r_inf_table)
    return sa / phi, ss / phi


__all__ = ["KM_RT_METHODS", "km_reflectance", "km_reflectance_infinite", "km_to_rt", "relative_km_to_specific",
           "rt_to_km"]
