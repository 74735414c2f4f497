"""An open store version checked against a recipe: what it lacks (:func:`store_problems`), the
`flakedb build` command that adds it, and how its wavelengths become the paint's channels
(:class:`StoreContext`, handed to :func:`flakedb.paint.mapping.build_paint`; docs/store.md)."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from flakedb.colour.colorimetry import spectra_to_rgb_matrix
from flakedb.paint.catalog import optical_entry
from flakedb.paint.mapping import catalog_species
from flakedb.paint.components import (particle_entry, recipe_alpha, recipe_distribution, recipe_overrides, recipe_top_alpha,
                                      store_key)
from flakedb.rt.scattering.stored import StoredFlakeMedium
from flakedb.store import versions as st
from flakedb.store.versions import StoreError


def _same_entry(a, b) -> bool:
    norm = lambda e: json.loads(json.dumps(optical_entry(e), sort_keys=True, default=float))
    return norm(a) == norm(b)


def _overrides(p) -> str:
    """The recipe fields that make ``p``'s optics differ from its catalogue species' (:func:`store_key`)."""
    return ", ".join(sorted(recipe_overrides(p)))


def wavelength_map(store_nm, recipe_nm, tol_nm=1e-9):
    """(C, W) map from the store's wavelengths to the recipe's bands: a band on the store's grid
    selects it (exact: the direct path samples its optics at the band's wavelength too); a band
    between two store wavelengths is their linear interpolation (the kernel is linear in U).  Returns
    ``(map, info)`` with ``selected`` / ``interpolated`` counts and the largest gap bridged (nm); raises
    ValueError for a band outside the store's range.

    A band on the store's grid selects it, a band between two store wavelengths is interpolated:

    >>> M, info = wavelength_map([400.0, 500.0, 600.0, 700.0], [500.0, 550.0])
    >>> M.tolist(), info
    ([[0.0, 1.0, 0.0, 0.0], [0.0, 0.5, 0.5, 0.0]], {'selected': 1, 'interpolated': 1, 'largest_gap_nm': 100.0})
    >>> wavelength_map([400.0, 500.0], [800.0])
    Traceback (most recent call last):
    ...
    ValueError: 800 nm is outside the store's 400-500 nm
    """
    swl = np.asarray(store_nm, float)
    wl = np.asarray(recipe_nm, float)
    Mp = np.zeros((wl.size, swl.size))
    sel = interp = 0
    gap = 0.0
    for c, w in enumerate(wl):
        j = int(np.argmin(np.abs(swl - w)))
        if abs(swl[j] - w) <= tol_nm:
            Mp[c, j] = 1.0
            sel += 1
            continue
        if w < swl.min() or w > swl.max():
            raise ValueError(f"{w:g} nm is outside the store's {swl.min():g}-{swl.max():g} nm")
        k = int(np.searchsorted(swl, w))
        t = (w - swl[k - 1]) / (swl[k] - swl[k - 1])
        Mp[c, k - 1], Mp[c, k] = 1.0 - t, t
        interp += 1
        gap = max(gap, float(swl[k] - swl[k - 1]))
    return Mp, {"selected": sel, "interpolated": interp, "largest_gap_nm": gap}


def store_problems(version, recipe, n, raw=False) -> list[str]:
    """What the open store ``version`` lacks to serve ``recipe``'s catalogue species at node count ``n``
    (empty: it can).  Checks the top interface (a smooth coat of the recipe's index η, or η = 1),
    the node count n, every species (present, built from the same catalogue entry, flakes in the
    recipe's orientation distribution and at its α), the wavelength range, ``--raw`` (a version built with --raw), and recipe overrides the
    store cannot honour."""
    probs = []
    eta = float(recipe.binder_ior)
    rough = recipe_top_alpha(recipe) > 0
    if any(b.ior != eta for b in recipe.basecoats):
        probs.append(f"the recipe has basecoats of another binder index than η = {eta:g} (an inner interface); store "
                     f"versions serve one binder index: compose without --store")
    st_eta = version.eta_top
    if st_eta is None or abs(float(st_eta) - eta) > 1e-12:
        probs.append(f"top interface: the recipe's binder / coat index is η = {eta:g}, the store version was built "
                     f"for eta_top = {st_eta} ({'plain Radau grid, catalogue binder index' if st_eta is None else 'η'})")
    elif eta != 1.0 and rough != (version.top == "rough"):
        probs.append(f"top interface: the recipe has a {'rough' if rough else 'smooth'} coat, the store version was "
                     f"built for a {version.top} top (its nodes inside the binder differ)")
    if int(n) not in version.resolutions:
        probs.append(f"node count: the solve uses n = {n}, the store has n {version.resolutions}")
    have = set(version.species)
    stored_inputs = version.metadata["inputs"]["species"]
    for p in catalog_species(recipe):
        key = store_key(p)   # the species, or the species with the recipe's films / pigment size (store_key)
        label = repr(p.species) if key == p.species else f"{p.species!r} with the recipe's {_overrides(p)} ({key})"
        if key not in have:
            probs.append(f"species {label} ({p.path}) is not in the store")
            continue
        if not _same_entry(stored_inputs[key], particle_entry(p)):
            probs.append(f"species {label}: the store was built from a different catalogue entry "
                         f"(the catalogue changed since): rebuild")
        if p.is_flake:
            a, d = recipe_alpha(p), recipe_distribution(p)
            have_d = version.distributions(key)
            if d not in have_d:
                probs.append(f"{p.path}: orientation_distribution {d!r} is not in the store: it holds {p.species!r} "
                             f"for the {' and '.join(have_d) or 'no'} distribution(s) only (a version written "
                             f"without distributions holds Beckmann flakes); the kernel depends on the distribution "
                             f"through D(h): add it as a new version with the command below")
            elif not any(abs(a - x) <= 1e-12 for x in version.alphas(key, d)):
                probs.append(f"{p.path}: orientation α = {a:g} is not in the store (it has α "
                             f"{version.alphas(key, d)} for {label}"
                             f"{'' if d == 'beckmann' else f' ({d})'}); the kernel depends on α through D(h): "
                             f"add it as a new version with the command below (projected once, not per compose)")
    if recipe.wavelength_nm is not None:
        try:
            wavelength_map(version.wavelength_nm, recipe.wavelength_nm)
        except ValueError as exc:
            swl = version.wavelength_nm
            probs.append(f"wavelengths: the recipe's grid {recipe.wavelength_nm[0]:g}-{recipe.wavelength_nm[-1]:g} nm "
                         f"has a band the store cannot give ({exc}); the store has {swl.min():g}-{swl.max():g} nm in "
                         f"{swl.size} bands")
    if raw and not version.raw:
        probs.append("--raw: the store version holds truncated factors (build it with --raw)")
    return probs


def store_build_command(version, recipe, n, raw=False) -> str:
    """The `flakedb build` command that makes a version serving ``recipe`` at ``n``."""
    src = recipe.source if recipe.source and not str(recipe.source).startswith("<") else "RECIPE.yaml"
    cmd = [f"flakedb build --recipe {src} "
           f"--store {version.url if version is not None else 'STORE'} --n {n} --eta-top {float(recipe.binder_ior):g}"]
    if raw:
        cmd.append("--raw")
    return " ".join(cmd)


@dataclass
class StoreContext:
    """An open store version checked against a recipe, and how its wavelengths become the paint's
    channels: ``channel_map`` (C, W) = (RGB map @) band selection / interpolation."""

    version: object
    n: int
    raw: bool
    band_map: np.ndarray
    channel_map: np.ndarray
    map_info: dict

    @classmethod
    def for_recipe(cls, version, recipe, n, raw=False):
        probs = store_problems(version, recipe, n, raw)
        if probs:
            raise StoreError(
                f"store {version.url} (version {version.version[:12]}) cannot serve recipe {recipe.name!r} at n = {n}:\n  "
                + "\n  ".join(probs)
                + f"\nthe store has: species {', '.join(version.species)}; n {version.resolutions}; "
                  f"eta_top {version.eta_top}; {len(version.wavelength_nm)} bands "
                  f"{version.wavelength_nm.min():g}-{version.wavelength_nm.max():g} nm; raw (untruncated) "
                  f"{'yes' if version.raw else 'no'}"
                + f"\nto add what is missing: {store_build_command(version, recipe, n, raw)}")
        wl = np.asarray(recipe.wavelength_nm, float)
        band_map, info = wavelength_map(version.wavelength_nm, wl)
        cmap = band_map
        if recipe.mode == "rgb":
            cmap = spectra_to_rgb_matrix(wl).T @ band_map  # (3, W): linear sRGB of the band spectra
        return cls(version, int(n), bool(raw), band_map, cmap, info)

    @classmethod
    def open_for_recipe(cls, url, recipe, n, raw=False):
        """The newest complete version of the store at ``url`` that serves ``recipe`` at ``n`` (``latest``
        first; a store accumulates versions as `flakedb build --recipe` adds what recipes need), as a
        :class:`StoreContext`.  None serving it: the StoreError of ``latest`` (what it lacks, and
        the build command that adds it)."""
        first_error = None
        versions = st.complete_versions(url)
        if not versions:
            st.open_version(url, verify=False)  # raises: no published / no complete version
        for v in versions:
            try:
                version = st.open_version(url, v, verify=False)
                return cls.for_recipe(version, recipe, n, raw)
            except StoreError as exc:
                first_error = first_error or exc
        raise first_error

    def prefixes(self, recipe) -> list[str]:
        """The store paths this recipe reads (what compose verifies)."""
        out = [f"grid/n{self.n}/"]
        for p in catalog_species(recipe):
            out.append(self.version.flake_prefix(store_key(p), self.n, recipe_alpha(p), recipe_distribution(p)) + "/"
                       if p.is_flake else f"species/{store_key(p)}/")
        return out

    def flake_medium(self, species, alpha, a_rho, opaque=False, distribution="beckmann"):
        """A :class:`flakedb.rt.scattering.stored.StoredFlakeMedium` of the species at the recipe's α, orientation
        distribution and loading."""
        return StoredFlakeMedium(self.version.flake_factors(species, self.n, alpha, distribution), float(a_rho),
                                 self.channel_map, bool(opaque))

    def pigment(self, species) -> dict:
        """The pigment's stored Mie optics at the recipe's bands (selected / interpolated, not RGB-mapped)."""
        d = self.version.pigment(species)
        B = self.band_map
        return {"c_ext_um2": B @ d["c_ext_um2"], "c_sca_um2": B @ d["c_sca_um2"],
                "mean_volume_um3": float(np.mean(d["mean_volume_um3"])),
                "legendre_moments": B @ d["legendre_moments"],
                "source": f"store {self.version.url} version {self.version.version[:12]} {species}"}

    def record(self) -> dict:
        """What the outputs record of the store."""
        return {"url": self.version.url, "version": self.version.version, "raw": self.raw, "n": self.n,
                "bands": self.map_info}
