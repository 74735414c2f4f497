"""Recipe → inputs of the texture model (docs/texture.md §5): flake statistics, per-flake optics and
the extinction of everything else, from the same catalogue optics the solver uses.

* Flakes (catalogue interference and mirror flakes): number density ρ = φ / (⟨A⟩ t) with
  ⟨A⟩ = π D_m² exp(2 s²)/4 the mean area of the log-normal number distribution of diameters
  (median ``diameter_um`` of the recipe or the catalogue, s = ln ``diameter_gsd``, default
  :data:`DEFAULT_DIAMETER_GSD`); thickness, orientation distribution and spread α, diameter and the
  loading aρ = ρ⟨A⟩ from the solver's own mapping (:mod:`flakedb.paint.mapping`: ``recipe_alpha``,
  ``recipe_distribution``, ``flake_a_rho_from_volume_fraction``), so the texture and the BSDF read one
  recipe one way; R(c, λ), T(c, λ) from :func:`flakedb.paint.species.flake_reflectance_transmittance`
  on the adaptive c grid of :func:`flakedb.paint.components.adaptive_flake_optics`; ``opaque`` sets T = 0.
* Pigments: σ_t = ρ⟨C_ext⟩ per band (:func:`flakedb.paint.species.pigment_optics`, Mie, Du 2004, or
  with ``stored`` the store's cross-sections, as the solver takes them:
  :func:`flakedb.paint.mapping.build_paint`): the extinction of the direct beam (scattered light joins
  the ground, not the glint).
* An absorbing clear coat: its absorption; a custom medium: σ_t = τ/d (grey).
* Luminance weights: the Y column of :func:`flakedb.colour.colorimetry.tristimulus_weights` (D65,
  CIE 1931 2°) on the recipe's grid (spectral and RGB modes both evaluate on the spectral grid).

Not modelled (said in the report's ``notes``): custom flakes (no diameter), inner index changes
(the model refracts once, at the coat), a rough clear coat (glints are blurred by it; the model
treats the coat as smooth), a metal base (its mirror is not a flake).
"""

from __future__ import annotations

import numpy as np

from flakedb.colour.colorimetry import tristimulus_weights
from flakedb.paint.components import (
    adaptive_flake_optics,
    flake_a_rho_from_volume_fraction,
    particle_entry,
    pigment_number_density,
    recipe_alpha,
    recipe_distribution,
    store_key,
)
from flakedb.paint.recipe import CatalogParticle, CustomFlake, CustomMedium, Spectrum
from flakedb.paint.species import flake_reflectance_transmittance, pigment_optics, tinter_coefficients
from flakedb.texture.model import (
    Absorber,
    FlakeLayer,
    TextureModelLimit,
    TextureStack,
    texture_indices,
    texture_indices_grounded,
)

#: Default geometric standard deviation of flake diameters (number distribution).  Assumption: effect
#: pigment grades are sold by D10/D50/D90 of the volume distribution with D90/D10 ≈ 2.5–3.5 (e.g.
#: Schlenk, Eckart aluminium and Merck Iriodin data sheets); for a log-normal D90/D10 = σ_g^2.563,
#: so σ_g ≈ 1.43–1.63; 1.5 is the middle.  A recipe's ``diameter_gsd`` overrides it.
DEFAULT_DIAMETER_GSD = 1.5
#: Flake-cosine tolerance of the R, T tables (the solver's is 1e-4; the indices need less).
TEXTURE_C_TOL = 1e-3


def _spectrum(value, wl):
    return value.at(wl) if isinstance(value, Spectrum) else np.full(wl.size, float(value))


def texture_stack(recipe, stored=None) -> tuple[TextureStack, list]:
    """(:class:`flakedb.texture.model.TextureStack`, notes) of ``recipe`` (module docstring).

    ``stored``: the :class:`flakedb.solve.store_context.StoreContext` the solve used, or None: catalogue
    pigments' ⟨C_ext⟩ and ⟨V⟩ come from it (at the recipe's bands) instead of a second Mie evaluation,
    exactly where :func:`flakedb.paint.mapping.build_paint` takes them from it.

    The flakes' volume fraction comes back as ρ⟨A⟩t, below the 40 µm coat, and the luminance weights sum to 1:

    >>> import flakedb
    >>> recipe = flakedb.parse_recipe('''
    ... flakedb: 1
    ... name: doc-silver
    ... spectral: {mode: spectral, range_nm: [380, 780], step_nm: 20}
    ... resolution: 16
    ... layers:
    ...   - clearcoat: {thickness_um: 40, ior: 1.5, roughness: 0}
    ...   - basecoat:
    ...       thickness_um: 15
    ...       ior: 1.5
    ...       particles:
    ...         - {species: metallic, volume_fraction: 0.08, orientation_alpha: 0.2}
    ...   - primer: {color: gray}
    ... ''')
    >>> stack, notes = texture_stack(recipe)
    >>> (f,) = stack.flakes
    >>> bool(abs(f.number_density_per_um3 * f.mean_area_um2() * f.flake_thickness_um - 0.08) < 1e-15), f.z_top_um, f.alpha
    (True, 40.0, 0.2)
    >>> abs(float(stack.y_weights.sum()) - 1.0) < 1e-14, notes
    (True, [])
    """
    notes = []
    wl = None if recipe.wavelength_nm is None else np.asarray(recipe.wavelength_nm, float)
    if wl is None:
        y = np.ones(1)
    else:
        y = np.asarray(tristimulus_weights(wl)[:, 1], float)
        y = y / y.sum()
    C = y.size
    eta = float(recipe.binder_ior)
    cc = recipe.clearcoat
    z = 0.0
    absorbers, flakes = [], []
    if cc is not None:
        if cc.roughness > 0:
            notes.append(f"{cc.path}.roughness {cc.roughness:g}: the coat is treated as smooth; a rough coat blurs glints")
        if cc.absorption_per_um is not None and wl is not None:
            absorbers.append(Absorber(0.0, cc.thickness_um, _spectrum(cc.absorption_per_um, wl)))
        elif cc.absorption_per_um is not None:
            absorbers.append(Absorber(0.0, cc.thickness_um, np.full(1, float(cc.absorption_per_um))))
        z = cc.thickness_um
    for b in recipe.basecoats:
        if b.ior != eta:
            notes.append(f"{b.path}.ior {b.ior:g} differs from the top binder's {eta:g}: not modelled (one refraction, at the coat)")
        for p in b.particles:
            if isinstance(p, CatalogParticle) and p.is_flake:
                c, R, T, _ = adaptive_flake_optics(
                    lambda cc_: flake_reflectance_transmittance(p.entry, wl, cc_, b.ior), tol=TEXTURE_C_TOL)
                if p.opaque:
                    T = np.zeros_like(T)
                Dm = float(p.diameter_um if p.diameter_um is not None else p.entry["diameter_um"]["value"])
                gsd = float(p.diameter_gsd if p.diameter_gsd is not None else DEFAULT_DIAMETER_GSD)
                t = float(p.entry["thickness_um"]["value"])
                mean_area = 0.25 * np.pi * Dm * Dm * np.exp(2.0 * np.log(gsd) ** 2)
                rho = flake_a_rho_from_volume_fraction(p.volume_fraction, t) / mean_area  # the solver's aρ = ρ⟨A⟩
                flakes.append(FlakeLayer(p.species, z, b.thickness_um, rho, Dm, gsd, t, recipe_alpha(p), c, R, T,
                                         distribution=recipe_distribution(p)))
            elif isinstance(p, CatalogParticle) and p.kind == "tinter":  # σ_t = φ (σ_a/φ + σ_s/φ), as the solver's
                a, s = tinter_coefficients(p.entry, wl)
                absorbers.append(Absorber(z, b.thickness_um, float(p.volume_fraction) * (a + s)))
            elif isinstance(p, CatalogParticle) and stored is not None and wl is not None:
                po = stored.pigment(store_key(p))  # the solver's own cross-sections (flakedb.paint.components.stored_pigment_component)
                absorbers.append(Absorber(z, b.thickness_um,
                                          pigment_number_density(p.volume_fraction, po["mean_volume_um3"]) * np.asarray(po["c_ext_um2"])))
            elif isinstance(p, CatalogParticle):
                po = pigment_optics(particle_entry(p), wl, b.ior)
                absorbers.append(Absorber(z, b.thickness_um, pigment_number_density(p.volume_fraction, po.mean_volume_um3) * np.asarray(po.c_ext_um2)))
            elif isinstance(p, CustomMedium):
                absorbers.append(Absorber(z, b.thickness_um, np.full(C, float(p.optical_depth) / b.thickness_um)))
            elif isinstance(p, CustomFlake):
                notes.append(f"{p.path}: a custom flake has no diameter: left out of the texture")
        z += b.thickness_um
    if getattr(recipe, "metal", None) is not None:
        notes.append("metal base: its mirror is not a flake; no glints from it")
    return TextureStack(eta, y, tuple(flakes), tuple(absorbers), wl), notes


def texture_report(recipe, observers, ground=None, stored=None) -> dict:
    """The ``texture`` report of a recipe: one entry per observer (:func:`flakedb.texture.model.texture_indices`);
    ``stored`` as :func:`texture_stack`.

    ``ground``: optional callable ``ground(observer) -> {"directional": {light_deg: β}, "diffuse": β}``
    giving the smooth BSDF's luminance factors (compose passes one); without it contrasts and
    graininess are relative to the flakes' own mean (upper bounds, ``ground: "flakes"``), and
    :func:`texture_report_grounded` can ground them later (what compose does: the texture is computed
    while the BSDF is solved, and grounded on it after)."""
    stack, notes = texture_stack(recipe, stored)
    out = {"recipe": recipe.name, "model": "docs/texture.md", "notes": notes,
           "flakes": [{"species": f.name, "diameter_median_um": f.diameter_median_um, "diameter_gsd": f.diameter_gsd,
                       "orientation_alpha": f.alpha, "orientation_distribution": f.distribution,
                       "flakes_per_mm2": f.areal_density_per_um2 * 1e6,
                       "depth_um": [f.z_top_um, f.z_top_um + f.thickness_um]} for f in stack.flakes]}
    if not stack.flakes:
        out["sparkle"] = False
        has_flakes = any(isinstance(p, CustomFlake) or (isinstance(p, CatalogParticle) and p.is_flake)
                         for _, p in recipe.particles())
        out["summary"] = ("no flakes the texture model can use (see the notes): no sparkle predicted" if has_flakes
                          else "no flakes: no sparkle and no graininess (a pigment-only paint)")
        out["observers"] = []
        return out
    out["sparkle"] = True
    memo = {}  # the observers share the light and view directions' parts (flakedb.texture.model.texture_indices)
    try:
        out["observers"] = [texture_indices(stack, o, ground(o) if ground else None, memo=memo) for o in observers]
    except TextureModelLimit as e:  # the BSDF is still composed; the texture says why it has no numbers
        out.update(sparkle=False, observers=[], summary=f"sparkle and graininess not predicted: {e}")
    return out


def texture_report_grounded(report: dict, observers, ground) -> dict:
    """A :func:`texture_report` of ``observers`` made without ``ground``, grounded on ``ground`` (the
    callable of :func:`texture_report`): the same report as passing ``ground`` to it, to the last bit
    (:func:`flakedb.texture.model.texture_indices_grounded`)."""
    entries = report.get("observers") or []
    names = [o.name for o in observers]
    if [e["observer"] for e in entries] != names[:len(entries)] or (entries and len(entries) != len(names)):
        raise ValueError(f"texture report of observers {[e['observer'] for e in entries]} grounded for {names}")
    return dict(report, observers=[texture_indices_grounded(e, ground(o)) for e, o in zip(entries, observers)])
