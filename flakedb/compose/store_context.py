"""An open store version checked against a recipe: what it lacks (:func:`store_problems`), the
`flakedb build` command that adds it, and how its bands become the paint's channels
(:class:`StoreContext`, handed to :func:`flakedb.paint.mapping.build_paint`)."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from flakedb.colour.colorimetry import spectra_to_rgb_matrix
from flakedb.paint.mapping import catalog_species
from flakedb.store.versions import StoreError


def _same_entry(a, b) -> bool:
    norm = lambda e: json.loads(json.dumps(e, sort_keys=True, default=float))
    return norm(a) == norm(b)


def store_problems(version, recipe, n, raw=False) -> list[str]:
    """What the open store ``version`` lacks to serve ``recipe``'s catalogue species at node count ``n``
    (empty: it can).  Checks the top interface (a smooth coat of the recipe's index η, or η = 1),
    the resolution n, every species (present, and built from the same catalogue entry), the
    wavelengths, the raw samples when ``raw``, and recipe overrides the store cannot honour."""
    probs = []
    eta = float(recipe.binder_ior)
    cc = recipe.clearcoat
    if eta != 1.0 and cc is not None and cc.roughness > 0:
        probs.append(f"the recipe has a rough coat (roughness {cc.roughness:g}); store versions serve smooth coats "
                     f"and index-matched stacks only: compose without --store")
    st_eta = version.eta_top
    if st_eta is None or abs(float(st_eta) - eta) > 1e-12:
        probs.append(f"top interface: the recipe's binder / coat index is η = {eta:g}, the store version was built "
                     f"for eta_top = {st_eta} ({'plain Radau grid, catalogue binder index' if st_eta is None else 'η'})")
    if not any(nn == n for nn, _ in version.resolutions):
        probs.append(f"node count: the solve uses n = {n}, the store has (n, m) = {version.resolutions}")
    have = set(version.species)
    stored_inputs = version.metadata["inputs"]["species"]
    for p in catalog_species(recipe):
        if p.species not in have:
            probs.append(f"species {p.species!r} ({p.path}) is not in the store")
        elif not _same_entry(stored_inputs[p.species], p.entry):
            probs.append(f"species {p.species!r}: the store was built from a different catalogue entry "
                         f"(the catalogue changed since): rebuild")
        if p.kind == "pigment" and (p.median_diameter_um is not None or p.gsd is not None):
            probs.append(f"{p.path}: the recipe overrides the pigment's size distribution; the store holds the "
                         f"catalogue's: compose without --store")
    if recipe.wavelength_nm is not None:
        swl = np.asarray(version.wavelength_nm, float)
        miss = [float(w) for w in recipe.wavelength_nm if not np.any(np.abs(swl - w) <= 1e-9)]
        if miss:
            probs.append(f"wavelengths: the recipe's grid {recipe.wavelength_nm[0]:g}-{recipe.wavelength_nm[-1]:g} nm has "
                         f"{len(miss)} band(s) the store lacks (e.g. {miss[0]:g} nm); the store has "
                         f"{swl.min():g}-{swl.max():g} nm in {swl.size} bands")
    if raw and not version.metadata["inputs"]["store_raw"]:
        probs.append("--raw: the store version holds only the compressed factors (build it with --raw)")
    return probs


def store_build_command(version, recipe, n, raw=False) -> str:
    """The `flakedb build` command that makes a version serving ``recipe`` at ``n``."""
    wl = recipe.wavelength_nm
    names = sorted({p.species for p in catalog_species(recipe)})
    cmd = [f"flakedb build --store {version.url if version is not None else 'STORE'} --n {n} --eta-top {float(recipe.binder_ior):g}"]
    if wl is not None and len(wl) > 1:
        cmd.append(f"--range-nm {wl[0]:g} {wl[-1]:g} --step-nm {wl[1] - wl[0]:g}")
    cmd += [f"--species {s}" for s in names]
    if raw:
        cmd.append("--raw")
    return " ".join(cmd)


@dataclass
class StoreContext:
    """An open store version checked against a recipe, and how its bands become the paint's channels."""

    version: object
    n: int
    raw: bool
    channel_index: np.ndarray
    channel_map: np.ndarray | None

    @classmethod
    def for_recipe(cls, version, recipe, n, raw=False):
        probs = store_problems(version, recipe, n, raw)
        if probs:
            raise StoreError(
                f"store {version.url} (version {version.version[:12]}) cannot serve recipe {recipe.name!r} at n = {n}:\n  "
                + "\n  ".join(probs)
                + f"\nthe store has: species {', '.join(version.species)}; (n, m) {version.resolutions}; "
                  f"eta_top {version.eta_top}; {len(version.wavelength_nm)} bands "
                  f"{version.wavelength_nm.min():g}-{version.wavelength_nm.max():g} nm; raw samples "
                  f"{'yes' if version.metadata['inputs']['store_raw'] else 'no'}"
                + f"\nto add what is missing: {store_build_command(version, recipe, n, raw)}")
        swl = np.asarray(version.wavelength_nm, float)
        wl = np.asarray(recipe.wavelength_nm, float)
        idx = np.array([int(np.argmin(np.abs(swl - w))) for w in wl])
        cmap = None
        if recipe.mode == "rgb":
            cmap = spectra_to_rgb_matrix(wl)  # (W, 3): spectra @ cmap = linear sRGB (the map is linear)
        return cls(version, int(n), bool(raw), idx, cmap)

    def reflectance(self, species, weights=None):
        """The species' stored R series in the paint's channels (:meth:`StoreVersion.stored_reflectance`)."""
        return self.version.stored_reflectance(species, self.n, raw=self.raw, channel_index=self.channel_index,
                                        channel_map=self.channel_map, weights=weights)

    def record(self) -> dict:
        """What the outputs record of the store."""
        return {"url": self.version.url, "version": self.version.version, "raw": self.raw, "n": self.n}
