"""Catalogue tinters from a relative two-constant Kubelka–Munk database (catalog/tinters/).

A two-constant KM database of artist paints (the RIT/Golden one in catalog/tinters/README.md) gives
each paint's K(λ) and S(λ) relative to its white paint's S (S_white ≡ 1 per band), per unit *paint*,
not per unit pigment.  Two numbers make them the per-unit-volume-fraction optics of a ``tinter``:

* the white's absolute S: the catalogue white (``reference.species``) at the white paint's pigment
  volume fraction, from its Mie optics (σ_s, σ_a, g per unit volume fraction) through
  :func:`flakedb.optics.kubelka_munk.rt_to_km`, so that a flakedb let-down of the new tinter with
  that white mixes as the database's ladders did;
* each coloured paint's pigment volume fraction φ_P: σ/φ = km_to_rt(K_rel · S_ref, S_rel · S_ref, g) / φ_P
  (:func:`flakedb.optics.kubelka_munk.relative_km_to_specific`), by the conversion ``palette.yaml`` names
  (``conversion``; "R-inf-matched" asks the solver for R∞: :func:`semi_infinite_albedo`).

The file ``palette.yaml`` beside the table holds those numbers, g and every source; this module only
computes.  Tables end where the data end unless ``extend_to_nm`` says otherwise (then the last
measured band is held: the file states why and what it costs).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from flakedb.optics.kubelka_munk import relative_km_to_specific, rt_to_km
from flakedb.rt.scattering.media import PhaseMedium
from flakedb.rt.adding.stack import Slab, SolverSettings, solve_stack
from flakedb.paint.catalog import get_species
from flakedb.paint.species import binder_index, pigment_optics
from flakedb.resources import CATALOG_DIR

#: The palette description and its relative KM table (both in the package catalogue).
PALETTE_FILE = CATALOG_DIR / "tinters" / "palette.yaml"


def read_km_table(path: Path) -> tuple[np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """(wavelength_nm (W,), {paint: (K_rel (W,), S_rel (W,))}) from a CSV with columns
    ``wavelength_nm, K_<paint>, S_<paint>, ...``.  The shipped database is relative to its white: S of the
    white paint is 1 at every wavelength.

    >>> from flakedb.resources import CATALOG_DIR
    >>> wl, paints = read_km_table(CATALOG_DIR / "tinters" / "rit-golden-heavy-body-km.csv")
    >>> float(wl[0]), len(paints), bool(np.allclose(paints["TitaniumWhite"][1], 1.0))
    (380.0, 9, True)
    """
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    head, data = rows[0], np.array(rows[1:], dtype=float)
    cols = {h: data[:, i] for i, h in enumerate(head)}
    paints = [h[2:] for h in head if h.startswith("K_")]
    return cols["wavelength_nm"], {p: (cols[f"K_{p}"], cols[f"S_{p}"]) for p in paints}


def reference_scattering_km(catalog: dict, species: str, volume_fraction: float,
                            wavelength_nm) -> np.ndarray:
    """Absolute KM S [1/µm] of a paint of the catalogue pigment ``species`` at ``volume_fraction``:
    S = ¾ σ_s (1 − g) − ¼ σ_a with σ = φ · C / v̄ from its Mie optics (Star 1988; flakedb.optics.kubelka_munk)."""
    wl = np.asarray(wavelength_nm, dtype=float)
    p = pigment_optics(get_species(species, catalog), wl, binder_index(catalog, wl))
    sigma_s = volume_fraction * p.c_sca_um2 / p.mean_volume_um3
    sigma_a = volume_fraction * (p.c_ext_um2 - p.c_sca_um2) / p.mean_volume_um3
    return rt_to_km(sigma_a, sigma_s, p.g)[1]


#: σ_s/σ_a grid of the R∞ table (0, then 10^-4 … 10^5: R∞ up to 0.9919 at g 0.2, above every tinter's KM R∞) and
#: the solver's optical depth of "semi-infinite": at τ 2000, 8000 and 32000 R∞ agrees to the last bit at
#: q ≤ 10^5 (measured; the diffusion length is 1/√(3 σ_a σ_s(1 − g)) ≈ 200 there).
R_INF_RATIOS = np.concatenate([[0.0], np.logspace(-4.0, 5.0, 181)])
R_INF_DEPTH = 2000.0


def semi_infinite_albedo(g, ratios=R_INF_RATIOS, n=32):
    """(ratios, R∞) of an index-matched, optically thick (τ = :data:`R_INF_DEPTH`) HG medium of mean cosine
    ``g``: the hemispherical reflectance under uniform diffuse illumination, Σ_i μ_i w_i A(μ_i) / Σ_i μ_i w_i,
    for σ_s/σ_a = ``ratios`` (the adding-doubling solver at ``n`` nodes); increasing in the ratio.

    >>> q, R = semi_infinite_albedo(0.2, np.array([0.0, 1.0, 1e6]))
    >>> float(R[0]), bool(0.05 < R[1] < 0.2), bool(R[2] > 0.99)
    (0.0, True, True)
    """
    q = np.asarray(ratios, dtype=float)
    omega = q / (1.0 + q)
    med = PhaseMedium(np.ones(q.size), omega, ("hg", float(g)))
    st = solve_stack(None, [Slab(R_INF_DEPTH, med)], None, SolverSettings.product(n), channels=q.size)
    wx = st.w * st.x
    return q, (st.albedo() * wx).sum(axis=1) / wx.sum()


def palette_tables(palette: dict, catalog: dict, table_dir: Path) -> dict[str, dict]:
    """{species: {"wavelength_nm", "sigma_a_per_um", "sigma_s_per_um", "asymmetry_g"}} for every
    species of ``palette`` (the parsed palette.yaml), computed as the module docstring says."""
    wl, km = read_km_table(table_dir / palette["table"])
    ref = palette["reference"]
    S_ref = reference_scattering_km(catalog, ref["species"], float(ref["volume_fraction"]["value"]), wl)
    method = palette.get("conversion", {}).get("value", "Star1988")
    out = {}
    tables = {}  # the solver's R∞ table per g: one solve serves every species of that g
    for name, sp in palette["species"].items():
        K, S = km[sp["column"]]
        g = float(sp["asymmetry_g"]["value"])
        if method == "R-inf-matched" and g not in tables:
            tables[g] = semi_infinite_albedo(g)
        table = tables.get(g)
        a, s = relative_km_to_specific(K, S, S_ref, float(sp["pigment_volume_fraction"]["value"]), g,
                                       method=method, r_inf_table=table)
        w = wl
        top = palette.get("extend_to_nm")
        if top is not None and top > wl[-1]:   # hold the last measured band (palette.yaml says why)
            step = wl[-1] - wl[-2]
            extra = np.arange(wl[-1] + step, top + 0.5 * step, step)
            w = np.concatenate([wl, extra])
            a = np.concatenate([a, np.full(extra.shape, a[-1])])
            s = np.concatenate([s, np.full(extra.shape, s[-1])])
        out[name] = {"wavelength_nm": w, "sigma_a_per_um": a, "sigma_s_per_um": s, "asymmetry_g": g}
    return out


__all__ = ["PALETTE_FILE", "R_INF_DEPTH", "R_INF_RATIOS", "palette_tables", "read_km_table",
           "reference_scattering_km", "semi_infinite_albedo"]
