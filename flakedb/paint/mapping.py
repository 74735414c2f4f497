"""Recipe → solver inputs: the physics mapping of a paint (docs/model.md §1, §3, §6).

A :class:`flakedb.paint.recipe.Recipe` becomes the arguments of :func:`flakedb.rt.adding.stack.solve_stack`::

    top     Smooth(η) | Rough(η, α) | None      η = the top binder's index (the clear coat's, else the
                                                 first basecoat's; ior 1 = no interface)
            + InnerSmooth(η_b / η_a)             before a basecoat whose ior differs from the binder over
                                                 it (a rise or a fall): a smooth inner interface (docs/model.md §4)
    slabs   [Slab(d_clear, absorbing coat)]      only when the coat absorbs: PhaseMedium(σ_a, albedo 0)
            + [Slab(d_base, Mixture(…)) …]       one per basecoat that holds particles
    bottom  Lambertian(albedo per channel)       the primer, or
            | RoughConductor(N per channel, α)    a metal base (N = n + ik relative to vacuum), or
            | None                                nothing (a transmissive, index-matched stack)

A non-absorbing clear coat adds no slab at all: inside one binder it changes nothing (the
smooth or rough top interface is the coat's surface).  A basecoat without particles is likewise
clear binder and adds nothing.

Particles (docs/model.md §3 "the anisotropic medium", §6 "particle optics")
----------------------------------------------------------------------
* **Flakes** (interference and mirror flakes of the catalogue; paper eq. 2, docs/model.md §3): a
  :class:`flakedb.rt.scattering.media.FlakeMedium` with

  - loading ``aρ = volume_fraction / t_flake`` (flake area × number density, 1/µm; docs/model.md: "aρ =
    volume fraction / flake thickness": N flakes of area a and thickness t fill a volume N a t,
    so the volume fraction is φ = ρ a t).  The flake diameter cancels, so it does not enter the
    optics (it is recorded);
  - R(c, λ), T(c, λ) from :func:`flakedb.paint.species.flake_reflectance_transmittance` (transfer-matrix
    method for interference flakes; R = albedo, T = 0 for mirror flakes) on the flake-cosine grid
    :func:`flake_cos_grid` (c = |cos| of the angle of incidence on the flake *in the binder*),
    with the recipe's binder ior as the embedding index (the same η the solver uses);
  - ``opaque: true`` keeps R and sets T = 0 (the paper's Fig. 5 opaque flakes: Jakob et al. 2010);
  - the Beckmann orientation spread α of the catalogue, or the recipe's ``orientation_alpha``.

* **Pigments** (spheres; docs/model.md §3 "uniform D with a Mie kernel is an isotropic Mie medium", §6):
  a :class:`flakedb.rt.scattering.media.PhaseMedium` with number density ``ρ = volume_fraction / <V>``
  (``<V>`` the mean particle volume of the log-normal, µm³), ``σ_t = ρ <C_ext>``,
  ``albedo = <C_sca>/<C_ext>`` and the C_sca-weighted Mie phase function tabulated on
  :func:`phase_cos_grid` (from :func:`flakedb.paint.species.pigment_optics`, Du 2004, relative index
  m = N/n_binder, size parameter x = π d n_binder / λ).

* **Tinters** (a colourant known by its optics per unit volume fraction φ, made by ``flakedb calibrate``
  from drawdowns or from Kubelka–Munk K and S; docs/calibration.md): a :class:`flakedb.rt.scattering.media.PhaseMedium`
  with ``σ_a = φ · σ_a/φ``, ``σ_s = φ · σ_s/φ`` (the entry's tables at the band centres,
  :func:`flakedb.paint.species.tinter_coefficients`) and the Henyey–Greenstein phase function of the
  entry's g (:func:`tinter_medium`).  Linear in φ: the dilute, independent-scattering assumption every
  species here makes.  In RGB mode σ_t and σ_s are mapped as a pigment's cross-sections.  Never from
  the store (cheap to compute directly).

* **Custom species** (research stacks), loaded by optical depth τ in a layer of thickness d:

  - a flake with constant or tabulated (vs c) grey R and T: ``aρ = τ / (d · s_t(1))`` with
    ``s_t(μ) = ∫ (1 − T(|ω·m|)) |ω·m| D(m) dm`` (σ_t per unit aρ, eq. 2) at normal incidence, so
    that σ_t(μ = 1) · d = τ;
  - a medium with single-scattering albedo ϖ (a number, or a spectrum: per band, or in RGB mode
    through the same linear map as every spectrum, clipped to [0, 1]; :func:`custom_medium_albedo`)
    and an isotropic, Henyey–Greenstein, von Mises–Fisher (κ, or its mean cosine g converted to κ;
    :func:`flakedb.rt.scattering.media.phase_vMF`) or tabulated phase function: ``σ_t = τ / d`` (the same in
    every channel).  A tabulated phase function is normalised so that its
    piecewise-linear interpolant (what :class:`~flakedb.rt.scattering.media.PhaseMedium` evaluates) integrates
    to 1 over the sphere.

From the precomputed store (issue #6)
-----------------------------------
With an open store version (:func:`build_paint` ``store=``), catalogue flakes become
:class:`flakedb.rt.scattering.stored.StoredFlakeMedium` and catalogue pigments
:class:`flakedb.rt.scattering.stored.StoredPigmentMedium`: the kernels' R(μ_i, μ_o, φ_d) comes from the store
(compressed factors, or the raw samples with ``raw``), the rest as above: the loadings, σ_t(μ) and
σ_s(μ) of flakes (1-D integrals of R(c), T(c): the store has no T), a pigment's ρ <C_ext> and
<C_sca> (Mie cross-sections, no phase function), and the recipe's α (D(h) is evaluated, not
stored).  :func:`flakedb.solve.store_context.store_problems` lists what the store lacks for a recipe.  In RGB mode the stored
spectral R is mapped to linear sRGB coefficient by coefficient (the map is linear).  For pigments the
direct path's clips are reproduced: C_sca ≤ C_ext scales each channel's kernel, and the phase ≥ 0
clip is applied to the evaluated kernel (:class:`flakedb.rt.scattering.stored.StoredPigmentMedium`
``nonnegative``), whose renormalisation to σ_s the solver does as for the direct path.  Without the
phase clip the store path differed from the direct one by ΔE00 0.83 (cadmium-yellow, n = 16, 380–780
nm; the blue channel's phase goes negative over 14 % of cos Θ); with it 1.2e-3 (tests/test_stored.py).
For flakes the direct path's per-c clip of R to [0, 1] with R + T ≤ 1 needs T, which the store does
not hold: it is not applied (the direct path reports its size in ``info['rgb_clip']``).  A rough coat needs a version built for a rough top (``flakedb build --recipe`` or ``--top rough``:
the air-side Radau nodes inside, as the solver keeps them below a rough interface).  A particle whose
recipe changes its optics (an interference flake's films, a pigment's size distribution) is its own species
of the store, named by :func:`flakedb.paint.components.store_key` (``flakedb build --recipe`` adds it).

Primer (Lambertian, docs/model.md §4): ``color`` black / gray / white → albedo 0.04 / 0.18 / 0.9
(:data:`flakedb.paint.recipe.PRIMER_ALBEDO`); or an albedo; or a spectrum (linear in λ).

Metal base (docs/model.md §4 "metal base"): a :class:`flakedb.rt.adding.stack.RoughConductor` of the recipe's
Beckmann roughness, with its complex index N = n + ik relative to vacuum (the solver divides it by the
binder's index above): per band from the catalogue material (:func:`flakedb.paint.materials.refractive_index`)
in spectral mode, the recipe's constant {n, k} in every mode.  In ``rgb`` mode N itself cannot be
converted (the reflectance is not linear in N, and an "RGB index" has no physical meaning); what is
physical and linear in the light is the metal's reflectance.  So the smooth-metal Fresnel reflectance
F(μ, λ) against the binder is converted to RGB like any reflectance, and each channel gets the N whose
conductor Fresnel curve fits that RGB curve best in the cosine-weighted least-squares sense over μ
(:func:`metal_index_rgb`; two parameters n, k per channel).  The fit's largest error in F is recorded in
``info['metal_rgb_fit_error']`` (Al in the binder 1.5: measured in tests/paint/test_mapping.py).  The
microfacet lobe then uses this N per channel; the Fresnel factor at the microfacets sees the same
reflectance curve as the spectral solve, averaged over the band as the paper's RGB mode does.

Channels
--------
* ``spectral``: one channel per band of the recipe's grid; every optical quantity per band.
* ``rgb`` (the paper's mode, docs/model.md §6): spectra are computed on the grid and converted to the
  white-normalised linear sRGB of :func:`flakedb.colour.colorimetry.spectra_to_rgb_mode` *before* the
  solve: flake R(c) and T(c) per c; pigments' <C_ext> and <C_sca>, and the phase function as
  rgb(C_sca p)/rgb(C_sca) (so a channel's phase is its scattering-weighted mean); the primer's
  albedo and a custom medium's albedo spectrum; a coat's absorption through its normal-incidence transmittance,
  a_rgb = −ln(rgb(exp(−a d)))/d.  sRGB weights have negative lobes, so a converted value may fall
  outside its physical range; it is clipped (R, T, albedo to [0, 1] with R + T ≤ 1 by scaling;
  cross-sections ≥ 0 with C_sca ≤ C_ext; phase ≥ 0) and the largest clip is reported in ``info``.
* ``mono``: one grey channel; every input is wavelength-independent (checked by the recipe).

The node count of a solve is decided in :mod:`flakedb.solve.resolution`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from dataclasses import replace as replace_dataclass

import numpy as np

from flakedb.colour.colorimetry import spectra_to_rgb_mode
from flakedb.paint.catalog import is_stored
from flakedb.paint.components import (
    custom_medium_component,
    flake_component,
    metal_bottom,
    pigment_component,
    recipe_top_alpha,
    spectrum_or_const,
    tinter_component,
)
from flakedb.paint.recipe import CatalogParticle, CustomFlake, CustomMedium
from flakedb.rt.scattering.media import Mixture, PhaseMedium
from flakedb.rt.adding.stack import InnerRough, InnerSmooth, Lambertian, Rough, Slab, Smooth, SolverSettings, solve_stack
from flakedb.rt.scattering.stored import StoredMixture


@dataclass
class Paint:
    """Solver inputs of a recipe.  ``channels``: names (``"450nm"``…, ``R G B`` or ``mono``);
    ``components``: one JSON-able dict per particle with what was derived (loading, ranges);
    ``info``: anything else worth recording (clips in RGB mode, phase normalisations)."""

    top: object
    slabs: list
    bottom: object
    channels: tuple
    mode: str
    wavelength_nm: np.ndarray | None
    components: list = field(default_factory=list)
    info: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    #: each particle's medium as built, by its recipe path (what :func:`with_media` replaces)
    media: dict = field(default_factory=dict)

    @property
    def n_channels(self):
        return len(self.channels)

    @property
    def eta(self) -> float:
        """The top binder's index relative to the air (1: no top interface), read from :attr:`top`."""
        return 1.0 if self.top is None else float(self.top.eta)

    @property
    def top_alpha(self) -> float:
        """The rough top's Beckmann roughness (0: smooth or none), read from :attr:`top`."""
        return float(self.top.alpha) if isinstance(self.top, Rough) else 0.0

    @property
    def delta(self):
        """The smooth coat's mirror term as the file format records it, or None."""
        if isinstance(self.top, Smooth) and self.eta != 1.0:
            return {"kind": "fresnel", "eta": float(self.eta)}
        return None


def recipe_interfaces(recipe) -> tuple:
    """``(top, inner)``: the recipe's top interface (``Smooth(η)``, ``Rough(η, α)`` or None for η = 1) and, per
    basecoat, the inner interface above it (``InnerSmooth(η_b/η_a)`` / ``InnerRough(η_b/η_a, α)`` where its binder
    index differs from the one above, else None) — the one mapping of the recipe's interfaces, read by
    :func:`build_paint` and by the resolution (:mod:`flakedb.solve.resolution`) without building any optics.

    >>> class C: roughness = 0.1
    >>> class B:
    ...     def __init__(self, ior, a): self.ior, self.interface_roughness = ior, a
    >>> class R: binder_ior, clearcoat, basecoats = 1.5, C(), [B(1.5, 0.0), B(1.6, 0.05)]
    >>> top, inner = recipe_interfaces(R())
    >>> type(top).__name__, top.alpha, inner[0], round(inner[1].eta, 6), inner[1].alpha
    ('Rough', 0.1, None, 1.066667, 0.05)
    """
    eta = float(recipe.binder_ior)
    top_alpha = recipe_top_alpha(recipe)
    top = None if eta == 1.0 else (Rough(eta, top_alpha) if top_alpha > 0 else Smooth(eta))
    inner, n_above = [], eta  # the binder index above the next basecoat (the top binder's)
    for b in recipe.basecoats:
        if b.ior == n_above:
            inner.append(None)
            continue
        a_in = float(b.interface_roughness)  # a change of the binder index (a rise or a fall)
        inner.append(InnerRough(b.ior / n_above, a_in) if a_in > 0 else InnerSmooth(b.ior / n_above))
        n_above = b.ior
    return top, inner


def build_paint(recipe, catalog=None, stored=None) -> Paint:
    """The solver inputs of ``recipe`` (a :class:`flakedb.paint.recipe.Recipe`); see the module docstring.

    Without ``stored`` every particle's optics is computed directly from the catalogue.  With
    ``stored`` (a :class:`flakedb.solve.store_context.StoreContext`: an open store version checked
    against the recipe at the solve's node count), catalogue species take their kernels' R from it.
    """
    mode = recipe.mode
    wl = recipe.wavelength_nm
    if mode == "spectral":
        channels = tuple(f"{w:g}nm" for w in wl)
    elif mode == "rgb":
        channels = ("R", "G", "B")
    else:
        channels = ("mono",)
    C = len(channels)
    eta = float(recipe.binder_ior)
    info: dict = {}
    media: dict = {}
    if stored is not None:
        info["store"] = stored.record()
    components = []
    cc = recipe.clearcoat
    top, inner = recipe_interfaces(recipe)
    slabs = []
    if cc is not None and cc.absorption_per_um is not None:
        if mode == "rgb":
            a = spectrum_or_const(cc.absorption_per_um, wl, len(wl))
            t_rgb = spectra_to_rgb_mode(np.exp(-a * cc.thickness_um), wl)
            a_ch = -np.log(np.clip(t_rgb, 1e-300, 1.0)) / cc.thickness_um
        else:
            a_ch = spectrum_or_const(cc.absorption_per_um, wl, C) if mode == "spectral" else np.full(
                C, float(cc.absorption_per_um))
        if np.any(a_ch > 0):
            slabs.append(Slab(cc.thickness_um, PhaseMedium(a_ch, 0.0, "isotropic")))
            components.append({"path": cc.path, "kind": "absorbing clear coat",
                               "absorption_per_um": [float(a_ch.min()), float(a_ch.max())],
                               "optical_depth": [float(a_ch.min() * cc.thickness_um), float(a_ch.max() * cc.thickness_um)]})

    for b, interface in zip(recipe.basecoats, inner):
        if interface is not None:
            slabs.append(interface)
            components.append({"path": b.path, "kind": "inner interface", "eta_above": b.ior / interface.eta,
                               "eta_below": b.ior, "relative_index": interface.eta,
                               "roughness": float(b.interface_roughness)})
        meds = []
        for p in b.particles:
            if isinstance(p, CatalogParticle) and p.is_flake:
                med, rec = flake_component(p, recipe, b.thickness_um, b.ior, wl, C, info, stored)
            elif isinstance(p, CatalogParticle) and p.kind == "tinter":
                med, rec = tinter_component(p, recipe, b.thickness_um, wl, info)
            elif isinstance(p, CatalogParticle):
                med, rec = pigment_component(p, recipe, b.thickness_um, b.ior, wl, info, stored)
            elif isinstance(p, CustomFlake):
                med, rec = flake_component(p, recipe, b.thickness_um, b.ior, wl, C, info)
            elif isinstance(p, CustomMedium):
                med, rec = custom_medium_component(p, b.thickness_um, C, info, mode, wl)
            else:  # pragma: no cover - the recipe module builds only these
                raise TypeError(f"unknown particle {p!r}")
            meds.append(med)
            components.append(rec)
            media[p.path] = med
        if meds:
            mix = StoredMixture if any(hasattr(m, "projected_kernel") for m in meds) else Mixture
            slabs.append(Slab(b.thickness_um, meds[0] if len(meds) == 1 else mix(meds)))

    bottom = None
    if recipe.primer is not None:
        pr = recipe.primer
        if mode == "rgb":
            alb = spectra_to_rgb_mode(spectrum_or_const(pr.albedo, wl, len(wl)), wl)
            info["primer_rgb_clip"] = float(np.abs(np.clip(alb, 0, 1) - alb).max())
            alb = np.clip(alb, 0.0, 1.0)
        else:
            alb = spectrum_or_const(pr.albedo, wl, C) if mode == "spectral" else np.full(C, float(pr.albedo))
        bottom = Lambertian(alb)
        components.append({"path": pr.path, "kind": "primer", "label": pr.label,
                           "albedo": [float(np.min(alb)), float(np.max(alb))]})

    if getattr(recipe, "metal", None) is not None:
        bottom, rec = metal_bottom(recipe.metal, mode, wl, C, eta, info)
        components.append(rec)

    return Paint(top=top, slabs=slabs, bottom=bottom, channels=channels, mode=mode,
                 wavelength_nm=None if wl is None else np.asarray(wl),
                 components=components, info=info, warnings=list(recipe.warnings), media=media)


def catalog_species(recipe) -> list:
    """The catalogue particles of a recipe that a store can serve (:func:`flakedb.paint.catalog.is_stored`:
    not tinters nor grating flakes, which are always computed directly), in layer order."""
    return [p for _, p in recipe.particles() if isinstance(p, CatalogParticle) and is_stored(p.entry)]


def with_media(paint: Paint, replace: dict) -> Paint:
    """A copy of ``paint`` with the media of some particles replaced, ``replace``: recipe path → new medium
    (each in the slab, alone or in its layer's mixture, where :attr:`Paint.media` has the old one).  What
    a fit that moves one species uses (:mod:`flakedb.match.tinter`): the other species' optics are kept."""
    swap = {id(paint.media[path]): med for path, med in replace.items()}
    slabs = []
    for s in paint.slabs:
        if isinstance(s, Slab):
            m = s.medium
            if isinstance(m, (Mixture, StoredMixture)):
                s = Slab(s.thickness_um, type(m)([swap.get(id(c), c) for c in m.components]))
            elif id(m) in swap:
                s = Slab(s.thickness_um, swap[id(m)])
        slabs.append(s)
    return replace_dataclass(paint, slabs=slabs, media={**paint.media, **replace})


def solve_paint(paint: Paint, n: int, **settings):
    """Solve the paint's stack at ``n`` nodes; returns :class:`flakedb.rt.adding.stack.StackBSDF`."""
    return solve_stack(paint.top, paint.slabs, paint.bottom, SolverSettings.product(n, **settings),
                       channels=paint.n_channels)
