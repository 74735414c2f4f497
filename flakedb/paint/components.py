"""The solver medium (or bottom) of each ingredient of a recipe, and the rules they share (docs/model.md §3, §6):
flake optics on an adaptive cosine grid (:func:`adaptive_flake_optics`), Mie pigments, tinters, custom media, a metal
base; loadings (aρ, number densities); the RGB-mode conversions.  :func:`flakedb.paint.mapping.build_paint`
assembles them into a stack (the module docstring there states the mapping).
"""

from __future__ import annotations

import copy
import hashlib
import json

import numpy as np
from numpy.polynomial.legendre import leggauss

from flakedb.colour.colorimetry import spectra_to_rgb_mode
from flakedb.optics.fresnel import fresnel_conductor
from flakedb.paint.catalog import catalog_distribution
from flakedb.paint.limits import is_rough_interface
from flakedb.paint.materials import refractive_index
from flakedb.paint.recipe import CatalogParticle, Spectrum
from flakedb.paint.species import flake_reflectance_transmittance, pigment_optics, tinter_coefficients
from flakedb.rt.basis.legendre import legendre_moments_gauss, legendre_series, truncate_legendre
from flakedb.rt.scattering.grating_flake import GratingFlakeMedium
from flakedb.rt.scattering.media import FlakeMedium, PhaseMedium, vmf_mean_cosine
from flakedb.rt.scattering.microflake import DEFAULT_DISTRIBUTION, FlakeOptics, extinction_Ergun
from flakedb.rt.common.reuse import active_cache, array_key
from flakedb.rt.adding.stack import RoughConductor
from flakedb.rt.scattering.stored import StoredPigmentMedium


#: Flake-cosine grid: start from FLAKE_C_START nodes c = cos θ, θ uniform on [0°, 90°], and bisect
#: every interval whose midpoint differs from the linear interpolant by more than FLAKE_C_TOL in R
#: or T (any band), up to FLAKE_C_MAX nodes.  Thin-film fringes in c are narrow (the 120 nm TiO2 /
#: 300 nm SiO2 pearlescent flake has R dropping from 0.26 to 0.001 within Δc = 0.015 at 400 nm), so
#: a fixed grid is not enough: 48 θ-uniform nodes leave errors of 0.15 there.  Measured against a
#: 20001-node grid (10 nm bands): max error 1.0e-3 for every catalogue flake with 68 (metallic) to
#: 323 (pearlescent) nodes at a tolerance of 1e-3.  That table error moved the composed BSDF of the
#: fig7 pearlescent paints by 1.7e-3 of its maximum (ΔE00 0.024) against a 1e-4 table (issue #11,
#: docs/store.md), above the store's 1e-3 acceptance; at 1e-4: 192 (metallic) to 1003 (pearlescent)
#: nodes, a few tenths of a second of thin-film evaluation more, no change in the projection's cost
#: (the kernel basis has at most one row per band).
FLAKE_C_START = 33
FLAKE_C_TOL = 1e-4
FLAKE_C_MAX = 2049
#: Scattering-angle step of the tabulated Mie phase function (uniform in Θ, dense near forward in
#: cos Θ).  Error of linear interpolation in cos Θ measured in tests/test_compose.py.
PHASE_THETA_STEP_DEG = 0.5


def recipe_top_alpha(recipe) -> float:
    """The Beckmann roughness α of ``recipe``'s top interface: its clear coat's roughness where that coat is
    a rough interface (:func:`flakedb.paint.limits.is_rough_interface`: α > 0 and binder index ≠ 1), else 0
    (a smooth top, or none).  The one place the rough-top rule is applied to a recipe."""
    cc = recipe.clearcoat
    alpha = 0.0 if cc is None else float(cc.roughness)
    return alpha if is_rough_interface(recipe.binder_ior, alpha) else 0.0


def recipe_alpha(p) -> float:
    """The orientation spread α of a catalogue flake in a recipe: its ``orientation_alpha`` override, else
    the catalogue's (the spread of :func:`recipe_distribution`)."""
    return float(p.orientation_alpha if p.orientation_alpha is not None else p.entry["orientation_alpha"]["value"])


def recipe_distribution(p) -> str:
    """The flake-normal distribution (a key of :data:`flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS`) of a
    catalogue or custom flake in a recipe: its ``orientation_distribution``, else the catalogue entry's,
    else Beckmann (the paper's eq. 5; every catalogue entry and store written before the field)."""
    own = getattr(p, "orientation_distribution", None)
    if own is not None:
        return str(own)
    return catalog_distribution(getattr(p, "entry", None) or {})


def flake_cos_grid(n=FLAKE_C_START) -> np.ndarray:
    """c = cos θ, θ uniform on [0°, 90°], ascending, exactly 0 and 1 at the ends (n,)."""
    c = np.cos(np.linspace(0.5 * np.pi, 0.0, int(n)))
    c[0], c[-1] = 0.0, 1.0
    return c


def adaptive_flake_optics(fn, tol=FLAKE_C_TOL, n_start=FLAKE_C_START, max_nodes=FLAKE_C_MAX):
    """Tabulate ``R, T = fn(c)`` ((W, nc) each) on a c grid refined until linear interpolation is
    within ``tol`` at every interval midpoint (all bands), or ``max_nodes`` would be exceeded.

    Returns ``(c, R, T, max_midpoint_error)``; the error is that of the last refinement pass
    (≤ tol unless the node cap stopped it).  An interval that passed keeps its midpoint and error, so
    each pass evaluates ``fn`` only at the midpoints of the intervals the last one split (``fn`` acts on
    each c alone: the table is the one that re-evaluating every midpoint gives).
    """
    c = flake_cos_grid(n_start)
    R, T = fn(c)
    mid = 0.5 * (c[:-1] + c[1:])
    Rm, Tm = fn(mid)
    while True:
        err = np.maximum(np.abs(Rm - 0.5 * (R[:, :-1] + R[:, 1:])),
                         np.abs(Tm - 0.5 * (T[:, :-1] + T[:, 1:]))).max(axis=0)
        bad = err > tol
        if not bad.any() or c.size + int(bad.sum()) > max_nodes:
            return c, R, T, float(err.max())
        # node i of the refined grid: the old nodes with each split interval's midpoint after its left node
        split = np.flatnonzero(bad)
        c = np.insert(c, split + 1, mid[split])
        R = np.insert(R, split + 1, Rm[:, split], axis=1)
        T = np.insert(T, split + 1, Tm[:, split], axis=1)
        # the refined grid's intervals: a kept one per passed interval, two halves per split one
        new = np.zeros(c.size - 1, bool)
        pos = split + np.arange(split.size)  # the left half of each split interval in the refined grid
        new[pos] = new[pos + 1] = True
        mid = 0.5 * (c[:-1] + c[1:])
        keep = np.flatnonzero(~new)
        Rn, Tn = fn(mid[new])
        Rm2 = np.empty((R.shape[0], mid.size))
        Tm2 = np.empty_like(Rm2)
        Rm2[:, keep], Tm2[:, keep] = Rm[:, ~bad], Tm[:, ~bad]
        Rm2[:, new], Tm2[:, new] = Rn, Tn
        Rm, Tm = Rm2, Tm2


def phase_cos_grid(step_deg=PHASE_THETA_STEP_DEG) -> np.ndarray:
    """cos Θ, Θ uniform from 180° to 0° in ``step_deg`` steps, ascending from −1 to 1."""
    m = int(round(180.0 / step_deg)) + 1
    c = np.cos(np.linspace(np.pi, 0.0, m))
    c[0], c[-1] = -1.0, 1.0
    return c


def normalise_phase_table(cos_theta, values) -> tuple[np.ndarray, np.ndarray]:
    """Scale a tabulated phase function (…, M) so that its linear interpolant in cos Θ integrates to 1
    over the sphere (2π ∫ p dcosΘ by the trapezoidal rule, exact for the interpolant).

    Returns ``(normalised values, the integrals before scaling)``.

    A Henyey–Greenstein phase function tabulated on :func:`phase_cos_grid` (0.5° steps) integrates to 1
    within 1e-5 before the scaling, exactly after it:

    >>> from flakedb.rt.scattering.microflake import phase_HG
    >>> c = phase_cos_grid()
    >>> p, before = normalise_phase_table(c, phase_HG(c, 0.3)[None])
    >>> bool(abs(before[0] - 1.0) < 1e-5), round(float(2 * np.pi * np.trapezoid(p[0], c)), 12)
    (True, 1.0)
    """
    v = np.asarray(values, float)
    integral = 2.0 * np.pi * np.trapezoid(v, np.asarray(cos_theta, float), axis=-1)
    return v / np.asarray(integral)[..., None], integral


# ----------------------------------------------------------------------------------------------
# Loadings (docs/model.md §3)
# ----------------------------------------------------------------------------------------------


def flake_a_rho_from_volume_fraction(volume_fraction, flake_thickness_um) -> float:
    """aρ (1/µm) of flakes of thickness ``flake_thickness_um`` at ``volume_fraction``: φ / t (docs/model.md §3)."""
    return float(volume_fraction) / float(flake_thickness_um)


def flake_a_rho_from_optical_depth(optical_depth, layer_um, alpha, optics, distribution=DEFAULT_DISTRIBUTION) -> float:
    """aρ (1/µm) such that σ_t(μ = 1) · d = τ for flakes of ``optics`` (channel 0) and spread α of ``distribution``."""
    s1 = float(np.atleast_1d(extinction_Ergun(np.array([1.0]), alpha, optics, 1.0,
                                              distribution=distribution))[0].ravel()[0])
    return float(optical_depth) / (float(layer_um) * s1)


def pigment_number_density(volume_fraction, mean_volume_um3) -> float:
    """ρ (1/µm³) = volume fraction / mean particle volume."""
    return float(volume_fraction) / float(mean_volume_um3)


# ----------------------------------------------------------------------------------------------
# RGB mode conversions
# ----------------------------------------------------------------------------------------------


def flake_rt_tospectra_to_rgb_mode(R, T, wl) -> tuple[np.ndarray, np.ndarray, float]:
    """(W, nc) spectra → (3, nc) RGB-mode R and T, clipped to [0, 1] with R + T ≤ 1; and the largest clip."""
    Rr = spectra_to_rgb_mode(np.asarray(R).T, wl).T
    Tr = spectra_to_rgb_mode(np.asarray(T).T, wl).T
    Rc, Tc = np.clip(Rr, 0.0, 1.0), np.clip(Tr, 0.0, 1.0)
    s = Rc + Tc
    scale = np.where(s > 1.0, 1.0 / np.maximum(s, 1e-300), 1.0)
    Rc, Tc = Rc * scale, Tc * scale
    clip = float(max(np.abs(Rc - Rr).max(), np.abs(Tc - Tr).max()))
    return Rc, Tc, clip


def pigment_tospectra_to_rgb_mode(c_ext, c_sca, phase, wl):
    """Per-band <C_ext>, <C_sca> (W,) and phase (W, M) → RGB-mode (3,), (3,), (3, M); and the largest clip."""
    e = spectra_to_rgb_mode(np.asarray(c_ext), wl)
    s = spectra_to_rgb_mode(np.asarray(c_sca), wl)
    sp = spectra_to_rgb_mode((np.asarray(c_sca)[:, None] * np.asarray(phase)).T, wl).T  # (3, M)
    ec = np.maximum(e, 0.0)
    sc = np.clip(s, 0.0, ec)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(s[:, None] > 0, sp / s[:, None], 0.0)
    pc = np.maximum(p, 0.0)
    clip = float(max(np.abs(ec - e).max() / max(np.abs(e).max(), 1e-300),
                     np.abs(sc - s).max() / max(np.abs(s).max(), 1e-300),
                     np.abs(pc - p).max() / max(np.abs(p).max(), 1e-300)))
    return ec, sc, pc, clip


#: Gauss–Legendre nodes in μ ∈ [0, 1] of the RGB metal fit (:func:`metal_index_rgb`).
METAL_FIT_NODES = 48


def metal_index_rgb(N_spectral, eta, wl):
    """RGB-mode complex index of a metal base (module docstring, "Metal base").

    ``N_spectral`` (W,): the metal's index per band of ``wl`` relative to vacuum; ``eta``: the binder's
    index.  The smooth-interface Fresnel reflectance F(μ, λ) of N/η (:func:`flakedb.optics.fresnel.fresnel_conductor`)
    is converted to RGB (:func:`flakedb.colour.colorimetry.spectra_to_rgb_mode`, clipped to [0, 1]) at
    :data:`METAL_FIT_NODES` Gauss–Legendre μ nodes, and per channel n, k > 0 minimise
    Σ_j w_j μ_j (F(μ_j; (n + ik)/η) − F_rgb(μ_j))² (scipy least squares in log n, log k, started from
    the band-averaged N).  Returns (N_rgb (3,) complex relative to vacuum, the largest |F − F_rgb| over μ
    and channels, the largest clip of F_rgb)."""
    from scipy.optimize import least_squares  # lazy: scipy.optimize takes 0.3 s to import; only a metal base needs it

    N_spectral = np.asarray(N_spectral, dtype=complex)
    g, wg = leggauss(METAL_FIT_NODES)
    mu, wmu = 0.5 * (g + 1.0), 0.5 * wg
    F = fresnel_conductor(mu[:, None], N_spectral[None, :] / float(eta)).R  # (M, W)
    F_rgb = spectra_to_rgb_mode(F, wl)  # (M, 3)
    F_c = np.clip(F_rgb, 0.0, 1.0)
    clip = float(np.abs(F_c - F_rgb).max())
    sw = np.sqrt(wmu * mu)
    start = np.log(np.array([np.mean(N_spectral.real), max(np.mean(N_spectral.imag), 1e-3)]))
    out, err = np.zeros(3, dtype=complex), 0.0
    for c in range(3):
        def resid(p, c=c):
            return sw * (fresnel_conductor(mu, complex(np.exp(p[0]), np.exp(p[1])) / float(eta)).R - F_c[:, c])
        sol = least_squares(resid, start, method="lm", xtol=1e-14, ftol=1e-14)
        out[c] = complex(np.exp(sol.x[0]), np.exp(sol.x[1]))
        err = max(err, float(np.abs(resid(sol.x) / sw).max()))
    return out, err, clip


def metal_bottom(metal, mode, wl, C, eta, info):
    """RoughConductor of a recipe's metal base and its record (module docstring, "Metal base")."""
    if not isinstance(metal.material, str):
        N = np.full(C, complex(metal.material))
    elif mode == "rgb":
        N, err, clip = metal_index_rgb(refractive_index(metal.material, wl), eta, wl)
        info["metal_rgb_fit_error"] = err
        info["metal_rgb_clip"] = clip
    else:
        N = np.asarray(refractive_index(metal.material, wl), dtype=complex)
    bottom = RoughConductor(N, float(metal.roughness), bool(metal.energy_compensation))
    F0 = fresnel_conductor(np.ones(1), N / eta).R
    rec = {"path": metal.path, "kind": "metal base", "material": metal.label, "roughness": float(metal.roughness),
           "energy_compensation": bool(metal.energy_compensation),
           "n": [float(N.real.min()), float(N.real.max())], "k": [float(N.imag.min()), float(N.imag.max())],
           "normal_reflectance_in_binder": [float(F0.min()), float(F0.max())]}
    return bottom, rec


# ----------------------------------------------------------------------------------------------
# The paint
# ----------------------------------------------------------------------------------------------


def entry_key(entry) -> str:
    """A digest of a catalogue entry's whole content (as the recipe resolved it: film overrides, a size
    override applied): two entries with the same key give the same optics."""
    text = json.dumps(entry, sort_keys=True, default=repr)
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def particle_entry(p) -> dict:
    """The catalogue entry a catalogue particle's optics come from, as the recipe resolved it: ``p.entry`` (an
    interference flake's film overrides are already applied to it) with a pigment's ``median_diameter_um`` /
    ``gsd`` overrides.  The one place a recipe's optical overrides meet the entry (the direct path and the
    store's entry of :func:`store_key` both read it)."""
    if p.kind != "pigment" or (p.median_diameter_um is None and p.gsd is None):
        return p.entry
    entry = copy.deepcopy(p.entry)
    if p.median_diameter_um is not None:
        entry["median_diameter_um"] = {"value": float(p.median_diameter_um), "source": "recipe"}
    if p.gsd is not None:
        entry["gsd"] = {"value": float(p.gsd), "source": "recipe"}
    return entry


def recipe_overrides(p) -> dict:
    """The recipe fields that make a catalogue particle's optics differ from its species' entry: an interference
    flake's film overrides and a pigment's ``median_diameter_um`` / ``gsd`` (name -> value)."""
    over = dict(getattr(p, "film_overrides", None) or {})
    over.update(getattr(p, "grating_overrides", None) or {})
    if p.kind == "pigment":
        over.update({k: float(v) for k, v in (("median_diameter_um", p.median_diameter_um), ("gsd", p.gsd))
                     if v is not None})
    return over


def store_key(p) -> str:
    """The name a store holds a catalogue particle's optics under: the species name, or, where the recipe changes
    the optics (an interference flake's films, a pigment's size distribution), ``<species>~<12 hex>``: the
    species with a digest of the overrides (blake2b of their sorted JSON), so each overridden species is one
    more species of a version (``flakedb build --recipe`` projects it; the stored entry is
    :func:`particle_entry`, checked against the recipe's when a compose reads it)."""
    over = recipe_overrides(p)
    if not over:
        return p.species
    text = json.dumps({k: (list(map(float, v)) if isinstance(v, (list, tuple)) else float(v))
                       for k, v in sorted(over.items())}, sort_keys=True)
    return f"{p.species}~{hashlib.blake2b(text.encode(), digest_size=6).hexdigest()}"


def reused(key, compute):
    """``compute()``, or inside a fit's reuse scope (:func:`flakedb.rt.common.reuse.reusing`) the value an earlier
    evaluation computed under ``key`` — a species' optics per unit loading, keyed by everything it depends on
    (the entry, the wavelengths, the binder index, the grids), never by the loading."""
    cache = active_cache()
    return compute() if cache is None else cache.get_or_compute(key, compute)


def spectrum_or_const(value, wl, C):
    if isinstance(value, Spectrum):
        return value.at(wl)
    return np.full(C, float(value))


def flake_component(p, recipe, layer_um, n_binder, wl, C, info, stored=None):
    """FlakeMedium (or StoredFlakeMedium with ``stored``) and its record for a catalogue or custom flake."""
    dist = recipe_distribution(p)
    grating = p.entry.get("grating") if isinstance(p, CatalogParticle) else None
    if grating is not None:
        stored = None                          # computed directly: not in any store (paint.catalog.is_stored)
    if isinstance(p, CatalogParticle) and stored is not None:
        alpha = recipe_alpha(p)
        t = float(p.entry["thickness_um"]["value"])
        a_rho = flake_a_rho_from_volume_fraction(p.volume_fraction, t)
        rec = {"path": p.path, "species": p.species, "kind": p.kind, "volume_fraction": p.volume_fraction,
               "flake_thickness_um": t, "orientation_alpha": alpha, "orientation_distribution": dist,
               "a_rho_per_um": a_rho, "opaque": p.opaque,
               "diameter_um": float(p.diameter_um if p.diameter_um is not None else p.entry["diameter_um"]["value"]),
               "loading": "volume_fraction / flake thickness (model.md §3)"}
    elif isinstance(p, CatalogParticle):
        c, R, T, c_err = reused(("flake optics", entry_key(p.entry), array_key(wl), array_key(n_binder),
                                 FLAKE_C_TOL, FLAKE_C_START, FLAKE_C_MAX), lambda: adaptive_flake_optics(
            lambda cc: flake_reflectance_transmittance(p.entry, wl, cc, n_binder)))  # (W, nc) each
        info.setdefault("flake_c_grid", {})[p.path] = {"nodes": int(c.size), "max_midpoint_error": c_err}
        if p.opaque:
            T = np.zeros_like(T)
        if recipe.mode == "rgb":
            R, T, clip = flake_rt_tospectra_to_rgb_mode(R, T, wl)
            info.setdefault("rgb_clip", {})[p.path] = clip
        alpha = recipe_alpha(p)
        t = float(p.entry["thickness_um"]["value"])
        a_rho = flake_a_rho_from_volume_fraction(p.volume_fraction, t)
        optics = FlakeOptics(c, R, T)
        rec = {"path": p.path, "species": p.species, "kind": p.kind, "volume_fraction": p.volume_fraction,
               "flake_thickness_um": t, "orientation_alpha": alpha, "orientation_distribution": dist,
               "a_rho_per_um": a_rho, "opaque": p.opaque,
               "diameter_um": float(p.diameter_um if p.diameter_um is not None else p.entry["diameter_um"]["value"]),
               "loading": "volume_fraction / flake thickness (docs/model.md §3)"}
        if p.film_overrides:
            rec["film_overrides"] = {k: (list(map(float, v)) if isinstance(v, list) else float(v))
                                     for k, v in p.film_overrides.items()}
    else:
        c = np.union1d(p.R.c, p.T.c)
        R = np.interp(c, p.R.c, p.R.value)
        T = np.interp(c, p.T.c, p.T.value)
        optics = FlakeOptics(c, np.broadcast_to(R, (C, c.size)), np.broadcast_to(T, (C, c.size)))
        alpha = float(p.orientation_alpha)
        a_rho = flake_a_rho_from_optical_depth(p.optical_depth, layer_um, alpha, optics, dist)
        rec = {"path": p.path, "species": p.name, "kind": "custom flake", "optical_depth": p.optical_depth,
               "orientation_alpha": alpha, "orientation_distribution": dist, "a_rho_per_um": a_rho,
               "loading": "optical depth: sigma_t(mu=1) x layer thickness"}
    if stored is not None and isinstance(p, CatalogParticle):
        med = stored.flake_medium(store_key(p), alpha, a_rho, opaque=p.opaque, distribution=dist)
        rec["kernel"] = med.factors.source
    elif grating is not None:
        period, amplitude = float(grating["period_nm"]["value"]), float(grating["amplitude_nm"]["value"])
        med = GratingFlakeMedium(alpha, optics, a_rho, np.asarray(wl, float), period, amplitude, n_binder, dist)
        rec.update({"grating_period_nm": period, "grating_amplitude_nm": amplitude,
                    "kernel": "grating flake (flakedb.rt.scattering.grating_flake: scalar sinusoidal-grating "
                              "efficiencies, computed directly)"})
        if p.grating_overrides:
            rec["grating_overrides"] = {k: float(v) for k, v in p.grating_overrides.items()}
    else:
        med = FlakeMedium(alpha, optics, a_rho, dist)
    st = np.atleast_2d(med.sigma_t(np.array([1.0])))[:, 0]
    rec["sigma_t_normal_per_um"] = [float(st.min()), float(st.max())]
    rec["optical_depth_normal"] = [float(st.min() * layer_um), float(st.max() * layer_um)]
    return med, rec


def stored_pigment_component(p, recipe, layer_um, n_binder, wl, info, stored):
    """StoredPigmentMedium: ⟨C_ext⟩, ⟨C_sca⟩, ⟨V⟩ and the phase function's Legendre moments from the
    store (:meth:`flakedb.solve.store_context.StoreContext.pigment`), the RGB mode's clips as
    :func:`pigment_tospectra_to_rgb_mode` (the phase ≥ 0 clip on the series, :func:`rgb_phase_moments`)."""
    po = stored.pigment(store_key(p))  # per recipe band: c_ext_um2, c_sca_um2, mean_volume_um3 (scalar), chi
    c_ext, c_sca, chi = po["c_ext_um2"], po["c_sca_um2"], po["legendre_moments"]
    if recipe.mode == "rgb":
        e = spectra_to_rgb_mode(c_ext, wl)
        s_ = spectra_to_rgb_mode(c_sca, wl)
        c_ext, c_sca = np.maximum(e, 0.0), np.clip(s_, 0.0, np.maximum(e, 0.0))
        chi, clip_p = rgb_phase_moments(spectra_to_rgb_mode((po["c_sca_um2"][:, None] * po["legendre_moments"]).T, wl).T, s_)
        info.setdefault("rgb_clip", {})[p.path] = float(max(np.abs(c_ext - e).max() / max(np.abs(e).max(), 1e-300),
                                                            np.abs(c_sca - s_).max() / max(np.abs(s_).max(), 1e-300),
                                                            clip_p))
    chi, linfo = truncate_legendre(chi)
    rho = pigment_number_density(p.volume_fraction, po["mean_volume_um3"])
    sigma_t, sigma_s = rho * c_ext, rho * c_sca
    with np.errstate(divide="ignore", invalid="ignore"):
        albedo = np.where(c_ext > 0, c_sca / c_ext, 0.0)
    med = StoredPigmentMedium(sigma_t, sigma_s, chi, po["source"])
    rec = {"path": p.path, "species": p.species, "kind": "pigment", "volume_fraction": p.volume_fraction,
           "median_diameter_um": float(p.entry["median_diameter_um"]["value"]), "gsd": float(p.entry["gsd"]["value"]),
           "mean_volume_um3": float(po["mean_volume_um3"]), "number_density_per_um3": rho,
           "sigma_t_per_um": [float(sigma_t.min()), float(sigma_t.max())],
           "albedo": [float(albedo.min()), float(albedo.max())],
           "optical_depth": [float(sigma_t.min() * layer_um), float(sigma_t.max() * layer_um)],
           "loading": "number density = volume_fraction / mean particle volume; sigma_t = rho C_ext",
           "kernel": f"{po['source']}: Legendre degree {linfo['degree']} (tail {linfo['tail']:.1e}), addition theorem"}
    return med, rec


def rgb_phase_moments(sp_chi, s):
    """RGB-mode phase moments from the mapped rgb(C_sca χ) (3, K + 1) and rgb(C_sca) (3,): χ = rgb(C_sca χ)/rgb(C_sca)
    (each channel's phase is its scattering-weighted mean, as :func:`pigment_tospectra_to_rgb_mode`), its
    negative lobes clipped to 0 and renormalised (the series evaluated and re-projected on Gauss–Legendre
    nodes).  Returns (χ (3, K + 1), the largest clip relative to max p)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        chi = np.where(np.asarray(s)[:, None] > 0, sp_chi / np.asarray(s)[:, None], 0.0)
    K = chi.shape[1] - 1
    t, wt = np.polynomial.legendre.leggauss(2 * K + 2)
    p = legendre_series(chi, t)
    pc = np.maximum(p, 0.0)
    clip = float(np.abs(pc - p).max() / max(np.abs(p).max(), 1e-300))
    if clip > 0:
        chi, _ = legendre_moments_gauss(t, wt, pc, tol=0.0, k_max=K)
        with np.errstate(divide="ignore", invalid="ignore"):
            chi = np.where(chi[:, :1] > 0, chi / chi[:, :1], 0.0)
    return chi, clip


def pigment_component(p, recipe, layer_um, n_binder, wl, info, stored=None):
    if stored is not None:
        return stored_pigment_component(p, recipe, layer_um, n_binder, wl, info, stored)
    entry = particle_entry(p)
    mu = phase_cos_grid()

    def optics():
        po = pigment_optics(entry, wl, n_binder, mu=mu)
        return (np.asarray(po.c_ext_um2, float), np.asarray(po.c_sca_um2, float), np.asarray(po.phase_function),
                np.asarray(float(po.mean_volume_um3)))

    c_ext, c_sca, phase, mean_volume = reused(
        ("pigment optics", entry_key(entry), array_key(wl), array_key(n_binder), array_key(mu)), optics)
    mean_volume = float(mean_volume)
    phase, integral = normalise_phase_table(mu, phase)
    info.setdefault("phase_table_norm_error", {})[p.path] = float(np.abs(integral - 1.0).max())
    if recipe.mode == "rgb":
        c_ext, c_sca, phase, clip = pigment_tospectra_to_rgb_mode(c_ext, c_sca, phase, wl)
        phase, _ = normalise_phase_table(mu, phase)
        info.setdefault("rgb_clip", {})[p.path] = clip
    rho = pigment_number_density(p.volume_fraction, mean_volume)
    sigma_t = rho * c_ext
    with np.errstate(divide="ignore", invalid="ignore"):
        albedo = np.where(c_ext > 0, c_sca / c_ext, 0.0)
    med = PhaseMedium(sigma_t, albedo, ("table", mu, phase))
    rec = {"path": p.path, "species": p.species, "kind": "pigment", "volume_fraction": p.volume_fraction,
           "median_diameter_um": float(entry["median_diameter_um"]["value"]), "gsd": float(entry["gsd"]["value"]),
           "mean_volume_um3": mean_volume, "number_density_per_um3": rho,
           "sigma_t_per_um": [float(sigma_t.min()), float(sigma_t.max())],
           "albedo": [float(albedo.min()), float(albedo.max())],
           "optical_depth": [float(sigma_t.min() * layer_um), float(sigma_t.max() * layer_um)],
           "loading": "number density = volume_fraction / mean particle volume; sigma_t = rho C_ext"}
    return med, rec


def tinter_medium(sigma_a_per_phi_um, sigma_s_per_phi_um, g, volume_fraction) -> PhaseMedium:
    """The medium of a tinter at ``volume_fraction`` φ (module docstring, "Tinters"): σ_t = φ (σ_a/φ + σ_s/φ),
    albedo σ_s/σ_t (0 where σ_t = 0), Henyey–Greenstein g.  ``sigma_*_per_phi_um`` (C,) in 1/µm per unit
    volume fraction; ``g`` scalar or (C,).

    >>> m = tinter_medium([3.0, 0.0], [1.0, 0.0], 0.4, 0.02)
    >>> m.sigma_t_per_um.tolist(), m.albedo.tolist(), m.phase
    ([0.08, 0.0], [0.25, 0.0], ('hg', 0.4))
    """
    a = np.asarray(sigma_a_per_phi_um, float)
    s = np.asarray(sigma_s_per_phi_um, float)
    t = float(volume_fraction) * (a + s)
    with np.errstate(divide="ignore", invalid="ignore"):
        albedo = np.where(a + s > 0, s / np.where(a + s > 0, a + s, 1.0), 0.0)
    return PhaseMedium(t, albedo, ("hg", g))


def tinter_component(p, recipe, layer_um, wl, info):
    """The PhaseMedium of a catalogue tinter (:func:`tinter_medium`) and its record."""
    a, s = tinter_coefficients(p.entry, wl)
    if recipe.mode == "rgb":  # as a pigment's <C_ext>, <C_sca> (pigment_tospectra_to_rgb_mode)
        e, sc = spectra_to_rgb_mode(a + s, wl), spectra_to_rgb_mode(s, wl)
        ec = np.maximum(e, 0.0)
        scc = np.clip(sc, 0.0, ec)
        info.setdefault("rgb_clip", {})[p.path] = float(max(np.abs(ec - e).max() / max(np.abs(e).max(), 1e-300),
                                                            np.abs(scc - sc).max() / max(np.abs(sc).max(), 1e-300)))
        a, s = ec - scc, scc
    g = float(p.entry["asymmetry_g"]["value"])
    med = tinter_medium(a, s, g, p.volume_fraction)
    st = np.asarray(med.sigma_t_per_um)
    rec = {"path": p.path, "species": p.species, "kind": "tinter", "volume_fraction": p.volume_fraction,
           "sigma_t_per_um": [float(st.min()), float(st.max())],
           "albedo": [float(np.min(med.albedo)), float(np.max(med.albedo))], "phase": ["hg", g],
           "optical_depth": [float(st.min() * layer_um), float(st.max() * layer_um)],
           "loading": "sigma = volume_fraction x the tinter's sigma per unit volume fraction"}
    return med, rec


def custom_medium_albedo(albedo, mode, wl, C):
    """A custom medium's single-scattering albedo per channel (C,), and the RGB mode's clip.

    ``albedo`` a float or a :class:`flakedb.paint.recipe.Spectrum`.  Spectral mode: the spectrum at
    the band centres; mono: the number; RGB mode: the white-normalised linear sRGB of the spectrum
    (:func:`flakedb.colour.colorimetry.spectra_to_rgb_mode`, the map every other spectrum takes;
    σ_t is the same in every channel, so this is rgb(σ_s)/rgb(σ_t) as for pigments), clipped to
    [0, 1] like the primer's albedo (module docstring, "Channels").  Returns ``(albedo, clip)``, clip
    the largest |clipped − converted| (0 outside RGB mode)."""
    if not isinstance(albedo, Spectrum):
        return np.full(C, float(albedo)), 0.0
    if mode == "rgb":
        a = spectra_to_rgb_mode(albedo.at(wl), wl)
        ac = np.clip(a, 0.0, 1.0)
        return ac, float(np.abs(ac - a).max())
    return albedo.at(wl), 0.0


def custom_medium_component(p, layer_um, C, info, mode=None, wl=None):
    phase = p.phase
    if isinstance(phase, tuple) and phase[0] == "table":
        vals, integral = normalise_phase_table(phase[1], phase[2])
        info.setdefault("phase_table_normalised_from", {})[p.path] = float(integral)
        phase = ("table", np.asarray(phase[1], float), vals)
    sigma_t = float(p.optical_depth) / float(layer_um)
    albedo, clip = custom_medium_albedo(p.albedo, mode, wl, C)
    if isinstance(p.albedo, Spectrum) and mode == "rgb":
        info.setdefault("rgb_clip", {})[p.path] = clip
    med = PhaseMedium(np.full(C, sigma_t), albedo, phase)
    if isinstance(phase, str):
        ph_rec = phase
    elif phase[0] == "hg":
        ph_rec = ["hg", phase[1]]
    elif phase[0] == "vmf":
        ph_rec = {"vmf": {"kappa": float(phase[1]), "g": float(vmf_mean_cosine(phase[1]))}}
    else:
        ph_rec = "table"
    rec = {"path": p.path, "species": p.name, "kind": "custom medium", "optical_depth": p.optical_depth,
           "sigma_t_per_um": sigma_t,
           "albedo": float(p.albedo) if not isinstance(p.albedo, Spectrum) else [float(albedo.min()), float(albedo.max())],
           "phase": ph_rec, "loading": "optical depth: sigma_t x layer thickness"}
    return med, rec
